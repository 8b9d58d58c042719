"""Model discrepancy: the part of a prediction's error the parameters' σ cannot cover.

A fitted model's σ says how well the data fix the parameters *of this model*; it says
nothing about how far the model is from the damper.  In the spirit of Kennedy & O'Hagan
(J. R. Stat. Soc. B 63, 2001) the prediction of a quantity y at the conditions of use
is written

    y_true = y_model(θ̂) + δ,    Var = J·C·Jᵀ + σ_δ²

with δ the model discrepancy.  Here σ_δ is taken relative to the predicted quantity and
estimated honestly: from the model's errors on experiments its fit did **not** see
(held-out experiments of the standard set, or, for a plan that ran them all, each group
of them left out of the fit in turn), measured on the gas pressure, which carries the
gas force θ4·p that dominates a drop test's peak force.  Each held-out experiment gives
one relative error, RMS(p̂ − p)/mean(p); σ_δ is their root mean square (the maximum-
likelihood σ of a zero-mean discrepancy; a bias counts in it).

It is an estimate on the shaker's envelope; a drop test lies outside it (five times the
velocity), so whether σ_δ covers the drop is measured, not assumed
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


def relative_pressure_errors(model: CompiledModel, theta: np.ndarray, data: Sequence[PeriodicData],
                             outputs: Sequence[str], n_grid: int) -> np.ndarray:
    """RMS(p̂ − p)/mean(p) of each experiment of ``data`` (prepared for ``outputs``, which
    include ``pressure_bar``), predicted at ``theta`` from its measured force."""
    row = list(outputs).index("pressure_bar")
    out = []
    for d in data:
        sol = PeriodicSolver(model, Grid(n_grid, "bdf2")).solve(d.inputs, d.frequency_hz, d.theta(theta),
                                                                label=d.label)
        p = model.output(sol.states, sol.dstates, sol.ddstates, sol.inputs, d.theta(theta))[
            model.output_index("pressure_bar")]
        measured = d.measured[row]
        out.append(float(np.sqrt(np.mean((p - measured) ** 2)) / np.mean(measured)))
    return np.array(out)


def from_errors(errors: Sequence[float] | np.ndarray, source: str) -> Discrepancy:
    """σ_δ from held-out relative errors: their root mean square."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        raise ValueError("no held-out experiment: a discrepancy needs data the fit did not see")
    return Discrepancy(float(np.sqrt(np.mean(e**2))), int(e.size), source)
