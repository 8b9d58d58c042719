"""The simulated damper's true parameters, from a file in the identify START.json format."""

from __future__ import annotations

from pathlib import Path

from identify.model import load_model
from identify.parameters import Parameters
from simulator.physics import Damper, TruthError


def load_truth(path: str | Path | None = None, model: str = "2dof") -> Damper:
    """Damper with the parameters of ``path`` (START.json, RESULT.json or flat JSON);
    missing parameters, or all of them without a file, take the nominal column.  A file
    the simulator cannot honour raises ParameterError or TruthError (both ValueError),
    one line naming the file."""
    compiled = load_model(model)
    params = Parameters.from_file(compiled, path) if path else Parameters(compiled)
    try:
        return Damper(params.as_dict(), model)
    except TruthError as exc:
        raise TruthError(f"{path}: {exc}") from None


def truth_document(damper: Damper) -> dict:
    """START.json form of a damper's parameters."""
    return {"model": damper.model, "parameters": dict(damper.theta)}
