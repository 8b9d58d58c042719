"""The emulated signals obey docs/models.md: the streaming plant behind the protocols, run
in-process on the simulated clock (no wall-clock pacing)."""

from __future__ import annotations

import numpy as np
import pytest

from identify.plans import STANDARD_SET, select
from simulator.daq import FRAME_DTYPE, TcpPort
from simulator.engine import VirtualRig
from simulator.physics import Damper, drop_test
from simulator.sensors import DATASHEET_CHANNELS
from simulator.truth import load_truth

RATE = 2000


def steady_periods(letter: str, periods: int, settle_s: float) -> tuple[np.ndarray, np.ndarray, Damper]:
    """Engineering samples (N, 4) of ``periods`` whole periods after ``settle_s`` of RUN."""
    spec = select(STANDARD_SET, [letter])[0]
    damper = load_truth()
    rig = VirtualRig(damper, TcpPort(), seed=3, modbus_port=0, speed=50)  # speed sizes the DAQ FIFO
    c = rig.controller
    c.write_coils(0, [True])
    c.write_holding(1, [0, int(spec.static_position_mm * 100), int(spec.amplitude_mm * 100),
                        int(round(spec.frequency_hz * 1000)), 20])
    c.write_holding(0, [2])
    rig.step_to(10.0 + settle_s)
    rig.daq.rate_hz = RATE
    rig.daq._handle("START")
    rig.step_to(rig.t + periods / spec.frequency_hz + 0.01)
    frames = np.frombuffer(bytes(rig.daq._out[3:]), dtype=FRAME_DTYPE)
    rig.daq.port.close()
    n = int(round(periods * RATE / spec.frequency_hz))
    counts = frames["counts"][:n].astype(float)
    eng = np.array([ch.offset + ch.gain * counts[:, i] for i, ch in enumerate(DATASHEET_CHANNELS)]).T
    return eng, np.arange(n) / RATE, damper


def fold_si(eng: np.ndarray, periods: int) -> dict[str, np.ndarray]:
    per = len(eng) // periods
    mean = eng[:per * periods].reshape(periods, per, 4).mean(axis=0)
    return {"q": mean[:, 0] * 1e-3, "F": mean[:, 1], "p": mean[:, 2] * 1e5, "T": mean[:, 3] + 273.15}


def smooth_derivatives(x: np.ndarray, frequency_hz: float, harmonics: int = 40) -> tuple[np.ndarray, ...]:
    X = np.fft.rfft(x)
    X[harmonics + 1:] = 0
    k = np.arange(len(X)) * 2 * np.pi * frequency_hz
    return np.fft.irfft(X, len(x)), np.fft.irfft(1j * k * X, len(x)), np.fft.irfft(-k**2 * X, len(x))


@pytest.mark.slow
def test_steady_signals_satisfy_the_model_equations_within_noise():
    spec = select(STANDARD_SET, ["h"])[0]
    eng, _, d = steady_periods("h", 4, 150.0)
    s = fold_si(eng, 4)
    # gas law with the measured stroke and temperature
    p_model = d.pressure(s["q"], s["T"])
    assert np.std(s["p"] - p_model) < 3 * 0.003e5 / 2
    # g1 (inverse dynamics) away from the velocity reversals, where friction's arctan is steep
    q, v, a = smooth_derivatives(s["q"], spec.frequency_hz)
    g1 = s["F"] - (d.theta1 * (a + d.theta2) + d.theta3 * v * np.abs(v) + d.theta4 * s["p"]
                   + (d.theta8 + d.theta9 * s["p"]) * np.arctan(d.theta10 * v) + d.theta11)
    moving = np.abs(v) > 0.005
    assert np.sqrt(np.mean(g1[moving] ** 2)) < 3.0   # N: force noise 2 N / sqrt(4) plus pressure noise
    # g2 over one period (T periodic): compression work equals the heat lost through the wall
    work = np.sum((d.theta4 * s["p"] + d.theta11) * v) * (1 / spec.frequency_hz) / len(v)
    heat = np.sum(d.theta16 * (1 + d.theta6 * s["q"]) * (s["T"] + d.theta17)) * (1 / spec.frequency_hz) / len(v)
    assert work == pytest.approx(heat, rel=0.03)


def loop_area(letter: str, settle_s: float) -> float:
    """∮ p dq of the pressure–stroke loop, normalised by its bounding box."""
    eng, _, _ = steady_periods(letter, 1, settle_s)
    q, p = eng[:, 0], eng[:, 2]
    area = np.sum(0.5 * (p + np.roll(p, 1)) * (q - np.roll(q, 1)))
    return float(area / (np.ptp(p) * np.ptp(q)))


@pytest.mark.slow
def test_heat_loss_loop_at_0_04_hz_and_nearly_adiabatic_at_2_hz():
    slow = loop_area("a", 100.0)
    fast = loop_area("j", 100.0)
    assert slow > 0.01                # paper Fig. 9: a loop of positive area
    assert abs(fast) < 0.2 * slow


def test_drop_test_settles_to_the_static_equilibrium_as_the_gas_cools():
    d = load_truth()
    t = np.linspace(0, 200, 20001)
    s = drop_test(d, 350.0, 0.0, t)
    # static equilibrium at ambient temperature: θ4·p(q) + θ11 = M·g
    dm = Damper(dict(d.theta, theta1=350.0, theta2=-9.81), d.model)
    from scipy.optimize import brentq
    q_static = brentq(lambda q: d.theta4 * dm.pressure(q, d.ambient_k) + d.theta11 - 350 * 9.81, 0.0, 0.3)
    assert s.temperature[-1] == pytest.approx(d.ambient_k, abs=0.05)
    assert s.q[-1] == pytest.approx(q_static, abs=2e-4)
    assert abs(s.q[t.searchsorted(2.0)] - q_static) > 1e-3   # warm gas first, then it cools and sinks
    assert np.max(np.abs(s.velocity)) > 0.1  # a real drop, not a creep
