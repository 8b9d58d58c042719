"""Bouc-Wen data with a known truth, made independently of the periodic solver.

A random-phase multisine drives the oscillator of ``identify/models/bouc_wen.py``,
written here a second time by hand, integrated in time from rest with scipy's DOP853
at tight tolerances until the response repeats; the last periods are sampled as the
rig would (displacement with white noise, force as commanded).  Sharing nothing with
the code under test but the equations is what makes a recovered truth meaningful.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from identify.dataset import FORMAT, csv_bytes, write_manifest
from identify.files import atomic_write_bytes

TRUTH = {"m": 2.0, "c": 10.0, "k": 5.0e4, "alpha": 5.0e4, "beta_gamma": 800.0, "beta_delta": -1100.0}
RATE_HZ = 750.0
SAMPLES = 8192  # per period
BAND_HZ = (5.0, 150.0)
RMS_N = 50.0
SUBSTEPS = 16  # integration steps per sample


def multisine(seed: int, samples: int = SAMPLES, rate_hz: float = RATE_HZ, band_hz: tuple[float, float] = BAND_HZ,
              rms: float = RMS_N) -> np.ndarray:
    """Complex line amplitudes (rfft layout, one period of ``samples``) of a random-phase
    multisine with equal amplitudes on every line inside the band."""
    f0 = rate_hz / samples
    k = np.arange(samples // 2 + 1)
    lines = (k * f0 >= band_hz[0]) & (k * f0 <= band_hz[1])
    phases = np.random.default_rng(seed).uniform(0, 2 * np.pi, lines.sum())
    spectrum = np.zeros(k.size, complex)
    # irfft(spectrum)·samples has the RMS sqrt(2·Σ|c|²)/… : equal |c| giving `rms`.
    spectrum[lines] = rms / np.sqrt(2 * lines.sum()) * np.exp(1j * phases)
    return spectrum


def sample_multisine(spectrum: np.ndarray, samples: int) -> np.ndarray:
    """One period of the multisine on ``samples`` equidistant points (exact: band-limited)."""
    padded = np.zeros(samples // 2 + 1, complex)
    padded[:spectrum.size] = spectrum[:padded.size]
    return np.fft.irfft(padded, n=samples) * samples


def integrate(theta: dict[str, float], spectrum: np.ndarray, count: int, samples: int = SAMPLES,
              rate_hz: float = RATE_HZ) -> np.ndarray:
    """Displacement at the first ``count`` sample times, from rest at t = 0.

    Classical Runge-Kutta, SUBSTEPS fixed steps per sample, and a step in which y' or z
    changes sign is split where it does (linear estimate): across the |y'| and |z|
    kinks (thousands per period) Runge-Kutta is only first-order accurate.  scipy's
    adaptive DOP853 pays a rejected step or more at every kink, which made it a hundred
    times slower here (tests/test_user_models.py checks the two agree)."""
    m, c, k, alpha, bg, bd = (theta[name] for name in ("m", "c", "k", "alpha", "beta_gamma", "beta_delta"))
    h = 1.0 / (rate_hz * SUBSTEPS)
    # The force at every step and half step, exactly (band-limited); between them cubic.
    table = sample_multisine(spectrum, samples * SUBSTEPS * 2).tolist()
    size = len(table)

    def force(j: int, frac: float) -> float:
        """Force at table index j + frac (0 <= frac <= 2), cubic through four table points."""
        i = j + int(frac)
        f = frac - int(frac)
        p0, p1, p2, p3 = (table[(i + d) % size] for d in (-1, 0, 1, 2))
        return p1 + f * (0.5 * (p2 - p0) + f * (p0 - 2.5 * p1 + 2 * p2 - 0.5 * p3
                                                + f * (1.5 * (p1 - p2) + 0.5 * (p3 - p0))))

    def step(y: float, v: float, z: float, dt: float, u0: float, u1: float, u2: float) -> tuple[float, float, float]:
        a1 = (u0 - c * v - k * y - z) / m
        b1 = alpha * v - bg * abs(v) * z - bd * v * abs(z)
        y2, v2, z2 = y + 0.5 * dt * v, v + 0.5 * dt * a1, z + 0.5 * dt * b1
        a2 = (u1 - c * v2 - k * y2 - z2) / m
        b2 = alpha * v2 - bg * abs(v2) * z2 - bd * v2 * abs(z2)
        y3, v3, z3 = y + 0.5 * dt * v2, v + 0.5 * dt * a2, z + 0.5 * dt * b2
        a3 = (u1 - c * v3 - k * y3 - z3) / m
        b3 = alpha * v3 - bg * abs(v3) * z3 - bd * v3 * abs(z3)
        y4, v4, z4 = y + dt * v3, v + dt * a3, z + dt * b3
        a4 = (u2 - c * v4 - k * y4 - z4) / m
        b4 = alpha * v4 - bg * abs(v4) * z4 - bd * v4 * abs(z4)
        return (y + dt / 6 * (v + 2 * v2 + 2 * v3 + v4), v + dt / 6 * (a1 + 2 * a2 + 2 * a3 + a4),
                z + dt / 6 * (b1 + 2 * b2 + 2 * b3 + b4))

    y = v = z = 0.0
    out = np.empty(count)
    j = 0  # table index of the current time
    for s in range(out.size):
        out[s] = y
        for _ in range(SUBSTEPS):
            yn, vn, zn = step(y, v, z, h, table[j], table[j + 1], table[(j + 2) % size])
            kinks = [a / (a - b) for a, b in ((v, vn), (z, zn)) if a * b < 0]
            if kinks:
                th = min(kinks)
                y, v, z = step(y, v, z, th * h, table[j], force(j, th), force(j, 2 * th))
                yn, vn, zn = step(y, v, z, (1 - th) * h, force(j, 2 * th), force(j, 1 + th), table[(j + 2) % size])
            y, v, z = yn, vn, zn
            j = (j + 2) % size
    return out


def simulate(theta: dict[str, float], spectrum: np.ndarray, periods: int, settle_periods: int = 1,
             samples: int = SAMPLES, rate_hz: float = RATE_HZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time, force and displacement of the last ``periods`` periods (at least 2), from
    rest after ``settle_periods`` periods; checks that consecutive periods agree."""
    y = integrate(theta, spectrum, (settle_periods + periods) * samples, samples, rate_hz)
    y_out = y[settle_periods * samples:]
    settled = np.max(np.abs(y_out[-samples:] - y_out[-2 * samples:-samples])) / np.max(np.abs(y_out))
    if settled > 1e-7:
        raise RuntimeError(f"Bouc-Wen reference not periodic after {settle_periods} periods ({settled:.2g})")
    t = np.arange(periods * samples) / rate_hz
    return t, sample_multisine(spectrum, samples)[np.arange(t.size) % samples], y_out


