"""Folding periodic records onto the n-point phase grid of one period.

The phase of a sample is (time_s · frequency_Hz) mod 1.  Samples are binned around the
grid phases τ_μ = μ/n and averaged over all periods; each bin keeps its mean phase as
well as its mean value, and the grid values are interpolated (periodically, linearly)
from those (phase, value) pairs.  That removes the bias a plain bin average has when a
bin's samples sit off its centre (2 Hz at 2 kHz has 1.25 samples per bin and period),
and fills bins that got no sample.

Folding is linear, grid = L·(bin means), and the record keeps L (two bins per grid
point) and the bin counts: white sample noise of variance σ² reaches the grid with the
covariance σ²·F·Fᵀ, F = L·diag(1/√count).  Interpolated grid values are averages of
neighbouring bins, so their noise is smaller than σ²/count and correlated along the
grid; with few samples per bin (2 Hz at 1 kHz: 3 samples in 500 of 800 bins) that
matters by a factor two and more, and the estimator uses F rather than a per-point
variance.

The period-to-period scatter estimates each channel's measurement noise: where a period
holds a whole number of samples, from differences of samples one period apart (the
signal cancels exactly); otherwise from the scatter around the folded curve, which also
picks up interpolation error where the signal is sharp.  Samples the rig lost leave
holes; pairs are then found by each sample's index on the sample grid, not by its row.
Taken by row, or from the scatter, a 0.04 Hz record with 1.6 % of its samples lost read
a stroke noise 22 times the real one, and the fit's σ grew with it.

A column whose mean drifts (a test machine's table creeping by millimetres over a
record) is not periodic, and folding it would lie: where the samples per period are
nearly whole (87.0, 95.0), each bin collects samples of a few neighbouring periods only,
different bins different ones, and the folded curve zig-zags by the drift (read as
signal up to harmonic 62 and as input noise the size of the signal's derivative).
Where a period holds a whole number of samples, every bin sees every period alike and
a drift only raises the scatter: such records are folded as measured.  Otherwise a
drift is removed before folding: the one-period moving mean of the column (a
sliding average over exactly one period, fractional ends interpolated, which cancels
the periodic part whatever it is) is fitted by a cubic in time over the record, and its
departure from the record's mean subtracted.  The removed range is kept per column
(``drift``), and the fit names it.  A column whose moving mean stays within
DRIFT_FRACTION of its range keeps its samples as measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DRIFT_FRACTION = 0.005  # a moving mean whose range is below this fraction of the column's range is no drift
DRIFT_DEGREE = 3  # the polynomial in time the one-period moving mean is fitted by


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
    interp_bins: np.ndarray  # (2, n) the two filled bins (indices into the filled ones) each grid value comes from
    interp_weights: np.ndarray  # (2, n) their interpolation weights
    drift: dict[str, float]  # column -> range of the drift removed before folding (0: none), column units

    @property
    def filled_counts(self) -> np.ndarray:
        """Sample counts of the bins that got samples, in grid order (m,)."""
        return self.counts[self.counts > 0]

    def noise_factor(self, z: np.ndarray) -> np.ndarray:
        """F·z along axis -2: (…, m, k) independent unit draws per filled bin -> (…, n, k)
        grid noise of a unit-variance white sample noise."""
        z = z / np.sqrt(self.filled_counts)[:, None]
        return self.interp_weights[0][:, None] * z[..., self.interp_bins[0], :] \
            + self.interp_weights[1][:, None] * z[..., self.interp_bins[1], :]

    def noise_factor_t(self, x: np.ndarray) -> np.ndarray:
        """Fᵀ·x along axis -2: (…, n, k) -> (…, m, k); ‖Fᵀx‖² is xᵀ·Cov·x for the grid
        noise of a unit-variance white sample noise."""
        m = len(self.filled_counts)
        moved = np.moveaxis(x, -2, 0)  # (n, …, k)
        columns = moved.reshape(self.n, -1)  # (n, P): every other axis flattened
        P = columns.shape[1]
        # One bincount over both interpolation weights, each grid point's two bins in turn:
        # np.add.at's order (so its sums to the last bit), at a tenth of its cost.
        index = (self.interp_bins.reshape(-1, 1) * P + np.arange(P)).ravel()
        terms = (self.interp_weights.reshape(2, -1, 1) * columns).ravel()
        out = np.bincount(index, terms, minlength=m * P).reshape((m,) + moved.shape[1:])
        return np.moveaxis(out, 0, -2) / np.sqrt(self.filled_counts)[:, None]

    @property
    def grid_factor(self) -> float:
        """Mean variance of one grid value for a unit-variance white sample noise: mean diag(F·Fᵀ)."""
        c = self.filled_counts
        w, b = self.interp_weights, self.interp_bins
        return float(np.mean(w[0] ** 2 / c[b[0]] + w[1] ** 2 / c[b[1]]))


def _period_pairs(t: np.ndarray, frequency_hz: float, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Row indices (i, j) of the samples exactly one period apart, when a period holds a
    whole number of samples and the record spans two periods or more; None otherwise.
    Absent rows (lost samples) are allowed: a sample whose partner was lost is not paired."""
    per = sample_rate_hz / frequency_hz
    lag = int(round(per))
    k = np.rint((t - t[0]) * sample_rate_hz).astype(np.int64)  # index on the sample grid
    if lag < 1 or abs(per - lag) > 1e-6 * per or k[-1] + 1 < 2 * lag:
        return None
    j = np.minimum(np.searchsorted(k, k + lag), len(k) - 1)
    i = np.flatnonzero(k[j] == k + lag)
    return i, j[i]


