"""A plan run on the plant as a rig runs it: one experiment after the other, each moved
to its static position, faded in, settled, captured and faded out, the wall's heat and
the oil's dissolved gas carried from one experiment to the next.  The plant's states are
integrated on a grid of their own (:mod:`simulator.plant.integrator`); the DAQ's
samples read them interpolated, the stroke and its derivatives exactly."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identify.plans import ExperimentSpec
from simulator.physics import Actuator, steady_stroke
from simulator.plant.damper import PlantDamper
from simulator.plant.integrator import STEP_S, integrate

MOVE_SPEED_M_S = 0.02   # between static positions, as the controller's moves
FADE_PERIODS = 1.0      # fade in and out over a period, at most FADE_MAX_S
FADE_MAX_S = 10.0
STEPS_PER_PERIOD = 200  # the states' grid: a period's 200th, at least STEP_S


@dataclass(frozen=True)
class Segment:
    """One experiment's drive from the last static position: move (σ < 0), fade in
    (0 ≤ σ < fade), steady, fade out after ``end`` (σ is the time since the fade began;
    the capture's times are the model tier's, phase zero at σ = 0)."""

    spec: ExperimentSpec
    actuator: Actuator
    start_m: float
    move_s: float
    fade_s: float
    end_s: float

    @classmethod
    def after(cls, spec: ExperimentSpec, actuator: Actuator, start_m: float, end_s: float) -> Segment:
        move = max(abs(spec.static_position_mm * 1e-3 - start_m) / MOVE_SPEED_M_S, 1.0)
        return cls(spec, actuator, start_m, move, min(FADE_PERIODS * spec.period_s, FADE_MAX_S), end_s)

    def stroke(self, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured stroke, velocity and acceleration at times σ (SI)."""
        static = self.spec.static_position_mm * 1e-3
        # The move: a half cosine from start_m to the static position.
        u = np.clip((sigma + self.move_s) / self.move_s, 0.0, 1.0)
        moving = (sigma < 0) & (sigma > -self.move_s)
        w = np.pi / self.move_s
        d = static - self.start_m
        q = self.start_m + d * 0.5 * (1 - np.cos(np.pi * u))
        v = np.where(moving, d * 0.5 * w * np.sin(np.pi * u), 0.0)
        a = np.where(moving, d * 0.5 * w**2 * np.cos(np.pi * u), 0.0)
        # The oscillation, faded in after σ = 0 and out after end_s.
        x, xd, xdd = steady_stroke(self.spec, self.actuator, sigma)
        x = x - static
        r, rd, rdd = _fade(sigma, self.fade_s)
        f, fd, fdd = _fade(self.end_s + self.fade_s - sigma, self.fade_s)
        g, gd, gdd = r * f, rd * f - r * fd, rdd * f - 2 * rd * fd + r * fdd
        return q + g * x, v + g * xd + gd * x, a + g * xdd + 2 * gd * xd + gdd * x


def _fade(s: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """0 → 1 over [0, length] as a half cosine, and its two derivatives."""
    u = np.clip(s / length, 0.0, 1.0)
    inside = (s > 0) & (s < length)
    w = np.pi / length
    return (0.5 * (1 - np.cos(np.pi * u)), np.where(inside, 0.5 * w * np.sin(np.pi * u), 0.0),
            np.where(inside, 0.5 * w**2 * np.cos(np.pi * u), 0.0))


@dataclass
class Capture:
    """One experiment's captured record: times (the model tier's) and the four SI channels."""

    spec: ExperimentSpec
    t: np.ndarray
    si: np.ndarray
    wall_k: float          # the wall's mean temperature over the capture
    dissolved_mol: float


def run_plan(plant: PlantDamper, plan: list[ExperimentSpec], actuator: Actuator, record_times: list[np.ndarray],
             settle_s: float) -> list[Capture]:
    """Captures of ``plan`` run in order from rest at q = 0; ``record_times[i]`` are the
    times of experiment i's samples, counted from its fade-in (≥ ``settle_s``)."""
    y = plant.rest_state(0.0)
    position = 0.0
    out = []
    for spec, times in zip(plan, record_times, strict=True):
        seg = Segment.after(spec, actuator, position, float(times[-1]))
        step = max(STEP_S, spec.period_s / STEPS_PER_PERIOD)
        grid = np.arange(-seg.move_s, times[-1] + seg.fade_s + step, step)
        q_m, v, _ = seg.stroke(grid)
        states = integrate(plant, grid, q_m, v, y)
        keep = (times >= settle_s)
        ts = times[keep]
        ys = np.vstack([np.interp(ts, grid, s) for s in states])
        q_s, v_s, a_s = seg.stroke(ts)
        out.append(Capture(spec, ts, plant.channels(q_s, v_s, a_s, ys), float(np.mean(ys[1])), float(np.mean(ys[2]))))
        y = states[:, -1]
        position = float(q_m[-1])
    return out
