"""A converged periodic solution: what the periodic solver returns and the starts build."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identify.differentiation import Factorization


@dataclass
class PeriodicSolution:
    """A converged periodic solution on the grid (SI units, time derivatives)."""

    label: str
    frequency_hz: float
    inputs: np.ndarray  # (n_inputs, n)
    states: np.ndarray  # (n_states, n)
    dstates: np.ndarray
    ddstates: np.ndarray
    iterations: int
    residual_norm: float  # scaled RMS of the residual equations at the solution
    factorization: Factorization = field(repr=False)
    start: str = "given"  # where Newton started: a name of identify.start.STARTS, or "given" (warm start)
