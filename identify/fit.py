"""One call from experiments to a fit result: the path ``identify fit`` takes, also used
in memory by the rig right after its last capture (so both give the same numbers)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from identify.dataset import Experiment
from identify.differentiation import Grid
from identify.errors import InputError
from identify.estimator import Estimator
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.preparation import prepare_periodic, resolve_outputs
from identify.result import FitResult


def fit_experiments(model: CompiledModel, experiments: list[Experiment], params: Parameters, estimate: list[str], *,
                    n: int = 800, scheme: str = "bdf2", outputs: list[str] | None = None, max_iterations: int = 40,
                    progress: Callable[[int, float, np.ndarray], None] | None = None,
                    fixed: dict[str, dict[int, float]] | None = None, stability: bool = False) -> FitResult:
    """Joint Bayesian fit of ``estimate`` over all ``experiments`` (shared parameters).

    ``params`` gives the start values and priors; it is not modified.  ``fixed`` holds
    per-experiment values of fixed parameters ({label: {parameter index: value}}, e.g.
    friction from :mod:`identify.friction`)."""
    params = params.copy()
    start = params.as_dict()
    params.set_estimated(estimate)
    outputs = resolve_outputs(model, outputs)
    data = prepare_periodic(model, experiments, n, outputs)
    if fixed:
        names = params.names()
        for d in data:
            d.fixed = dict(fixed.get(d.label, {}))
            clash = [names[i] for i in d.fixed if names[i] in estimate]
            if clash:
                raise InputError(f"{', '.join(clash)}: estimated and also fixed per experiment")
    result = Estimator(model, data, params.copy(), Grid(n, scheme), outputs, max_iterations=max_iterations,
                       progress=progress, stability=stability).fit()
    result.start = {k: start[k] for k in result.estimated}
    result.priors = {k: params[k].prior_std for k in result.estimated}
    return result