def write_dataset(out: str | Path, theta: dict[str, float] | None = None, phase_seed: int = 1, periods: int = 2,
                  noise: float = 0.01, noise_seed: int = 0, samples: int = SAMPLES) -> Path:
    """A dataset folder with one periodic experiment ``bw``: the force as commanded and
    the displacement [mm] with white noise of ``noise`` times its RMS; ``samples`` per
    period at RATE_HZ."""
    theta = dict(TRUTH if theta is None else theta)
    out = Path(out)
    t, u, y = simulate(theta, multisine(phase_seed, samples), periods, samples=samples,
                       settle_periods=max(1, -(-SAMPLES // samples)))
    y_mm = 1e3 * y
    y_mm = y_mm + noise * np.sqrt(np.mean(y_mm**2)) * np.random.default_rng(noise_seed).standard_normal(y.size)
    atomic_write_bytes(out / "bw.csv", csv_bytes({"time_s": t, "force_N": u, "displacement_mm": y_mm}, "%.12g"))
    write_manifest(out, {
        "format": FORMAT, "name": f"Bouc-Wen oscillator, random-phase multisine (seed {phase_seed})",
        "experiments": [{"label": "bw", "kind": "periodic", "file": "bw.csv", "frequency_Hz": RATE_HZ / samples,
                         "sample_rate_Hz": RATE_HZ, "periods": periods,
                         "excitation": f"random-phase multisine {BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz, {RMS_N:g} N RMS"}],
    })
    atomic_write_bytes(out / "truth.json", (json.dumps({"model": "bouc-wen", "parameters": theta}, indent=2)
                                            + "\n").encode())
    return out
