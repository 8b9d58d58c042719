"""Time integration of the plant's states along an imposed stroke, vectorised over a
block of time points.

Each state obeys y' = f(y); along a block the diagonal of ∂f/∂y (finite differences) is
taken at every node and the equation is written y' = −λ(t)·y + g(t, y), g = f + λ·y.
With g frozen at the last iterate, the linear part is integrated exactly over each step
(exponential trapezoid) and the whole block solved as a scan with cumulative products;
the iteration repeats until the block no longer changes, once with λ at the block's
start and once more with λ at the nodes' converged states (λ then depends on each node
alone, not on where a block begins).  Stiff states (the transducer line, ~1 ms) are
thereby exact in their linear part, and a block costs a handful of vectorised
right-hand sides instead of thousands of scalar ones.
Longer stretches are cut into blocks of at most :data:`MAX_BLOCK_POINTS` (the transfer
matrices grow with the square of a block) and :data:`MAX_BLOCK_S` (the iteration
contracts over a short block); a block that does not settle is halved and tried again.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from simulator.plant.damper import PlantDamper

MAX_BLOCK_POINTS = 64
MAX_BLOCK_S = 0.5
MIN_BLOCK_POINTS = 3
STEP_S = 2e-3          # the states' finest grid: the DAQ's 2 kHz reads them interpolated
MAX_ITERATIONS = 40
LAMBDA_PASSES = 2      # the linear part taken at the start, then at the first pass's states
LINEARISED = (0, 1, 2, 3, 4)  # not the void: its rate jumps where it opens
TOLERANCE = 1e-7  # change per iteration, relative to each state's scale (K; mol/n; m³/V0)


class PlantConvergenceError(ArithmeticError):
    """A block whose iteration did not settle: the plant is driven outside its physics."""


def _scales(plant: PlantDamper) -> np.ndarray:
    n = plant.n_total
    return np.array([1.0, 1.0, n, n * 1e-2, 1.0, plant.k.geometry_gas_volume])[:, None]


def integrate_block(plant: PlantDamper, t: np.ndarray, q: np.ndarray, v: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """States (6, len(t)) along the stroke q(t), v(t); ``t[0]`` is the start, y0 there."""
    n = len(t)
    if n == 1:
        return y0[:, None].copy()
    scale = _scales(plant)
    Y = np.repeat(y0[:, None], n, axis=1)
    F = plant.rates(q, v, Y)
    dt = np.diff(t)[None, :]
    for _ in range(LAMBDA_PASSES):
        # The linear part at each node's own state (after a first pass at the block's
        # start), so that the scheme does not depend on where the blocks are cut: offline
        # and served cut the same grid differently.
        lam = _diagonal(plant, q, v, Y, F, scale)
        lam_bar = 0.5 * (lam[:, 1:] + lam[:, :-1])
        x = lam_bar * dt
        alpha = np.exp(-x)
        small = np.abs(x) < 1e-8
        phi = np.where(small, dt, (1 - alpha) / np.where(small, 1.0, lam_bar))
        # y_k = exp(L_k)·y0 + Σ_{j<k} exp(L_k − L_{j+1})·β_j, L = −cumsum(λ̄·dt): a
        # lower-triangular transfer matrix per state, exponents of differences only (no
        # underflowing products to divide by).
        L = np.concatenate([np.zeros((len(y0), 1)), -np.cumsum(x, axis=1)], axis=1)
        expo = L[:, 1:, None] - L[:, None, 1:]
        lower = np.tril(np.ones((n - 1, n - 1), dtype=bool))
        E = np.where(lower, np.exp(np.where(lower, expo, 0.0)), 0.0)
        free = np.exp(L[:, 1:]) * y0[:, None]
        for _ in range(MAX_ITERATIONS):
            G = F + lam * Y
            beta = phi * 0.5 * (G[:, 1:] + G[:, :-1])
            new = np.empty_like(Y)
            new[:, 0] = y0
            new[:, 1:] = free + np.einsum("skj,sj->sk", E, beta)
            new[5] = _reflected(y0[5], plant.void_drive(q, v, Y), dt[0])
            change = float(np.max(np.abs(new - Y) / scale))
            Y = new
            F = plant.rates(q, v, Y)
            if change < TOLERANCE:
                break
        else:
            raise PlantConvergenceError(f"plant states did not settle within {MAX_ITERATIONS} iterations "
                                        f"over {t[0]:.3f}-{t[-1]:.3f} s (change {change:.2g})")
    return Y


def _diagonal(plant: PlantDamper, q: np.ndarray, v: np.ndarray, Y: np.ndarray, F: np.ndarray,
              scale: np.ndarray) -> np.ndarray:
    """−∂f_i/∂y_i at every node (finite differences, all states in one vectorised call)."""
    n, m = Y.shape[1], len(LINEARISED)
    lam = np.zeros_like(Y)
    delta = 1e-6 * scale[list(LINEARISED), 0]
    Yp = np.tile(Y, (1, m))
    for j, i in enumerate(LINEARISED):
        Yp[i, j * n:(j + 1) * n] += delta[j]
    fp = plant.rates(np.tile(q, m), np.tile(v, m), Yp)
    for j, i in enumerate(LINEARISED):
        lam[i] = -(fp[i, j * n:(j + 1) * n] - F[i]) / delta[j]
    return lam


def _reflected(start: float, drive: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """x_k = max(x_{k−1} + Δ_k, 0) for all k at once (the Skorokhod reflection of the
    trapezoid sums S: x = S − min(0, running minimum of S)); the void opens and shuts
    exactly, where an iteration on its switching rate would chatter."""
    S = start + np.concatenate([[0.0], np.cumsum(0.5 * (drive[1:] + drive[:-1]) * dt)])
    return S - np.minimum(0.0, np.minimum.accumulate(S))


def integrate_stroke(plant: PlantDamper, stroke: Callable[[np.ndarray], tuple[np.ndarray, ...]], start_s: float,
                     end_s: float, y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid (every :data:`STEP_S` from ``start_s`` until past ``end_s``) and the
    states on it along ``stroke(t)`` → (q, v, …), from y0 at ``start_s``."""
    grid = start_s + STEP_S * np.arange(int(np.ceil((end_s - start_s) / STEP_S - 1e-9)) + 1)
    q, v = stroke(grid)[:2]
    return grid, integrate(plant, grid, q, v, y0)


