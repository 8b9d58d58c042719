"""The simulated damper's true parameters, from a file in the identify START.json format,
optionally a production unit (:mod:`simulator.units`) of the nominal damper."""

from __future__ import annotations

import json
from pathlib import Path

from identify.model import load_model
from identify.parameters import Parameters
from simulator.physics import Damper, TruthError
from simulator.units import unit_parameters


def load_truth(path: str | Path | None = None, model: str = "2dof", unit: str | None = None,
               unit_seed: int = 0) -> Damper:
    """Damper with the parameters of ``path`` (START.json, RESULT.json or flat JSON);
    missing parameters, or all of them without a file, take the nominal column, or with
    ``unit`` that production unit's values.  A parameter the file names overrides the
    unit's.  A file the simulator cannot honour raises ParameterError or TruthError (both
    ValueError), one line naming the file."""
    compiled = load_model(model)
    params = Parameters.from_file(compiled, path) if path else Parameters(compiled)
    theta = params.as_dict()
    if unit is not None:
        given = _named_in_file(path, params) if path else set()
        produced = unit_parameters(unit, unit_seed, Parameters(compiled).as_dict())
        theta = {k: theta[k] if k in given else v for k, v in produced.items()}
    try:
        return Damper(theta, model)
    except TruthError as exc:
        raise TruthError(f"{path or f'unit {unit!r}'}: {exc}") from None


def _named_in_file(path: str | Path, params: Parameters) -> set[str]:
    """Stable names of the parameters the (already validated) file sets."""
    doc = json.loads(Path(path).read_text())
    body = doc.get("parameters", doc if "model" not in doc else {})
    return {params[k].name for k in body if k not in ("model", "format")}


def truth_document(damper: Damper) -> dict:
    """START.json form of a damper's parameters."""
    return {"model": damper.model, "parameters": dict(damper.theta)}
