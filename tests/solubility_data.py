"""Data of the dissolving-gas damper (identify/models/solubility_damper.py), made
independently of identify's generated code and periodic solver.

The stroke is imposed exactly (q = static + amplitude·sin(2π f t)); the gas temperature T
and the dissolved gas z are integrated in time with ``solve_ivp`` and their periodic
steady state found by shooting one period with ``fsolve``; pressure from the gas law
p = (θ5 − z)·T/(1 + θ6·q), the axle force from g1 by inverse dynamics.  The sensor chain
(noise, 16-bit quantisation) is the one of ``tests/independent_generator.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve

from tests.independent_generator import CHANNELS, Experiment, write_manifest, write_record
from tests.independent_generator import NOMINAL as NOMINAL_2DOF

NOMINAL: dict[str, float] = dict(NOMINAL_2DOF, theta18=10.0)


def _stroke(e: Experiment, t):
    w = 2 * np.pi * e.frequency_hz
    a = e.amplitude_mm * 1e-3
    s = np.sin(w * t)
    return e.static_position_mm * 1e-3 + a * s, a * w * np.cos(w * t), -a * w * w * s


def _pressure(th: dict[str, float], q, T, z):
    return (th["theta5"] - z) * T / (1 + th["theta6"] * q)


def _rates(th: dict[str, float], e: Experiment, t: float, y: np.ndarray) -> list[float]:
    T, z = y
    q, v, _ = _stroke(e, t)
    p = _pressure(th, q, T, z)
    dT = ((th["theta4"] * p + th["theta11"]) * v - th["theta16"] * (1 + th["theta6"] * q) * (T + th["theta17"])) \
        / th["theta15"]
    return [dT, (th["theta7"] * p - z) / th["theta18"]]


def _integrate(th, e, y0, t_end, dense=False):
    return solve_ivp(lambda t, y: _rates(th, e, t, y), (0.0, t_end), y0, method="DOP853", rtol=1e-11,
                     atol=[1e-9, 1e-9], max_step=1.0 / (400 * e.frequency_hz), dense_output=dense)


def clean_signals(e: Experiment, rate_hz: float, periods: float, th: dict[str, float]) -> pd.DataFrame:
    """Noise-free columns (engineering units) of the periodic steady state from phase 0."""
    period = 1.0 / e.frequency_hz
    ambient = -th["theta17"]
    q0 = e.static_position_mm * 1e-3
    p0 = th["theta5"] * ambient / (1 + th["theta6"] * q0 + th["theta7"] * ambient)
    y0 = fsolve(lambda y: _integrate(th, e, y, period).y[:, -1] - y, [ambient, th["theta7"] * p0], xtol=1e-12)
    t = np.arange(int(np.ceil(periods * rate_hz / e.frequency_hz))) / rate_hz
    T, z = _integrate(th, e, y0, t[-1] + 1.0 / rate_hz, dense=True).sol(t)
    q, v, acc = _stroke(e, t)
    p = _pressure(th, q, T, z)
    fe = (th["theta1"] * (acc + th["theta2"]) + th["theta3"] * v * np.abs(v) + th["theta4"] * p
          + (th["theta8"] + th["theta9"] * p) * np.arctan(th["theta10"] * v) + th["theta11"])
    return pd.DataFrame({"time_s": t, "stroke_mm": (q + th["theta12"]) * 1e3, "force_N": fe,
                         "pressure_bar": p / 1e5, "gas_temperature_C": T - 273.15})


def generate_dataset(out: str | Path, experiments: Sequence[Experiment], *, rate_hz: float = 500.0,
                     periods: float = 3, seed: int = 0, theta: dict[str, float] | None = None) -> Path:
    """Write ``dataset.json`` and one CSV per experiment into ``out``; return ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    th = dict(NOMINAL, **(theta or {}))
    rng = np.random.default_rng(seed)
    entries = []
    for e in experiments:
        clean = clean_signals(e, rate_hz, periods, th)
        cols = {"time_s": clean["time_s"].to_numpy()}
        for ch in CHANNELS:
            cols[ch.column] = ch.measure(clean[ch.column].to_numpy(), rng)
        entries.append(write_record(out, f"sol-{e.letter}", cols, e, rate_hz))
    return write_manifest(out, "dissolving-gas damper generator (tests)", "tests/solubility_data.py", seed, th,
                          entries)
