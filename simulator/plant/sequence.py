"""A plan run on the plant as a rig runs it: one experiment after the other, each moved
to its static position, faded in, settled, captured and faded out, the wall's heat and
the oil's dissolved gas carried from one experiment to the next.  The plant's states are
integrated on the grid the served rig integrates them on, every
:data:`~simulator.plant.integrator.STEP_S`; the DAQ's
samples read them interpolated, the stroke and its derivatives exactly."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identify.move_profile import CONTROLLER_MOVE, MoveProfile
from identify.plans import ExperimentSpec
from simulator.physics import Actuator, steady_stroke, waveform_harmonics
from simulator.plant.damper import PlantDamper
from simulator.plant.integrator import integrate_stroke, states_at
from simulator.plant.streaming import StreamingPlantTruth

FADE_PERIODS = 1.0      # fade in and out over a period, at most FADE_MAX_S
FADE_MAX_S = 10.0


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
        move = CONTROLLER_MOVE.duration_s(spec.static_position_mm * 1e-3 - start_m)
        return cls(spec, actuator, start_m, move, min(FADE_PERIODS * spec.period_s, FADE_MAX_S), end_s)

    def stroke(self, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured stroke, velocity and acceleration at times σ (SI)."""
        static = self.spec.static_position_mm * 1e-3
        # The controller's move from start_m to the static position, ending at σ = 0.
        q, v, a = MoveProfile.stroke(self.start_m, static, self.move_s, sigma + self.move_s)
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
        # The served rig's step for every experiment: a period's 200th (the step this
        # once took) left experiment a's loop area at 60 % of LSODA's.
        grid, states = integrate_stroke(plant, seg.stroke, -seg.move_s, times[-1] + seg.fade_s, y)
        keep = (times >= settle_s)
        ts = times[keep]
        q_s, v_s, a_s = seg.stroke(ts)
        ys = states_at(plant, grid, *seg.stroke(grid)[:2], states, ts)
        out.append(Capture(spec, ts, plant.channels(q_s, v_s, a_s, ys), float(np.mean(ys[1])), float(np.mean(ys[2]))))
        y = states[:, -1]
        position = float(seg.stroke(grid[-1:])[0][0])
    return out


def run_plan_from_run(plant: PlantDamper, plan: list[ExperimentSpec], actuator: Actuator,
                      record_times: list[np.ndarray], ramp_s: float) -> list[Capture]:
    """Captures of ``plan`` recorded from RUN on, as a plan with ``capture = "transient"``
    runs on a rig: from rest at q = 0, each experiment's move to its static position (the
    controller's, :mod:`identify.move_profile`), RUN with the amplitude ramped linearly over
    ``ramp_s`` (the controller's ramp) and captured from that instant for
    ``record_times[i]`` (uniform, counted from RUN), then the ramp down to the static
    position; the actuator tracks the setpoint as on the served rig, and the wall's heat
    and the dissolved gas carry from one experiment to the next (nothing is waited out)."""
    out = []
    truth: StreamingPlantTruth | None = None
    for spec, times in zip(plan, record_times, strict=True):
        dt = float(times[1] - times[0])
        if truth is None:
            truth = StreamingPlantTruth(plant, actuator, dt, 0.0)
        elif abs(truth.dt - dt) > 1e-12:
            raise ValueError("a transient capture's sample interval must be the same in every experiment")
        static = spec.static_position_mm * 1e-3
        start = truth.position_m
        move_s = CONTROLLER_MOVE.duration_s(static - start)
        if move_s > 0:
            steps = np.arange(1, int(np.ceil(move_s / dt)) + 1) * dt
            _advance(truth, MoveProfile.stroke(start, static, move_s, steps)[0])
        k, b = waveform_harmonics(spec.waveform)
        tau = times - times[0]
        envelope = np.clip(tau / max(ramp_s, 1e-9), 0.0, 1.0)
        shape = np.sin(np.outer(tau, 2 * np.pi * spec.frequency_hz * k)) @ b
        stroke, v, a, Y = _advance(truth, static + spec.amplitude_mm * 1e-3 * envelope * shape)
        if np.max(np.abs(v)) > actuator.velocity_limit_m_s:
            raise ValueError(f"experiment {spec.letter}: peak velocity {np.max(np.abs(v)):.3f} m/s exceeds the "
                             f"actuator's limit {actuator.velocity_limit_m_s} m/s")
        out.append(Capture(spec, tau, plant.channels(stroke, v, a, Y), float(np.mean(Y[1])), float(np.mean(Y[2]))))
        # STOP: the amplitude ramped down from where the capture ended, phase continuing.
        down = tau[-1] + np.arange(1, int(np.ceil(ramp_s / dt)) + 1) * dt
        fade = np.clip(1.0 - (down - tau[-1]) / max(ramp_s, 1e-9), 0.0, 1.0)
        _advance(truth, static + spec.amplitude_mm * 1e-3 * fade
                 * (np.sin(np.outer(down, 2 * np.pi * spec.frequency_hz * k)) @ b))
    return out


def _advance(truth: StreamingPlantTruth, setpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    stroke, v, a, Y = truth.advance(setpoint)
    truth.commit(len(setpoint), Y)
    return stroke, v, a, Y
