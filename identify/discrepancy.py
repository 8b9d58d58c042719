"""Model discrepancy: the part of a prediction's error the parameters' σ cannot cover.

A fitted model's σ says how well the data fix the parameters *of this model*; it says
nothing about how far the model is from the damper.  In the spirit of Kennedy & O'Hagan
(J. R. Stat. Soc. B 63, 2001) the prediction of a quantity y at the conditions of use
is written

    y_true = y_model(θ̂) + δ,    Var = J·C·Jᵀ + σ_δ²

with δ the model discrepancy.  Here σ_δ is taken relative to the predicted quantity and
estimated honestly, from errors on data the fit did **not** see: σ_δ is the root mean
square of relative errors (the maximum-likelihood σ of a zero-mean discrepancy; a bias
counts in it).  Two sources are used:

* held-out shaker experiments (of the standard set, or for a plan that ran them all,
  each group left out of the fit in turn), each giving the larger of its stroke and
  pressure RMS errors relative to the measured swing (half the peak-to-peak).  Both are
  needed: a force-driven prediction pins the pressure to the force (θ4·p balances it),
  so a wrong gas spring shows in the stroke, a wrong area or damping in the pressure;
* a type test of the quantity itself (a drop test of reference units, each relative
  peak error one draw).

The first lies on the shaker's envelope and a drop test outside it (five times the
velocity): whether either σ_δ covers the drop is measured, not assumed
(``benchmarks/bench_drop.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identify.differentiation import Grid
from identify.model import CompiledModel
from identify.periodic import PeriodicSolver
from identify.preparation import PeriodicData


@dataclass(frozen=True)
class Discrepancy:
    """σ_δ relative to the predicted quantity, and what it was estimated from."""

    relative: float
    n_experiments: int
    source: str

    def std(self, value: float) -> float:
        return abs(value) * self.relative

    def to_document(self) -> dict:
        return {"relative": self.relative, "n_experiments": self.n_experiments, "source": self.source}


def relative_output_errors(model: CompiledModel, theta: np.ndarray, data: Sequence[PeriodicData],
                           outputs: Sequence[str], n_grid: int) -> np.ndarray:
    """(experiments, outputs): RMS(ŷ − y) / (half the measured peak-to-peak) of each
    output of each experiment of ``data`` (prepared for ``outputs``), predicted at
    ``theta`` from its measured input."""
    rows = [model.output_index(o) for o in outputs]
    out = []
    for d in data:
        th = d.theta(theta)
        sol = PeriodicSolver(model, Grid(n_grid, "bdf2")).solve(d.inputs, d.frequency_hz, th, label=d.label)
        y = model.output(sol.states, sol.dstates, sol.ddstates, sol.inputs, th)[rows]
        swing = np.ptp(d.measured, axis=1) / 2
        out.append(np.sqrt(np.mean((y - d.measured) ** 2, axis=1)) / swing)
    return np.array(out)


def from_errors(errors: Sequence[float] | np.ndarray, source: str) -> Discrepancy:
    """σ_δ from held-out relative errors: their root mean square."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        raise ValueError("no held-out experiment: a discrepancy needs data the fit did not see")
    return Discrepancy(float(np.sqrt(np.mean(e**2))), int(e.size), source)
