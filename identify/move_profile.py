"""The shaker controller's move to a static position, defined once: a half cosine from
where the actuator stands to the target, at a fixed peak speed (the controller's
datasheet, docs/rig-interfaces.md §1: "a cosine profile at up to 50 mm/s").

The rig's planning predicts with it (from the rig's configuration, ``[limits]
move_speed_m_s``, whose default is :data:`CONTROLLER_MOVE`), the simulated controller
commands it and the plant tier's plan sequence drives the plant with it, so the three
cannot disagree.  Here because ``identify`` is the one package both ``rig`` and
``simulator`` import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MoveProfile:
    """A half-cosine move whose speed peaks at ``peak_speed_m_s`` halfway."""

    peak_speed_m_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.peak_speed_m_s) and self.peak_speed_m_s > 0):
            raise ValueError(f"a move's peak speed must be a positive number of m/s, not {self.peak_speed_m_s}")

    def duration_s(self, distance_m: float) -> float:
        """How long a move over ``distance_m`` (either sign) takes: π·|d| / (2·v_peak)."""
        return math.pi * abs(distance_m) / (2 * self.peak_speed_m_s)

    def durations_s(self, distance_m: np.ndarray) -> np.ndarray:
        """:meth:`duration_s` of each element."""
        return np.pi * np.abs(distance_m) / (2 * self.peak_speed_m_s)

    @staticmethod
    def during(start_m: float | np.ndarray, target_m: float | np.ndarray, duration_s: float | np.ndarray,
               t_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at ``t_s`` within the move (0 ≤ t ≤ duration;
        the half cosine itself, for an integrator's stages).  A zero-length move is there at once."""
        d = np.asarray(target_m) - np.asarray(start_m)
        w = np.pi / np.maximum(duration_s, 1e-12)
        return (start_m + d * 0.5 * (1 - np.cos(w * t_s)), d * 0.5 * w * np.sin(w * t_s),
                d * 0.5 * w**2 * np.cos(w * t_s))

    @classmethod
    def stroke(cls, start_m: float | np.ndarray, target_m: float | np.ndarray, duration_s: float | np.ndarray,
               t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at any ``t_s`` after the move began: before
        it at ``start_m``, after it at ``target_m``, at rest."""
        q, v, a = cls.during(start_m, target_m, duration_s, np.clip(t_s, 0.0, duration_s))
        moving = (t_s >= 0) & (t_s <= duration_s)
        return q, np.where(moving, v, 0.0), np.where(moving, a, 0.0)


CONTROLLER_MOVE = MoveProfile(peak_speed_m_s=0.050)   # the controller's datasheet (rig-interfaces.md §1)
