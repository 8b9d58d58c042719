"""A linear 1-dof oscillator as a user model, and its exact response to multisines.

For a linear system the periodic response is the input spectrum times the frequency
response, line by line: no integrator, no periodic solver, nothing shared with the code
under test.  Damped free motion decays by exp(−c/(2m)·t), which makes the Floquet
multipliers over a period known in closed form.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from identify.dataset import FORMAT, csv_bytes, write_manifest
from identify.files import atomic_write_bytes
from tests.hysteresis_data import multisine

TRUTH = {"m": 2.0, "c": 10.0, "k": 5.0e4}
RATE_HZ = 256.0
SAMPLES = 256  # per period: 1 Hz lines
BAND_HZ = (2.0, 60.0)  # the resonance sqrt(k/m)/2π = 25 Hz inside
RMS_N = 50.0

MODEL_SOURCE = '''\
from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class Linear(ModelDeclaration):
    name = "linear-1dof"
    description = "m y'' + c y' + k y = u"
    states = (State("y", "m", 1e-4),)
    inputs = {"u": Channel("force_N", "N")}
    outputs = {"displacement_mm": Channel("displacement_mm", "mm", scale=1e-3),
               "acceleration_m_s2": Channel("acceleration_m_s2", "m/s^2")}
    default_outputs = ("displacement_mm",)
    parameters = (
        ParameterSpec("m", "mass", "kg", 2.0, "moving mass"%(mass_bounds)s),
        ParameterSpec("c", "damping", "N s/m", 10.0, "viscous damping"%(damping_bounds)s),
        ParameterSpec("k", "stiffness", "N/m", 5.0e4, "stiffness"),
    )

    def residuals(self, s):
        return [s.m * s.y_tt + s.c * s.y_t + s.k * s.y - s.u]

    def output_equations(self, s):
        return {"displacement_mm": s.y, "acceleration_m_s2": s.y_tt}
'''


def write_model(folder: Path, mass_bounds: str = "", damping_bounds: str = "") -> str:
    """The model file in ``folder``; its ``--model`` argument.  ``*_bounds``: extra
    ParameterSpec arguments such as ``", minimum=0.0"``."""
    path = Path(folder) / "linear_1dof.py"
    path.write_text(MODEL_SOURCE % {"mass_bounds": mass_bounds, "damping_bounds": damping_bounds})
    return f"{path}:Linear"


def response(theta: dict[str, float], spectrum: np.ndarray, samples: int = SAMPLES,
             rate_hz: float = RATE_HZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One period of force [N], displacement [m] and acceleration [m/s²] of the periodic steady state."""
    w = 2 * np.pi * rate_hz / samples * np.arange(spectrum.size)
    h = 1.0 / (theta["k"] - theta["m"] * w**2 + 1j * theta["c"] * w)
    return tuple(np.fft.irfft(x, n=samples) * samples  # type: ignore[return-value]
                 for x in (spectrum, h * spectrum, -w**2 * h * spectrum))


def write_dataset(out: str | Path, theta: dict[str, float] | None = None, phase_seed: int = 1, periods: int = 3,
                  noise: float = 0.01, noise_seed: int = 0, label: str = "lin") -> Path:
    """A dataset folder with one periodic experiment: force as commanded, displacement
    [mm] and acceleration [m/s²], each with white noise of ``noise`` times its RMS."""
    theta = dict(TRUTH if theta is None else theta)
    out = Path(out)
    u, y, a = response(theta, multisine(phase_seed, SAMPLES, RATE_HZ, BAND_HZ, RMS_N))
    t = np.arange(periods * SAMPLES) / RATE_HZ
    rng = np.random.default_rng(noise_seed)
    columns = {"time_s": t, "force_N": np.tile(u, periods)}
    for name, x in (("displacement_mm", 1e3 * y), ("acceleration_m_s2", a)):
        x = np.tile(x, periods)
        columns[name] = x + noise * np.sqrt(np.mean(x**2)) * rng.standard_normal(x.size)
    atomic_write_bytes(out / f"{label}.csv", csv_bytes(columns, "%.12g"))
    write_manifest(out, {
        "format": FORMAT, "name": f"linear oscillator, random-phase multisine (seed {phase_seed})",
        "experiments": [{"label": label, "kind": "periodic", "file": f"{label}.csv",
                         "frequency_Hz": RATE_HZ / SAMPLES, "sample_rate_Hz": RATE_HZ, "periods": periods,
                         "excitation": f"random-phase multisine {BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz, {RMS_N:g} N RMS"}],
    })
    return out


TWO_MODES = {"m1": 1.0e-5, "m2": 0.5e-5, "k1": 1.0, "k2": 0.5, "c1": 2.0e-4, "c2": 2.0e-4}


def write_two_mode_dataset(out: str | Path, phase_seed: int, periods: int = 3, noise: float = 1e-3,
                           noise_seed: int = 0, rms: float = 0.5) -> Path:
    """A record in the Duffing model's columns (``input``, ``output``) from a linear chain
    of two masses (force on the first, output its displacement), under a random-phase
    multisine: data a 1-dof Duffing cannot describe."""
    p = TWO_MODES
    spectrum = multisine(phase_seed, SAMPLES, RATE_HZ, (3.0, 100.0), rms)
    w = 2 * np.pi * RATE_HZ / SAMPLES * np.arange(spectrum.size)
    M, K = np.diag([p["m1"], p["m2"]]), np.array([[p["k1"] + p["k2"], -p["k2"]], [-p["k2"], p["k2"]]])
    C = np.array([[p["c1"] + p["c2"], -p["c2"]], [-p["c2"], p["c2"]]])
    h = np.array([np.linalg.inv(K - wi**2 * M + 1j * wi * C)[0, 0] for wi in w])
    u, y = (np.fft.irfft(x, n=SAMPLES) * SAMPLES for x in (spectrum, h * spectrum))
    y = np.tile(y, periods)
    y += noise * np.sqrt(np.mean(y**2)) * np.random.default_rng(noise_seed).standard_normal(y.size)
    out = Path(out)
    atomic_write_bytes(out / "ms.csv", csv_bytes({"time_s": np.arange(y.size) / RATE_HZ, "input": np.tile(u, periods),
                                                  "output": y}, "%.12g"))
    write_manifest(out, {
        "format": FORMAT, "name": f"two-mode chain, random-phase multisine (seed {phase_seed})",
        "experiments": [{"label": "ms", "kind": "periodic", "file": "ms.csv", "frequency_Hz": RATE_HZ / SAMPLES,
                         "sample_rate_Hz": RATE_HZ, "periods": periods,
                         "excitation": f"random-phase multisine 3-100 Hz, {rms:g} V RMS"}],
    })
    return out