def detrend(t: np.ndarray, v: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, float]:
    """The column without its drift and the drift's range (module docstring); the column
    unchanged and 0 where it does not drift or spans less than three periods."""
    period = 1.0 / frequency_hz
    if t[-1] - t[0] < 3 * period or v.size < 8:
        return v, 0.0
    # Trapezoidal cumulative integral: the mean over [t - T/2, t + T/2] from its values.
    c = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))))
    inside = (t - t[0] >= period / 2) & (t[-1] - t >= period / 2)
    ti = t[inside]
    moving = (np.interp(ti + period / 2, t, c) - np.interp(ti - period / 2, t, c)) / period
    scale = (t - t.mean()) / max(t[-1] - t[0], 1e-300)
    coeffs = np.polynomial.polynomial.polyfit(scale[inside], moving, DRIFT_DEGREE)
    trend = np.polynomial.polynomial.polyval(scale, coeffs)
    trend -= trend.mean()
    span = float(np.ptp(trend))
    if span <= DRIFT_FRACTION * float(np.ptp(v)):
        return v, 0.0
    return v - trend, span


def _interpolation(xp: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Periodic linear interpolation from increasing points xp in [-0.5, n - 0.5) to the
    grid 0…n-1, as the two source indices and weights per grid point (np.interp's rule)."""
    m = len(xp)
    ext = np.concatenate(([xp[-1] - n], xp, [xp[0] + n]))
    mu = np.arange(n, dtype=float)
    left = np.clip(np.searchsorted(ext, mu, side="right") - 1, 0, m)
    w = (mu - ext[left]) / (ext[left + 1] - ext[left])
    return np.vstack([(left - 1) % m, left % m]), np.vstack([1.0 - w, w])


def fold(label: str, time_s: np.ndarray, columns: dict[str, np.ndarray], frequency_hz: float, n: int,
         sample_rate_hz: float | None = None) -> FoldedRecord:
    """Fold sample columns of a periodic record onto ``n`` phases of one period.

    ``sample_rate_hz`` is the rate of a record with absent rows (lost samples, declared
    in the manifest); without it the rows are taken to be consecutive samples."""
    t = np.asarray(time_s, dtype=float)
    rate = sample_rate_hz or (len(t) - 1) / (t[-1] - t[0])
    pos = np.mod(t * frequency_hz, 1.0) * n  # position on the grid, in grid steps
    b = np.floor(pos + 0.5).astype(np.int64)
    offset = pos - b  # in [-0.5, 0.5)
    b %= n
    counts = np.bincount(b, minlength=n)
    filled = counts > 0
    mean_offset = np.bincount(b, weights=offset, minlength=n)[filled] / counts[filled]
    bins, weights = _interpolation(np.arange(n)[filled] + mean_offset, n)
    values: dict[str, np.ndarray] = {}
    noise: dict[str, float] = {}
    dof = len(t) - int(filled.sum())
    pairs = _period_pairs(t, frequency_hz, rate)
    mu = np.arange(n, dtype=float)
    drift: dict[str, float] = {}
    for name, v in columns.items():
        v = np.asarray(v, dtype=float)
        # With whole samples per period every bin sees every period alike: a drift only
        # raises the scatter there, and such records are folded as measured.
        v, drift[name] = (v, 0.0) if pairs is not None else detrend(t, v, frequency_hz)
        fp = np.bincount(b, weights=v, minlength=n)[filled] / counts[filled]
        grid = weights[0] * fp[bins[0]] + weights[1] * fp[bins[1]]
        values[name] = grid
        if pairs is not None:
            noise[name] = float(np.sqrt(np.mean((v[pairs[1]] - v[pairs[0]]) ** 2) / 2))
        elif dof > 0:
            resid = v - np.interp(pos, mu, grid, period=n)
            noise[name] = float(np.sqrt(np.sum(resid**2) / dof))
        else:
            noise[name] = float("nan")
    duration = t[-1] - t[0] + 1.0 / rate
    return FoldedRecord(label, float(frequency_hz), n, values, noise, counts, duration * frequency_hz, len(t),
                        bins, weights, drift)
