"""The drift criterion: capture once what is left of the thermal transient could not
bias the identification by more than a stated multiple of its standard deviation.

The channel means over blocks of whole cycles (the change criterion's blocks, at least
``block_s``) relax geometrically towards the periodic state, y_k = y∞ + A r^k, all
channels with the one ratio r of the gas temperature (a power of the Floquet
multiplier of the thermal state).  The last ``fit_cycles`` block means are fitted with
that law (r by a search on a grid, y∞ and A linear for each r); the fit predicts D,
each channel's mean departure from the periodic state over the capture window.
Blocks, not single cycles: a decay fast enough to live in the last point alone is the
noise of that point, and a block's noise is √(cycles) smaller.

Why D bounds the bias: a least-squares estimate is linear in the data near the
optimum, θ̂ = θ + Gᵀ(noise + b), with Var θ̂ = σ²|G|² for white noise σ per sample; a
distortion b of the record shifts it by Gᵀb ≤ |G|·|b| (Cauchy–Schwarz), that is by at
most |b|/σ standard deviations of θ̂, whatever the parameter.  A departure D over the N
samples of the window has |b| ≈ |D|·√N.  Summed over the fitted channels, the bound is
z = √Σ_c (D_c √N / σ_c)²; the criterion passes when z, with D at its upper confidence
bound (over the ratios the data allow, |A| + ``GUARD`` standard errors), is below
``fraction``.  The upper bound is what keeps noisy block means (lost samples, a stall)
from passing early: they widen the fit's errors and so delay the capture.

The bound is the worst case, a distortion shaped exactly like a parameter's
sensitivity; a steady offset is far from that shape, so the fraction is calibrated
against identifications on the simulator (benchmarks/bench_session.py), not read as
the bias itself.  The drift alone (the window's end-to-end change) is not enough: a
criterion on it left θ4 and θ6 5-8 σ from the simulator's truth, the offset being what
the fit cannot absorb.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.config import DriftCriterion, SteadyStateCriteria

# Ratios searched for r: dense near 1 (slow relaxations: small gas volume, small wall
# area), where 1 - r spans 1e-4 (a time constant of 10^4 cycles) to 1.
RATIO_GRID = 1.0 - np.geomspace(1e-4, 0.99, 240)
GUARD = 2.0     # standard errors added to the fitted amplitude (one-sided, ~98 %)
# Block means before the law is fitted: three determine y∞, A and r, and the bound
# then takes the worst of every ratio in the model's range, all of them fitting.
MIN_BLOCKS = 3
# The first settling block begins this long after RUN's fade-in: the actuator's lag behind
# its command, which the acquisition skips and the settling prediction starts from.
DAQ_LAG_S = 0.5


@dataclass(frozen=True)
class DriftFit:
    ratio: float                     # fitted r per cycle
    drift: np.ndarray                # predicted mean departure of each channel over the capture window
    bias_sigma: float                # bound on the fit's bias (standard deviations), guard included


def window_drift(means: np.ndarray, mean_std: np.ndarray, window_blocks: float,
                 max_ratio: float = 1.0, min_ratio: float = 0.0) -> tuple[float, np.ndarray, np.ndarray]:
    """Fit y_k = y∞ + A r^k to consecutive block means (K, C), each channel's noise std
    ``mean_std`` (C,), with ``min_ratio`` ≤ r ≤ ``max_ratio`` per block.  Returns the fitted r, each
    channel's mean departure from y∞ over the capture window (``window_blocks`` long,
    right after the last block), and its upper bound: over every r the data do not
    reject (residual within GUARD² of the best), the largest |A| + GUARD standard
    errors.  A slow decay and a constant are nearly the same columns over a few
    blocks, so the best r alone can say "settled" of a decay it cannot see."""
    count, n_channels = means.shape
    k = np.arange(count, dtype=float) - (count - 1)            # 0 at the last block: A is its departure
    y = means / mean_std
    u = RATIO_GRID[:, None] ** k                                # (R, K): the decay's column for each r
    # Normal equations of [1, u] for every r at once (2×2, in closed form).
    s1, su, suu = float(count), u.sum(axis=1), (u * u).sum(axis=1)
    det = s1 * suu - su**2
    ok = (det > 1e-12 * s1 * suu) & (RATIO_GRID <= max_ratio) & (RATIO_GRID >= min_ratio)
    ty, tuy = y.sum(axis=0), u @ y                              # (C,), (R, C)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (s1 * tuy - su[:, None] * ty) / det[:, None]        # amplitude per r and channel
        c = (suu[:, None] * ty - su[:, None] * tuy) / det[:, None]
        residual = ((y[None] - c[:, None, :] - a[:, None, :] * u[:, :, None]) ** 2).sum(axis=(1, 2))
        se_a = np.sqrt(s1 / det)
    residual[~ok] = np.inf
    i = int(np.argmin(residual))
    dof = max(count - 3, 1)
    scale2 = max(float(residual[i]) / (dof * n_channels), 1.0)  # noisier than stated: widen, never narrow
    # A is the departure at the last block's centre: the window begins half a block later
    # and lasts window_blocks; what the fit sees is the window's mean departure from the
    # periodic state (its drift, the end-to-end change, is smaller where r is near 1).
    g = np.sqrt(RATIO_GRID) * (1 - RATIO_GRID**window_blocks) / (window_blocks * -np.log(RATIO_GRID))
    plausible = residual <= residual[i] + GUARD**2 * scale2
    with np.errstate(invalid="ignore"):
        upper = (np.abs(a) + GUARD * math.sqrt(scale2) * se_a[:, None]) * g[:, None]   # (R, C)
    worst = int(np.argmax(np.where(plausible, np.linalg.norm(upper, axis=1), -np.inf)))
    return float(RATIO_GRID[i]), a[i] * g[i] * mean_std, upper[worst] * mean_std


def bias_bound(criterion: DriftCriterion, channels: tuple[str, ...], means: np.ndarray, block_s: float,
               samples_per_block: float, window_blocks: float, model_time_constant_s: float | None = None
               ) -> DriftFit:
    """The criterion on the latest block means (K, len(channels)) of the fitted channels,
    blocks of ``block_s`` seconds (whole cycles), the capture window ``window_blocks`` long;
    ``model_time_constant_s``: the gas's relaxation the damper model predicts."""
    sigma = np.array([criterion.noise[c] for c in channels])
    # A few blocks cannot tell a slow relaxation from a straight line; physics can: no
    # gas relaxes slower than max_time_constant_s, nor much slower than the model says.
    fastest, slowest = criterion.time_constant_range_s(model_time_constant_s)
    r, drift, upper = window_drift(means[-criterion.fit_cycles:], sigma / math.sqrt(samples_per_block),
                                   window_blocks, math.exp(-block_s / slowest),
                                   math.exp(-block_s / fastest) if fastest > 0 else 0.0)
    z = upper * math.sqrt(window_blocks * samples_per_block) / sigma
    return DriftFit(r, drift, float(np.sqrt(np.sum(z**2))))


