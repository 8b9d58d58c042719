"""The two physics tiers the engine drives, behind one small interface: ``model`` (the
identification model's own equations, :mod:`simulator.physics`) and ``plant`` (the
plant truth, :mod:`simulator.plant`).  The controller, the DAQ and the faults see only
strokes, forces and the four channels, never which tier produced them.

A tier advances a block of setpoints to the measured stroke, velocity, acceleration and
rows X of whatever states its channels need (the model: the gas temperature; the plant:
its six states); the engine interpolates X at the DAQ's sample times and asks the tier
for the four SI channels there.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from simulator.physics import Actuator, Damper, StreamingPlant, drop_test, stop_force
from simulator.plant.damper import PlantDamper
from simulator.plant.drop import simulate_drop
from simulator.plant.streaming import StreamingPlantTruth


class DropTrack(Protocol):
    duration_s: float

    def channels(self, since: np.ndarray) -> np.ndarray: ...
    def stroke(self, since_s: float) -> float: ...


class ModelTier:
    """The identification model's damper (θ)."""

    def __init__(self, damper: Damper, actuator: Actuator, dt_s: float, position_m: float) -> None:
        self.damper = damper
        self.plant = StreamingPlant(damper, actuator, dt_s, position_m)

    def rest(self) -> np.ndarray:
        return np.array([self.plant.temperature_k])

    def advance(self, setpoint):
        stroke, v, a, T = self.plant.advance(setpoint)
        return stroke, v, a, T[None, :]

    def commit(self, n, X):
        self.plant.commit(n)

    def axle_force(self, stroke, v, a, X):
        return self.damper.axle_force(self.damper.internal_stroke(stroke), v, a, X[0])

    def channels(self, stroke, v, a, X):
        d, T = self.damper, X[0]
        q = d.internal_stroke(stroke)
        return np.vstack([stroke, d.axle_force(q, v, a, T), d.pressure(q, T), T])

    def drop(self, mass_kg: float, duration_s: float, velocity_m_s: float) -> DropTrack:
        return _ModelDrop(self.damper, mass_kg, duration_s, velocity_m_s)


class _ModelDrop:
    """The whole drop (touching down at q = 0 at ``velocity_m_s``, gas at ambient), integrated once."""

    def __init__(self, damper: Damper, mass_kg: float, duration_s: float, velocity_m_s: float) -> None:
        self.damper = damper
        self.rec = drop_test(damper, mass_kg, velocity_m_s, np.arange(0.0, duration_s, 1e-3))
        self.duration_s = float(self.rec.t[-1])

    def channels(self, since):
        rec, d = self.rec, self.damper
        inside = np.clip(since, 0.0, rec.t[-1])
        q = np.where(since >= 0, np.interp(inside, rec.t, rec.q), 0.0)
        v = np.where(since >= 0, np.interp(inside, rec.t, rec.velocity), 0.0)
        T = np.where(since >= 0, np.interp(inside, rec.t, rec.temperature), d.ambient_k)
        return np.vstack([d.measured_stroke(q), d.damper_force(q, v, T) + stop_force(q), d.pressure(q, T), T])

    def stroke(self, since_s):
        q = float(np.interp(min(since_s, self.rec.t[-1]), self.rec.t, self.rec.q)) if since_s >= 0 else 0.0
        return float(self.damper.measured_stroke(q))


class PlantTier:
    """The plant truth."""

    def __init__(self, plant: PlantDamper, actuator: Actuator, dt_s: float, position_m: float) -> None:
        self.plant = plant
        self.stream = StreamingPlantTruth(plant, actuator, dt_s, position_m)

    def rest(self) -> np.ndarray:
        return self.stream.state.copy()

    def advance(self, setpoint):
        return self.stream.advance(setpoint)

    def commit(self, n, X):
        self.stream.commit(n, X)

    def axle_force(self, stroke, v, a, X):
        return self.plant.channels(stroke, v, a, X)[1]

    def channels(self, stroke, v, a, X):
        return self.plant.channels(stroke, v, a, X)

    def drop(self, mass_kg: float, duration_s: float, velocity_m_s: float) -> DropTrack:
        return _PlantDrop(self.plant, mass_kg, duration_s, velocity_m_s)


class _PlantDrop:
    """The plant's drop (touching down at q = 0 at ``velocity_m_s``), integrated once and sampled."""

    def __init__(self, plant: PlantDamper, mass_kg: float, duration_s: float, velocity_m_s: float) -> None:
        self.plant = plant
        self.rec = simulate_drop(mass_kg=mass_kg, velocity_m_s=velocity_m_s, duration_s=duration_s, rate_hz=1000.0,
                                 constants=plant.k, ambient_k=plant.ambient_k)
        self.duration_s = float(self.rec.t[-1])
        rest = plant.channels(0.0, 0.0, -9.81, plant.rest_state(0.0))[:, 0]
        self._rest = rest.copy()
        self._rest[1] = self.rec.force_N[0]

    def channels(self, since):
        r = self.rec
        inside = np.clip(since, 0.0, r.t[-1])
        rows = [r.stroke_m, r.force_N, r.pressure_Pa, r.temperature_K]
        return np.vstack([np.where(since >= 0, np.interp(inside, r.t, x), rest)
                          for x, rest in zip(rows, self._rest, strict=True)])

    def stroke(self, since_s):
        return float(np.interp(min(since_s, self.rec.t[-1]), self.rec.t, self.rec.stroke_m)) if since_s >= 0 else 0.0


def rest_stroke(damper: Damper | PlantDamper) -> float:
    """What the stroke transducer reads with the damper fully extended (q = 0) [m]."""
    return 0.0 if isinstance(damper, PlantDamper) else float(damper.measured_stroke(0.0))


def make_tier(damper: Damper | PlantDamper, actuator: Actuator, dt_s: float,
              position_m: float) -> ModelTier | PlantTier:
    """The tier of ``damper``'s kind."""
    if isinstance(damper, PlantDamper):
        return PlantTier(damper, actuator, dt_s, position_m)
    return ModelTier(damper, actuator, dt_s, position_m)
