"""One call from experiments to a fit result: the path ``identify fit`` takes, also used
in memory by the rig right after its last capture (so both give the same numbers)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from identify.dataset import Experiment
from identify.differentiation import Grid
from identify.estimator import Estimator
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.preparation import prepare_periodic, resolve_outputs
from identify.result import FitResult


def fit_experiments(model: CompiledModel, experiments: list[Experiment], params: Parameters, estimate: list[str], *,
                    n: int = 800, scheme: str = "bdf2", outputs: list[str] | None = None, max_iterations: int = 40,
                    progress: Callable[[int, float, np.ndarray], None] | None = None) -> FitResult:
    """Joint Bayesian fit of ``estimate`` over all ``experiments`` (shared parameters).

    ``params`` gives the start values and priors; it is not modified."""
    params = params.copy()
    start = params.as_dict()
    params.set_estimated(estimate)
    outputs = resolve_outputs(model, outputs)
    data = prepare_periodic(model, experiments, n, outputs)
    result = Estimator(model, data, params.copy(), Grid(n, scheme), outputs, max_iterations=max_iterations,
                       progress=progress).fit()
    result.start = {k: start[k] for k in result.estimated}
    result.priors = {k: params[k].prior_std for k in result.estimated}
    return result