# ----- the blocks both the acquisition and its prediction (rig.planning.settling) compare -------------------------
def first_block_sample(criteria: SteadyStateCriteria, rate_hz: float) -> int:
    """The sample (counted from RUN and the DAQ's START) at which the first block begins."""
    return math.ceil((criteria.ramp_time_s + DAQ_LAG_S) * rate_hz)


def first_block_s(criteria: SteadyStateCriteria, rate_hz: float) -> float:
    """Time from RUN (and the DAQ's START) to the first comparison block."""
    return first_block_sample(criteria, rate_hz) / rate_hz


def block_cycles(criteria: SteadyStateCriteria, frequency_hz: float) -> int:
    """Whole cycles per comparison block (at least ``block_s``)."""
    return max(1, math.ceil(criteria.block_s * frequency_hz))


def last_block_cycles(criteria: SteadyStateCriteria, m: int) -> int:
    """Cycles at the block where the acquisition gives up (the first at or past max_cycles)."""
    return max(1, math.ceil(criteria.max_cycles / m)) * m


def blocks_bias(drift: DriftCriterion, means: np.ndarray, m: int, frequency_hz: float, samples_per_period: float,
                periods: int, time_constant_s: float | None) -> DriftFit:
    """:func:`bias_bound` on the latest block means of ``m`` cycles each, before a capture
    of ``periods`` cycles."""
    return bias_bound(drift, tuple(drift.noise), means, m / frequency_hz, m * samples_per_period, periods / m,
                      time_constant_s)


def drift_passes(criteria: SteadyStateCriteria, cycles: int, fit: DriftFit) -> bool:
    """The drift criterion, at a block ending ``cycles`` after RUN."""
    assert criteria.drift is not None   # a drift criterion always has its settings (rig.config)
    return cycles >= criteria.min_cycles and fit.bias_sigma < criteria.drift.fraction


def change_passes(criteria: SteadyStateCriteria, cycles: int | np.ndarray, change: np.ndarray,
                  thresholds: np.ndarray) -> np.ndarray:
    """The change criterion: every channel's block-to-block change (last axis) below its
    threshold, at blocks ending ``cycles`` after RUN (NaN, the first block's, fails)."""
    return (np.asarray(cycles) >= criteria.min_cycles) & np.all(change < thresholds, axis=-1)
