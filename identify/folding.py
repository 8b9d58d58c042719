"""Folding periodic records onto the n-point phase grid of one period.

The phase of a sample is (time_s · frequency_Hz) mod 1.  Samples are binned around the
grid phases τ_μ = μ/n and averaged over all periods; each bin keeps its mean phase as
well as its mean value, and the grid values are interpolated (periodically, linearly)
from those (phase, value) pairs.  That removes the bias a plain bin average has when a
bin's samples sit off its centre (2 Hz at 2 kHz has 1.25 samples per bin and period),
and fills bins that got no sample.

The period-to-period scatter estimates each channel's measurement noise: where a period
holds a whole number of samples, from differences of samples one period apart (the
signal cancels exactly); otherwise from the scatter around the folded curve, which also
picks up interpolation error where the signal is sharp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FoldedRecord:
    """One periodic record on the grid, in the units of its columns."""

    label: str
    frequency_hz: float
    n: int
    values: dict[str, np.ndarray]  # column -> (n,) grid values
    noise_std: dict[str, float]  # column -> per-sample noise std (nan when not estimable)
    counts: np.ndarray  # samples per bin (n,)
    periods: float  # how many periods the record covers
    samples: int

    def grid_variance(self, column: str) -> float:
        """Mean variance of one grid value of ``column`` from the measurement noise."""
        sigma = self.noise_std[column]
        return float(sigma**2 * np.mean(1.0 / np.maximum(self.counts, 1)))


def _whole_period_lag(t: np.ndarray, frequency_hz: float) -> int:
    """Samples per period when that is a whole number and the record spans two periods or more."""
    dt = (t[-1] - t[0]) / (len(t) - 1)
    per = 1.0 / (frequency_hz * dt)
    lag = int(round(per))
    if lag < 1 or abs(per - lag) > 1e-6 * per or len(t) < 2 * lag:
        return 0
    return lag


def fold(label: str, time_s: np.ndarray, columns: dict[str, np.ndarray], frequency_hz: float, n: int) -> FoldedRecord:
    """Fold sample columns of a periodic record onto ``n`` phases of one period."""
    t = np.asarray(time_s, dtype=float)
    pos = np.mod(t * frequency_hz, 1.0) * n  # position on the grid, in grid steps
    b = np.floor(pos + 0.5).astype(np.int64)
    offset = pos - b  # in [-0.5, 0.5)
    b %= n
    counts = np.bincount(b, minlength=n)
    filled = counts > 0
    mean_offset = np.bincount(b, weights=offset, minlength=n)[filled] / counts[filled]
    xp = np.arange(n)[filled] + mean_offset
    mu = np.arange(n, dtype=float)
    values: dict[str, np.ndarray] = {}
    noise: dict[str, float] = {}
    dof = len(t) - int(filled.sum())
    lag = _whole_period_lag(t, frequency_hz)
    for name, v in columns.items():
        v = np.asarray(v, dtype=float)
        fp = np.bincount(b, weights=v, minlength=n)[filled] / counts[filled]
        grid = np.interp(mu, xp, fp, period=n)
        values[name] = grid
        if lag:
            noise[name] = float(np.sqrt(np.mean((v[lag:] - v[:-lag]) ** 2) / 2))
        elif dof > 0:
            resid = v - np.interp(pos, mu, grid, period=n)
            noise[name] = float(np.sqrt(np.sum(resid**2) / dof))
        else:
            noise[name] = float("nan")
    duration = len(t) * (t[-1] - t[0]) / max(len(t) - 1, 1)
    return FoldedRecord(label, float(frequency_hz), n, values, noise, counts, duration * frequency_hz, len(t))