def states_at(plant: PlantDamper, nodes_s: np.ndarray, q: np.ndarray, v: np.ndarray, states: np.ndarray,
              times: np.ndarray) -> np.ndarray:
    """The states at ``times`` within the nodes, cubic Hermite on their values and rates
    (linear interpolation's error over a 2 ms node, a quarter of a millibar on a 2 Hz
    experiment's pressure, is what the provisional step of the served rig is not)."""
    rates = plant.rates(q, v, states)
    Y = CubicHermiteSpline(nodes_s, states, rates, axis=1)(times)
    Y[5] = np.maximum(Y[5], 0.0)   # the void is no smooth state: its rate jumps where it opens
    return Y


def integrate(plant: PlantDamper, t: np.ndarray, q: np.ndarray, v: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """States along a stroke of any length, block by block."""
    out = np.empty((len(y0), len(t)))
    out[:, 0] = y0
    start = 0
    while start < len(t) - 1:
        by_time = int(np.searchsorted(t, t[start] + MAX_BLOCK_S * (1 + 1e-9), side="right")) - 1
        stop = min(start + MAX_BLOCK_POINTS - 1, len(t) - 1, max(by_time, start + MIN_BLOCK_POINTS - 1))
        while True:
            try:
                out[:, start:stop + 1] = integrate_block(plant, t[start:stop + 1], q[start:stop + 1],
                                                         v[start:stop + 1], out[:, start])
                break
            except PlantConvergenceError:
                if stop - start < MIN_BLOCK_POINTS:
                    raise
                stop = start + (stop - start) // 2
        start = stop
    return out
