"""What the live view derives from the samples (no Qt here): the work loop's energy per
cycle, the stroke velocity, the samples drawn.  SI inside; the callers convert at the
display.  Settling (its cycles left) is the session's progress's to count
(rig.session.session_progress), never recounted here."""

from __future__ import annotations

import math

import numpy as np


def peak_decimate(t: np.ndarray, y: np.ndarray, buckets: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``2 * buckets`` points that draw like all of them: each bucket of samples
    becomes its minimum and its maximum (a spike stays visible, as on a scope)."""
    n = len(y)
    per = n // buckets
    if per < 2:
        return t, y
    m = per * buckets
    start = n - m                       # the newest samples are kept whole
    yb = y[start:].reshape(buckets, per)
    tb = t[start:].reshape(buckets, per)
    lo, hi = yb.argmin(axis=1), yb.argmax(axis=1)
    first = np.minimum(lo, hi)[:, None]
    second = np.maximum(lo, hi)[:, None]
    pick = np.hstack((first, second))   # in time order within each bucket
    rows = np.arange(buckets)[:, None]
    return tb[rows, pick].ravel(), yb[rows, pick].ravel()


def last_cycles(n_samples: int, rate_hz: float, frequency_hz: float, cycles: int) -> int:
    """How many of the newest samples make ``cycles`` whole cycles (0 if fewer are there)."""
    spp = rate_hz / frequency_hz
    whole = min(cycles, int(n_samples // spp))
    return int(round(whole * spp))


def loop_energy_j(stroke_m: np.ndarray, force_n: np.ndarray, cycles: int) -> float:
    """Energy dissipated per cycle, J: the work loop's area ∮F dq over whole cycles, divided
    by their number (positive for a damper that takes energy out; the gas spring's
    conservative part cancels over a closed loop)."""
    if cycles < 1 or len(stroke_m) < 3:
        return math.nan
    work = np.sum(0.5 * (force_n[1:] + force_n[:-1]) * np.diff(stroke_m))
    return float(work) / cycles


def velocity_m_s(stroke_m: np.ndarray, rate_hz: float, frequency_hz: float | None) -> np.ndarray:
    """Stroke velocity by a central difference over a span of about 1/100 of a period, so
    that the transducer's noise (10 µm at 2 kHz) does not swamp it."""
    n = len(stroke_m)
    span = max(1, int(rate_hz / (100 * frequency_hz))) if frequency_hz else 1
    v = np.zeros(n)
    if n > 2 * span:
        v[span:-span] = (stroke_m[2 * span:] - stroke_m[:-2 * span]) * rate_hz / (2 * span)
        v[:span], v[-span:] = v[span], v[-span - 1]
    return v
