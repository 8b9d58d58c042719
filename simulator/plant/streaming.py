"""The plant advanced block by block in simulated time, for the served rig: the
actuator tracks the controller's setpoint at the engine's rate and the plant's states
are integrated on the one grid every use shares (:data:`simulator.plant.integrator.STEP_S`
counted from the start), whatever the engine's blocks: a block's states after its last
grid node come from a provisional step to the block's end that is shown but never kept,
so the next block starts again from that node.  Offline (:mod:`simulator.plant.sequence`)
and served records therefore integrate the same nodes and agree to the iteration's
tolerance, not to the discretisation's error."""

from __future__ import annotations

import numpy as np

from simulator.physics import Actuator, ActuatorTrack
from simulator.plant.damper import PlantDamper
from simulator.plant.integrator import STEP_S, integrate, states_at


class StreamingPlantTruth:
    """The plant's counterpart of :class:`simulator.physics.StreamingPlant`:
    :meth:`advance` returns the measured stroke, velocity, acceleration and the plant's
    six states (6, n) at the next steps; :meth:`commit` keeps them."""

    def __init__(self, plant: PlantDamper, actuator: Actuator, dt_s: float, position_m: float) -> None:
        self.plant, self.dt = plant, dt_s
        self._track = ActuatorTrack(actuator, dt_s, position_m)
        self._every = max(int(round(STEP_S / dt_s)), 1)
        self._node = plant.rest_state(position_m)   # the states at the last grid node
        # Stroke and velocity at that node and at the committed steps after it.
        self._tail = (np.array([position_m]), np.array([0.0]))
        self.state = self._node.copy()               # the states at the last committed step
        self._pending: tuple = (0, None, None)

    def advance(self, setpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        stroke, v, a, filters = self._track.track(setpoint)
        n = len(setpoint)
        qq = np.concatenate((self._tail[0], stroke))
        vv = np.concatenate((self._tail[1], v))
        behind = len(self._tail[0]) - 1              # committed steps since the node
        end = behind + n
        idx = np.unique(np.concatenate([np.arange(0, end + 1, self._every), [end]]))
        states = integrate(self.plant, idx * self.dt, qq[idx], vv[idx], self._node)
        Y = states_at(self.plant, idx * self.dt, qq[idx], vv[idx], states, np.arange(behind + 1, end + 1) * self.dt)
        last_node = (end // self._every) * self._every
        node_state = states[:, int(np.searchsorted(idx, last_node))]
        self._pending = (n, filters, node_state, (qq[last_node:], vv[last_node:]))
        return stroke, v, a, Y

    @property
    def position_m(self) -> float:
        """The measured stroke at the last committed step."""
        return float(self._tail[0][-1])

    def commit(self, n: int, Y: np.ndarray) -> None:
        """Keep the last :meth:`advance` (whole; a shorter block is advanced again)."""
        length, filters, node_state, tail = self._pending
        if n != length:
            raise ValueError("commit a whole block; recompute a shorter one with advance()")
        self._track.keep(filters)
        self._node = node_state.copy()
        self._tail = (tail[0].copy(), tail[1].copy())
        self.state = Y[:, -1].copy()
