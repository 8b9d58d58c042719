"""The plant advanced block by block in simulated time, for the served rig: the
actuator tracks the controller's setpoint at the engine's rate, the plant's states are
integrated on every ``STEP_S`` of it (and at the block's end) and read interpolated at
the engine's steps."""

from __future__ import annotations

import numpy as np

from simulator.physics import Actuator, ActuatorTrack
from simulator.plant.damper import PlantDamper
from simulator.plant.integrator import STEP_S, integrate


class StreamingPlantTruth:
    """The plant's counterpart of :class:`simulator.physics.StreamingPlant`:
    :meth:`advance` returns the measured stroke, velocity, acceleration and the plant's
    six states (6, n) at the next steps; :meth:`commit` keeps them."""

    def __init__(self, plant: PlantDamper, actuator: Actuator, dt_s: float, position_m: float) -> None:
        self.plant, self.dt = plant, dt_s
        self._track = ActuatorTrack(actuator, dt_s, position_m)
        self._every = max(int(round(STEP_S / dt_s)), 1)
        self.state = plant.rest_state(position_m)
        self._last = (position_m, 0.0)
        self._pending: tuple = (0, None, None)

    def advance(self, setpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        stroke, v, a, filters = self._track.track(setpoint)
        n = len(setpoint)
        # The states' grid: the last committed step (index 0), every STEP_S, the block's end.
        idx = np.unique(np.concatenate([np.arange(0, n + 1, self._every), [n]]))
        qq = np.concatenate(([self._last[0]], stroke))
        vv = np.concatenate(([self._last[1]], v))
        states = integrate(self.plant, idx * self.dt, qq[idx], vv[idx], self.state)
        steps = np.arange(1, n + 1)
        Y = np.vstack([np.interp(steps, idx, s) for s in states])
        self._pending = (n, filters, (float(stroke[-1]), float(v[-1])))
        return stroke, v, a, Y

    @property
    def position_m(self) -> float:
        """The measured stroke at the last committed step."""
        return self._last[0]

    def commit(self, n: int, Y: np.ndarray) -> None:
        """Keep the last :meth:`advance` (whole; a shorter block is advanced again)."""
        length, filters, last = self._pending
        if n != length:
            raise ValueError("commit a whole block; recompute a shorter one with advance()")
        self._track.keep(filters)
        self.state = Y[:, -1].copy()
        self._last = last
