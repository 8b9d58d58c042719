"""An independent data generator for checking the identification against.

It shares no code with ``simulator/`` nor with ``identify``'s periodic solver: the
2-dof equations of ``shared/spec/models.md`` are written out again here, the stroke is
imposed exactly (q = static + amplitude·sin(2π f t), no actuator dynamics), the gas
temperature is integrated in time with ``solve_ivp`` on a fine step and its periodic
steady state found by shooting on one period with ``brentq``, the pressure follows from
the gas law and the axle force from g1 by inverse dynamics.  Each channel gets its own
white noise and 16-bit quantisation with the rig's datasheet figures, and the dataset is
written with pandas and json in the interchange format (dataset-format.md).

A bug shared by the simulator and ``identify`` (both read the same spec, but one team
wrote them) cannot cancel against this one, and the simulator's actuator model and
sensor chain are absent, which keeps this a check of the identification alone.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

# models.md, "nominal" column, SI.
NOMINAL: dict[str, float] = {
    "theta1": 20.0, "theta2": 9.81, "theta3": 5.0e3, "theta4": 5.0e-3, "theta5": 2166.7, "theta6": -3.0,
    "theta7": 2.0e-4, "theta8": 80.0, "theta9": 4.0e-5, "theta10": 2000.0, "theta11": -506.6,
    "theta12": 0.0, "theta15": 8.5, "theta16": 0.85, "theta17": -293.15,
}


@dataclass(frozen=True)
class AdcChannel:
    """One DAQ channel: white transducer noise, then a 16-bit converter
    (engineering = offset + resolution·counts, counts in [-32768, 32767])."""

    column: str
    noise_std: float
    resolution: float
    offset: float

    def measure(self, value: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        noisy = value + self.noise_std * rng.standard_normal(value.shape)
        counts = np.clip(np.rint((noisy - self.offset) / self.resolution), -32768, 32767)
        return self.offset + self.resolution * counts


# The rig's datasheet figures; offsets centre each range on the signals a damper gives.
CHANNELS: tuple[AdcChannel, ...] = (
    AdcChannel("stroke_mm", 0.01, 0.005, 140.0),
    AdcChannel("force_N", 2.0, 1.0, 0.0),
    AdcChannel("pressure_bar", 0.003, 0.001, 32.768),
    AdcChannel("gas_temperature_C", 0.02, 0.005, 50.0),
)


class Experiment(Protocol):
    """A displacement-controlled sine experiment, as a plan states it (mm, Hz; hashable,
    e.g. ``identify.plans.ExperimentSpec``, whose numbers are data, not code)."""

    @property
    def letter(self) -> str: ...

    @property
    def static_position_mm(self) -> float: ...

    @property
    def amplitude_mm(self) -> float: ...

    @property
    def frequency_hz(self) -> float: ...

    def __hash__(self) -> int: ...


def _stroke(e: Experiment, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = 2 * np.pi * e.frequency_hz
    a = e.amplitude_mm * 1e-3
    s = np.sin(w * t)
    return e.static_position_mm * 1e-3 + a * s, a * w * np.cos(w * t), -a * w * w * s


def _pressure(th: dict[str, float], q: np.ndarray, T: np.ndarray) -> np.ndarray:
    return th["theta5"] * T / (1 + th["theta6"] * q + th["theta7"] * T)


def _temperature_rate(th: dict[str, float], e: Experiment, t: float, T: np.ndarray) -> np.ndarray:
    # g2 solved for dT/dt
    q, v, _ = _stroke(e, np.asarray(t))
    work = (th["theta4"] * _pressure(th, q, T) + th["theta11"]) * v
    loss = th["theta16"] * (1 + th["theta6"] * q) * (T + th["theta17"])
    return (work - loss) / th["theta15"]


def _integrate(th: dict[str, float], e: Experiment, T0: float, t_end: float, dense: bool = False):
    # A fine maximum step (1/400 period) so that the integrator cannot step over a stroke
    # reversal, where the compression work changes sign.
    return solve_ivp(lambda t, T: _temperature_rate(th, e, t, T), (0.0, t_end), [T0], method="DOP853",
                     rtol=1e-11, atol=1e-9, max_step=1.0 / (400 * e.frequency_hz), dense_output=dense)


@functools.lru_cache(maxsize=64)
def clean_signals(e: Experiment, rate_hz: float, periods: float,
                  theta: tuple[tuple[str, float], ...] = tuple(NOMINAL.items())) -> pd.DataFrame:
    """Noise-free columns (engineering units) of the periodic steady state, sampled at
    ``rate_hz`` from phase 0 over ``periods`` periods."""
    th = dict(theta)
    period = 1.0 / e.frequency_hz
    ambient = -th["theta17"]

    # Shooting: the periodic steady state is the T0 that one period maps onto itself.
    def gap(T0: float) -> float:
        return float(_integrate(th, e, T0, period).y[0, -1]) - T0

    T0 = brentq(gap, ambient - 80.0, ambient + 200.0, xtol=1e-10, rtol=1e-14)
    t = np.arange(int(np.ceil(periods * rate_hz / e.frequency_hz))) / rate_hz
    T = _integrate(th, e, T0, t[-1] + 1.0 / rate_hz, dense=True).sol(t)[0]
    q, v, acc = _stroke(e, t)
    p = _pressure(th, q, T)
    # g1 solved for Fe: the force the shaker needs to impose this stroke.
    fe = (th["theta1"] * (acc + th["theta2"]) + th["theta3"] * v * np.abs(v) + th["theta4"] * p
          + (th["theta8"] + th["theta9"] * p) * np.arctan(th["theta10"] * v) + th["theta11"])
    return pd.DataFrame({"time_s": t, "stroke_mm": (q + th["theta12"]) * 1e3, "force_N": fe,
                         "pressure_bar": p / 1e5, "gas_temperature_C": T - 273.15})


def generate_dataset(out: str | Path, experiments: Sequence[Experiment], *, rate_hz: float = 1000.0,
                     periods: float = 3, seed: int = 0, noise_scale: float | dict[str, float] = 1.0,
                     theta: dict[str, float] | None = None) -> Path:
    """Write ``dataset.json`` and one CSV per experiment into ``out``; return ``out``.

    ``noise_scale`` multiplies every channel's noise, or per column ({column: factor});
    a factor 0 leaves quantisation only.  ``theta`` overrides nominal parameters."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    th = dict(NOMINAL, **(theta or {}))
    rng = np.random.default_rng(seed)
    entries = []
    for e in experiments:
        clean = clean_signals(e, float(rate_hz), float(periods), tuple(th.items()))
        cols = {"time_s": clean["time_s"].to_numpy()}
        for ch in CHANNELS:
            scale = noise_scale.get(ch.column, 1.0) if isinstance(noise_scale, dict) else noise_scale
            cols[ch.column] = AdcChannel(ch.column, scale * ch.noise_std, ch.resolution, ch.offset).measure(
                clean[ch.column].to_numpy(), rng)
        entries.append(write_record(out, f"ind-{e.letter}", cols, e, rate_hz))
    return write_manifest(out, "independent 2-dof generator (tests)", "tests/independent_generator.py", seed, th,
                          entries)


def write_record(out: Path, label: str, cols: dict[str, np.ndarray], e: Experiment, rate_hz: float) -> dict:
    """One experiment's CSV in the dataset format; its entry for ``dataset.json``."""
    pd.DataFrame(cols).to_csv(out / f"{label}.csv", index=False, float_format="%.10g")
    return {"label": label, "kind": "periodic", "file": f"{label}.csv", "frequency_Hz": e.frequency_hz,
            "static_position_mm": e.static_position_mm, "amplitude_mm": e.amplitude_mm, "waveform": "sine",
            "sample_rate_Hz": rate_hz}


def write_manifest(out: Path, name: str, generator: str, seed: int, th: dict[str, float], entries: list[dict]) -> Path:
    """``dataset.json`` of a generated dataset (the truth and the seed in its source); ``out``."""
    manifest = {"format": "damper-dataset/1", "name": name,
                "ambient": {"temperature_K": -th["theta17"], "pressure_Pa": 101325.0},
                "source": {"generator": generator, "seed": seed, "truth": th}, "experiments": entries}
    (out / "dataset.json").write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return out
