"""Fits the GUI runs on stored sessions (no Qt here): a re-fit with another model or
start file, and the 1-dof/2-dof comparison of ``identify compare`` (both on the stroke,
1-dof estimating θ5, θ6, θ7), each from the session's files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from identify.dataset import read_dataset, read_manifest
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.preparation import model_columns, resolve_outputs
from identify.result import FitResult

Progress = Callable[[int, float, np.ndarray], None]
ESTIMATE_1DOF = ["theta5", "theta6", "theta7"]


def refit(folder: Path, model_name: str, params_path: str | None, estimate: list[str],
          outputs: list[str] | None = None, progress: Progress | None = None) -> FitResult:
    """Fit the periodic experiments of a dataset folder, as ``identify fit`` does."""
    model = load_model(model_name)
    outputs = resolve_outputs(model, outputs)
    labels = [e.label for e in read_manifest(folder).experiments if e.kind == "periodic"]
    ds = read_dataset(folder, model_columns(model, outputs), labels)
    params = Parameters.from_file(model, params_path) if params_path else Parameters(model)
    return fit_experiments(model, ds.select(labels), params, estimate, outputs=outputs, progress=progress)


def compare_models(folder: Path, estimate_2dof: list[str], params_2dof: str | None,
                   progress: Progress | None = None) -> dict[str, FitResult]:
    """1-dof and 2-dof fitted to the stroke of the same experiments (``identify compare``)."""
    return {"1dof": refit(folder, "1dof", None, ESTIMATE_1DOF, ["stroke_mm"], progress),
            "2dof": refit(folder, "2dof", params_2dof, estimate_2dof, ["stroke_mm"], progress)}
