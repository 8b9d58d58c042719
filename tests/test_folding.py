"""Folding onto the phase grid: values, and the noise covariance the estimator relies on."""

from __future__ import annotations

import numpy as np

from identify.folding import fold

N = 800


def _record(frequency_hz: float, rate_hz: float, periods: float, t0: float = 0.0) -> np.ndarray:
    return t0 + np.arange(int(periods * rate_hz / frequency_hz)) / rate_hz


def test_grid_values_interpolate_the_bin_means_at_their_mean_phases():
    t = _record(0.5, 997.0, 2.3, t0=1.1)  # not a whole number of samples per period
    v = np.sin(2 * np.pi * 0.5 * t) + np.random.default_rng(0).standard_normal(len(t))
    pos = np.mod(t * 0.5, 1.0) * N
    b = np.floor(pos + 0.5).astype(int)
    off = pos - b
    b %= N
    counts = np.bincount(b, minlength=N)
    filled = counts > 0
    xp = np.arange(N)[filled] + np.bincount(b, weights=off, minlength=N)[filled] / counts[filled]
    fp = np.bincount(b, weights=v, minlength=N)[filled] / counts[filled]
    expected = np.interp(np.arange(N, dtype=float), xp, fp, period=N)
    assert np.allclose(fold("x", t, {"v": v}, 0.5, N).values["v"], expected, rtol=0, atol=1e-12)


def test_grid_noise_covariance_is_that_of_folded_white_noise():
    """2 Hz at 1 kHz over 3 periods: 500 of 800 bins hold 3 samples, the rest are
    interpolated.  The mean variance of a grid value is 0.224 σ², not mean(1/count) =
    0.583 σ², and neighbouring values share noise as F·Fᵀ says."""
    t = _record(2.0, 1000.0, 3)
    rec = fold("x", t, {"v": np.zeros(len(t))}, 2.0, N)
    assert abs(rec.grid_factor - 0.224) < 1e-3
    rng = np.random.default_rng(1)
    draws = np.array([fold("x", t, {"v": rng.standard_normal(len(t))}, 2.0, N).values["v"] for _ in range(600)])
    assert abs(np.mean(np.var(draws, axis=0)) / rec.grid_factor - 1) < 0.02
    x = rng.standard_normal((N, 3))  # a few directions on the grid: xᵀ·Cov·x = ‖Fᵀx‖²
    predicted = np.sum(rec.noise_factor_t(x) ** 2, axis=0)
    measured = np.var(draws @ x, axis=0)
    assert np.all(np.abs(measured / predicted - 1) < 0.2)  # 600 draws: ±6 % (1σ)


def test_noise_factor_and_its_transpose_are_adjoint():
    t = _record(1.0, 1000.0, 3)
    rec = fold("x", t, {"v": np.zeros(len(t))}, 1.0, N)
    rng = np.random.default_rng(2)
    z = rng.standard_normal((2, len(rec.filled_counts), 4))
    x = rng.standard_normal((2, N, 4))
    assert np.allclose(np.sum(rec.noise_factor(z) * x), np.sum(z * rec.noise_factor_t(x)))


def test_lost_samples_leave_the_noise_estimate_and_grid_as_they_were():
    """0.04 Hz at 2 kHz, 62.5 samples per bin, with a sharp (friction-like) edge and 1.6 %
    of the rows absent as the rig loses them: single samples and bursts.  The noise is
    still read from samples one period apart, paired by their index on the sample grid;
    by row, or from the scatter about the folded curve, it read 20 times too high."""
    rate, f = 2000.0, 0.04
    t_all = 76.5 + np.arange(int(3 * rate / f)) / rate
    rng = np.random.default_rng(3)
    signal = 100 * np.sin(2 * np.pi * f * t_all) + 5 * np.arctan(2000 * np.cos(2 * np.pi * f * t_all))
    v_all = signal + 0.01 * rng.standard_normal(len(t_all))
    lost = np.zeros(len(t_all), dtype=bool)
    for start in rng.choice(len(t_all) - 40, 120, replace=False):
        lost[start:start + rng.integers(1, 40)] = True
    assert 0.01 < lost.mean() < 0.03
    full = fold("x", t_all, {"v": v_all}, f, N)
    holed = fold("x", t_all[~lost], {"v": v_all[~lost]}, f, N, sample_rate_hz=rate)
    assert abs(full.noise_std["v"] / 0.01 - 1) < 0.02
    assert abs(holed.noise_std["v"] / full.noise_std["v"] - 1) < 0.02
    assert abs(holed.periods - 3.0) < 1e-9
    assert np.max(np.abs(holed.values["v"] - full.values["v"])) < 0.02   # a few σ of a grid value
