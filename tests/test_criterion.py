"""The drift criterion (rig.planning.criterion) on synthetic block means, and its settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.config import DEFAULT_RIG_CONFIG, ConfigError, load_rig_config
from rig.planning.criterion import DriftCriterion, bias_bound, window_drift

NOISE = {"stroke_mm": 0.01, "force_N": 2.0, "pressure_bar": 0.003}
CRITERION = DriftCriterion(10.0, 12, 120.0, NOISE)
SAMPLES = 10_000          # per 5 s block at 2 kHz


def decay(ratio: float, amplitude: np.ndarray, blocks: int) -> np.ndarray:
    k = np.arange(blocks)[:, None]
    return np.array([133.0, 900.0, 20.0]) + amplitude * ratio**k


def window_mean(ratio: float, blocks: float) -> float:
    """Mean of r^x over the window, x from the last block's centre (in blocks)."""
    return math.sqrt(ratio) * (1 - ratio**blocks) / (blocks * -math.log(ratio))


def test_the_fit_finds_the_decay_and_predicts_the_departure_over_the_window():
    amplitude = np.array([0.0, 40.0, 0.08])
    means = decay(0.74, amplitude, 12)
    r, drift, upper = window_drift(means, np.array([1e-4, 0.02, 3e-5]), 0.3)
    assert r == pytest.approx(0.74, abs=0.005)
    left = amplitude * 0.74**11                       # departure at the last block
    assert drift == pytest.approx(left * window_mean(0.74, 0.3), rel=0.05, abs=1e-9)  # r on a grid
    assert np.all(upper >= np.abs(drift))


def test_the_bound_falls_as_the_decay_goes_on_and_passes_below_the_fraction():
    amplitude = np.array([0.0, 40.0, 0.08])
    bounds = [bias_bound(CRITERION, tuple(NOISE), decay(0.88, amplitude, n), 5.0, SAMPLES, 0.3).bias_sigma
              for n in range(8, 120, 8)]
    assert all(b > a for a, b in zip(bounds[1:], bounds[:-1], strict=True))
    assert bounds[0] > 10 * CRITERION.fraction and bounds[-1] < CRITERION.fraction


def test_noise_alone_passes_but_a_drift_hidden_in_it_does_not():
    rng = np.random.default_rng(3)
    std = np.array([NOISE[c] for c in NOISE]) / math.sqrt(SAMPLES)
    passed = [bias_bound(CRITERION, tuple(NOISE), decay(0.5, 0.0, 12) + std * rng.standard_normal((12, 3)),
                         5.0, SAMPLES, 0.3).bias_sigma < CRITERION.fraction for _ in range(40)]
    assert np.mean(passed) > 0.8
    # A slow relaxation that departs over the window by twice the tolerance, behind the
    # same noise: never taken for settled.
    tolerance = CRITERION.fraction * NOISE["pressure_bar"] / math.sqrt(0.3 * SAMPLES)
    amplitude = 2 * tolerance / (0.95**11 * window_mean(0.95, 0.3))    # τ ≈ 100 s, within the one looked for
    for _ in range(20):
        slow = decay(0.95, np.array([0.0, 0.0, amplitude]), 12) + std * rng.standard_normal((12, 3))
        assert bias_bound(CRITERION, tuple(NOISE), slow, 5.0, SAMPLES, 0.3).bias_sigma > CRITERION.fraction


def test_a_tail_slower_than_the_first_blocks_is_not_read_as_settled():
    """A large transient: its first blocks fall fast (0.5 a block), its tail at the gas's
    own pace (0.8, what the model predicts).  Fitted freely, the fast start sets r and the
    tail passes as settled; within the model's range of time constants it does not."""
    rng = np.random.default_rng(5)
    std = np.array([NOISE[c] for c in NOISE]) / math.sqrt(SAMPLES)
    k = np.arange(20.0)
    fast_then_slow = np.where(k < 10, 0.5**k, 0.5**10 * 0.8 ** (k - 10))[:, None] * np.array([0.0, 400.0, 0.8])
    means = fast_then_slow + std * rng.standard_normal((20, 3))
    tau = -5.0 / math.log(0.8)
    criterion = DriftCriterion(2.0, 40, 120.0, NOISE, model_time_constant_factor=2.0)
    free = DriftCriterion(2.0, 40, 120.0, NOISE)
    bounded = bias_bound(criterion, tuple(NOISE), means, 5.0, SAMPLES, 3.0, tau)
    assert bounded.bias_sigma > 3 * criterion.fraction and bounded.ratio >= math.exp(-5.0 / (tau / 2)) - 1e-3
    assert bias_bound(free, tuple(NOISE), means, 5.0, SAMPLES, 3.0).bias_sigma < free.fraction


def test_blocks_noisier_than_stated_widen_the_errors():
    rng = np.random.default_rng(4)
    std = np.array([NOISE[c] for c in NOISE]) / math.sqrt(SAMPLES)
    quiet = decay(0.8, 0.0, 12) + std * rng.standard_normal((12, 3))
    noisy = decay(0.8, 0.0, 12) + 10 * std * rng.standard_normal((12, 3))

    def bound(means: np.ndarray) -> float:
        return float(np.linalg.norm(window_drift(means, std, 0.3)[2] / std))

    assert bound(noisy) > 3 * bound(quiet)


def test_default_config_selects_the_drift_criterion_in_one_line_and_bad_settings_get_one_line(tmp_path):
    assert load_rig_config().steady_state.criterion == "drift"
    text = DEFAULT_RIG_CONFIG.read_text()
    path = tmp_path / "drift.toml"
    path.write_text(text)
    ss = load_rig_config(path).steady_state
    assert ss.criterion == "drift" and ss.drift is not None and set(ss.drift.noise) == set(NOISE)
    for old, new, message in [('criterion = "drift"', 'criterion = "slow"', "criterion 'slow' is not one of"),
                              ("drift_fit_cycles = 40", "drift_fit_cycles = 2", "drift_fit_cycles at least 4"),
                              ("drift_sigma_fraction =", "sigma_fraction =", "missing key 'drift_sigma_fraction'")]:
        path = tmp_path / "rig.toml"
        path.write_text(text.replace(old, new))
        with pytest.raises(ConfigError, match=message):
            load_rig_config(path)
    path.write_text(text.replace('criterion = "drift"', 'criterion = "change"'))
    assert load_rig_config(path).steady_state.criterion == "change"
