"""Friction from the force jumps at velocity reversals (paper §5, Fig. 7).

At a reversal the seal friction (θ8 + θ9·p)·arctan(θ10·q̇) swings from one sign to the
other within a fraction of a millimetre per second, while everything else in the axle
force (gas spring, inertia, orifice damping) varies smoothly.  Near each reversal of a
folded period the force is fitted with a smooth quadratic in time plus
F_a·arctan(θ10·q̇): the amplitude F_a and the sharpness θ10 of that reversal.  Over a
set, F_a against the gas pressure at the reversals gives the line θ8 + θ9·p.

The results can be fed back as fixed per-experiment values of θ8, θ9, θ10 in a fit
(``identify fit --friction FRICTION.json``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from identify.dataset import DatasetError
from identify.errors import InputError
from identify.folding import FoldedRecord

HARMONICS = 60           # the stroke is smooth: its velocity from the first harmonics only
WINDOW_FRACTION = 0.03   # each side of a reversal, as a fraction of the period
MIN_SPEED_M_S = 2e-3     # the friction law must be saturated at the window's ends


class FrictionError(InputError):
    """Friction could not be extracted (names the experiment and why)."""


@dataclass
class Reversal:
    phase: float
    pressure_bar: float
    amplitude_n: float
    sharpness_s_m: float


@dataclass
class ExperimentFriction:
    label: str
    reversals: list[Reversal]
    theta8: float
    theta9: float
    theta10: float


@dataclass
class FrictionResult:
    experiments: list[ExperimentFriction]
    theta8: float           # over the set: F_a = θ8 + θ9·p
    theta9: float
    theta8_std: float
    theta9_std: float
    theta10: float          # median sharpness over the set

    def to_document(self) -> dict:
        return {"set": {"theta8": self.theta8, "theta9": self.theta9, "theta8_std": self.theta8_std,
                        "theta9_std": self.theta9_std, "theta10": self.theta10},
                "experiments": {e.label: {"theta8": e.theta8, "theta9": e.theta9, "theta10": e.theta10,
                                          "reversals": [asdict(r) for r in e.reversals]}
                                for e in self.experiments}}

    def table(self) -> str:
        lines = [f"{'experiment':<12} {'phase':>6} {'p [bar]':>9} {'F_a [N]':>9} {'theta10 [s/m]':>14}"]
        for e in self.experiments:
            for r in e.reversals:
                lines.append(f"{e.label:<12} {r.phase:6.3f} {r.pressure_bar:9.3f} {r.amplitude_n:9.2f} "
                             f"{r.sharpness_s_m:14.0f}")
        lines.append(f"set: F_a = theta8 + theta9 * p with theta8 = {self.theta8:.4g} ± {self.theta8_std:.2g} N, "
                     f"theta9 = {self.theta9:.4g} ± {self.theta9_std:.2g} m², theta10 = {self.theta10:.4g} s/m "
                     "(median)")
        return "\n".join(lines)


def _velocity(q: np.ndarray, frequency_hz: float) -> np.ndarray:
    Q = np.fft.rfft(q)
    Q[HARMONICS + 1:] = 0
    k = np.arange(len(Q)) * 2 * np.pi * frequency_hz
    return np.fft.irfft(1j * k * Q, len(q))


def _reversal_residual(x: np.ndarray, s: np.ndarray, v: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Smooth quadratic in the normalised time s plus amp·arctan(sharp·v), minus the force."""
    a, b, c, amp, sharp = x
    return a + b * s + c * s**2 + amp * np.arctan(sharp * v) - force


def reversals(folded: FoldedRecord, stroke_col: str = "stroke_mm", force_col: str = "force_N",
              pressure_col: str = "pressure_bar") -> list[Reversal]:
    """The friction amplitude and sharpness at each velocity reversal of a folded period."""
    n, f = folded.n, folded.frequency_hz
    q = folded.values[stroke_col] * 1e-3
    force = folded.values[force_col]
    p = folded.values[pressure_col]
    v = _velocity(q, f)
    turns = np.flatnonzero(np.sign(v) != np.sign(np.roll(v, -1)))
    w = max(8, int(WINDOW_FRACTION * n))
    out = []
    for i in turns:
        idx = (i + np.arange(-w, w + 1)) % n
        vv, ff = v[idx], force[idx]
        if min(abs(vv[0]), abs(vv[-1])) < MIN_SPEED_M_S:
            continue  # too slow to saturate the friction law inside the window
        s = np.arange(-w, w + 1) / w
        jump = (ff[-3:].mean() - ff[:3].mean()) * np.sign(vv[-1])
        x0 = [ff.mean(), 0.0, 0.0, max(jump / np.pi, 1.0), 1.0 / MIN_SPEED_M_S]
        fit = least_squares(_reversal_residual, x0, args=(s, vv, ff), x_scale=[abs(ff.mean()) + 1, 10, 10, 10, 1e3],
                            bounds=([-np.inf, -np.inf, -np.inf, 0, 10], np.inf))
        out.append(Reversal(float(i / n), float(p[i]), float(fit.x[3]), float(fit.x[4])))
    return out


def extract(records: list[FoldedRecord]) -> FrictionResult:
    """Per-experiment friction and the set's linear law F_a = θ8 + θ9·p."""
    exps = []
    for rec in records:
        revs = reversals(rec)
        if len(revs) < 2:
            raise FrictionError(f"{rec.label}: {len(revs)} usable velocity reversals (needs 2: the stroke must "
                                f"reverse at more than {MIN_SPEED_M_S * 1e3:g} mm/s away from the turning point)")
        P = np.array([r.pressure_bar * 1e5 for r in revs])
        A = np.array([r.amplitude_n for r in revs])
        if np.ptp(P) > 1e3:
            theta9, theta8 = np.polyfit(P, A, 1)
        else:
            theta9, theta8 = 0.0, float(A.mean())
        exps.append(ExperimentFriction(rec.label, revs, float(theta8), float(theta9),
                                       float(np.median([r.sharpness_s_m for r in revs]))))
    P = np.array([r.pressure_bar * 1e5 for e in exps for r in e.reversals])
    A = np.array([r.amplitude_n for e in exps for r in e.reversals])
    if len(P) < 3:
        raise FrictionError("fewer than 3 reversals over the set: no line through friction against pressure")
    (theta9, theta8), cov = np.polyfit(P, A, 1, cov=True)
    return FrictionResult(exps, float(theta8), float(theta9), float(np.sqrt(cov[1, 1])), float(np.sqrt(cov[0, 0])),
                          float(np.median([e.theta10 for e in exps])))


def load_fixed(path: str | Path, names: list[str]) -> dict[str, dict[int, float]]:
    """Per-experiment fixed θ8, θ9, θ10 from a FRICTION.json: {label: {parameter index: value}}."""
    try:
        doc = json.loads(Path(path).read_text())
        return {label: {names.index(k): float(e[k]) for k in ("theta8", "theta9", "theta10")}
                for label, e in doc["experiments"].items()}
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: not a FRICTION.json ({exc})") from None
