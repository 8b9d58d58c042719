"""The virtual rig: one simulated time line for the controller, the plant and the DAQ.

An engine thread advances simulated time to ``speed × wall time`` in blocks of at
most :data:`BLOCK_S`; in each block the controller's setpoint drives the plant at
:data:`PHYSICS_RATE_HZ`, limits are checked sample by sample (a trip cuts the block
at the offending sample), the DAQ's due samples are interpolated from the plant's
states and quantised, and scheduled faults fire.  Modbus reads and DAQ frames
therefore describe the same simulated instant; given the seed and the command
times, the data are deterministic.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from simulator.controller import Alarm, ShakerController
from simulator.daq import DaqDevice, Port
from simulator.faults import Fault, FaultLog
from simulator.modbus import ModbusEndpoint
from simulator.physics import Actuator, Damper
from simulator.plant.damper import PlantDamper
from simulator.plant.drop import DROP_VELOCITY_M_S
from simulator.sensors import SensorSet
from simulator.tiers import DropTrack, make_tier, rest_stroke

PHYSICS_RATE_HZ = 10_000.0
BLOCK_S = 0.1  # at most; at 1x a wall tick is a couple of milliseconds of simulated time
TICK_S = 0.002  # wall-clock sleep between engine steps
DROP_RECORD_S = 120.0  # a drop and the gas cooling back to ambient


@dataclass
class _Scheduled:
    at_s: float
    fault: Fault
    action: str = "begin"   # or "end" for the second half of a timed fault


@dataclass
class VirtualRig:
    """The simulated rig: damper + actuator + controller + sensors + DAQ (+ Modbus).
    ``damper``: the model tier's :class:`Damper` or the plant truth's
    :class:`PlantDamper` (:mod:`simulator.tiers`)."""

    damper: Damper | PlantDamper
    daq_port: Port
    speed: float = 1.0
    seed: int = 0
    faults: list[Fault] = field(default_factory=list)
    log: FaultLog = field(default_factory=FaultLog)
    modbus_host: str = "127.0.0.1"
    modbus_port: int = 5020
    modbus_serial: str | None = None
    actuator: Actuator = field(default_factory=Actuator)
    rig_type: str = "shaker"        # or "drop": a mass released onto the damper by a RUN command
    drop_mass_kg: float = 350.0
    drop_velocity_m_s: float = DROP_VELOCITY_M_S   # at touchdown (q = 0): the paper's landing

    def __post_init__(self) -> None:
        self.t = 0.0
        self._dt = 1.0 / PHYSICS_RATE_HZ
        # The controller's position transducer reads the measured stroke; a drop rig holds
        # the damper at q = 0 until the release.
        rest_m = rest_stroke(self.damper) if self.rig_type == "drop" else 0.0
        # Each hydraulics switching at its simulated time, as data (serve's --state file); on_state
        # is told after each one.
        self.hydraulics: list[tuple[float, bool]] = []
        self.on_state: Callable[[], None] = lambda: None
        self.controller = ShakerController(initial_position_m=rest_m, on_event=lambda m: self.log.record(self.t, m),
                                           on_hydraulics=self._hydraulics_switched)
        self.tier = make_tier(self.damper, self.actuator, self._dt, self.controller.position_m)
        self.sensors = SensorSet(seed=self.seed)
        self.daq = DaqDevice(self.daq_port, now=lambda: self.t, log=self.log, speed=self.speed, seed=self.seed)
        self.modbus = ModbusEndpoint(self.controller, host=self.modbus_host, port=self.modbus_port,
                                     serial_port=self.modbus_serial)
        self._last = self._states_at_rest()
        self._servo_drift: tuple[float, float] | None = None  # (start, m/s) of a servo null drift
        self._schedule: list[_Scheduled] = sorted(
            (_Scheduled(f.at_s if f.at_s is not None else 0.0, f) for f in self.faults if not f.after_run),
            key=lambda s: s.at_s)
        self._after_run = [f for f in self.faults if f.after_run]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rig-engine", daemon=True)
        self._drop: DropTrack | None = None
        self._released_at: float | None = None
        if self.rig_type == "drop":
            # The whole drop (touching down at q = 0, gas at ambient) is integrated once,
            # stiffly and tightly; the stream samples it from the moment of release.
            self._drop = self.tier.drop(self.drop_mass_kg, DROP_RECORD_S, self.drop_velocity_m_s)
        elif self.rig_type != "shaker":
            raise ValueError(f"rig type {self.rig_type!r}: shaker or drop")

    def _hydraulics_switched(self, on: bool) -> None:
        self.hydraulics.append((self.t, on))
        self.on_state()

    # ----- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        """Open the endpoints and start the simulated clock."""
        self.modbus.start()
        self.daq.start()
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self.modbus.close()
        self.daq.close()

    def _run(self) -> None:
        wall0, sim0 = time.monotonic(), self.t
        while not self._stop.is_set():
            self.step_to(sim0 + self.speed * (time.monotonic() - wall0))
            self._stop.wait(TICK_S)

    # ----- simulation --------------------------------------------------------------------
    def step_to(self, t_target: float) -> None:
        """Advance simulated time to ``t_target`` (whole physics steps)."""
        while self.t + 0.5 * self._dt < t_target:
            n = int(min(BLOCK_S, t_target - self.t) / self._dt + 0.5)
            self._block(max(n, 1))

    def _states_at_rest(self) -> tuple[float, float, float, np.ndarray]:
        return (self.controller.position_m, 0.0, 0.0, self.tier.rest())

    def _block(self, n: int) -> None:
        if self._drop is not None:
            self._drop_block(n, self._drop)
            return
        t = self.t + self._dt * np.arange(1, n + 1)
        u = self.controller.setpoint(t)
        if self._servo_drift is not None:
            t0, rate = self._servo_drift
            u = u + rate * np.maximum(t - t0, 0.0)
        stroke, v, a, X = self.tier.advance(u)
        force = self.tier.axle_force(stroke, v, a, X)
        trip = self.controller.trip_index(stroke, force) if self.controller.hydraulics_on else None
        if trip is not None and trip[0] + 1 < n:
            n = trip[0] + 1
            t, u, force = t[:n], u[:n], force[:n]
            stroke, v, a, X = self.tier.advance(u)
        self.tier.commit(n, X)
        self._sample(t, stroke, v, a, X)
        t_end = float(t[-1])
        self._last = (float(stroke[-1]), float(v[-1]), float(a[-1]), X[:, -1].copy())
        self.t = t_end
        if trip is not None:
            i, alarm = trip
            limit = (f"force {force[-1]:.0f} N" if alarm == Alarm.FORCE_LIMIT else f"stroke {stroke[-1] * 1e3:.2f} mm")
            self.controller.position_m = float(stroke[-1])
            self.controller.trip_on_limit(alarm, t_end, float(stroke[-1]), float(force[-1]), limit)
        self.controller.update(t_end, float(stroke[-1]), float(v[-1]), float(force[-1]))
        self._fire_faults()

    def _drop_block(self, n: int, rec: DropTrack) -> None:
        """Drop rig: RUN releases the mass; the load cell under the axle reads the damper force.
        ``rec`` is the whole drop, integrated once."""
        t = self.t + self._dt * np.arange(1, n + 1)
        c = self.controller
        if self._released_at is None and c.holding["mode"] == 2 and c.hydraulics_on:
            self._released_at = self.t
            self.log.record(self.t, f"drop: {self.drop_mass_kg:g} kg touching down at q = 0 at "
                                    f"{self.drop_velocity_m_s:g} m/s")
        ts = self.daq.due_times(float(t[-1]))
        if len(ts):
            since = ts - self._released_at if self._released_at is not None else np.full(len(ts), -1.0)
            counts, over = self.sensors.counts(rec.channels(since), ts)
            self.daq.emit(counts, over)
        released = self._released_at is not None
        tt = float(t[-1]) - (self._released_at or 0.0)
        stroke_m = rec.stroke(tt) if released else rec.stroke(-1.0)
        if released and tt > rec.duration_s and c.holding["mode"] == 2:
            c.write_holding(0, [0])  # the drop is over: IDLE, the mass resting on the damper (one drop per run)
        self.t = float(t[-1])
        c.update(self.t, stroke_m, 0.0, 0.0)
        self._fire_faults()

    def _sample(self, t: np.ndarray, stroke: np.ndarray, v: np.ndarray, a: np.ndarray, X: np.ndarray) -> None:
        ts = self.daq.due_times(float(t[-1]))
        if not len(ts):
            return
        grid = np.concatenate(([self.t], t))
        last_stroke, last_v, last_a, last_X = self._last
        strokes, vs, as_ = (np.interp(ts, grid, np.concatenate(([last], x)))
                            for last, x in ((last_stroke, stroke), (last_v, v), (last_a, a)))
        Xs = np.vstack([np.interp(ts, grid, np.concatenate(([last], x))) for last, x in zip(last_X, X, strict=True)])
        si = self.tier.channels(strokes, vs, as_, Xs)
        counts, over = self.sensors.counts(si, ts)
        self.daq.emit(counts, over)

    def inject(self, fault: Fault) -> None:
        """Apply ``fault`` now (its time is ignored): a client driving simulated time
        itself times faults against what it does, e.g. a phase of the acquisition.
        Not for ``modbus-down``: its end starts the Modbus server."""
        self._apply(_Scheduled(self.t, fault))

    def _fire_faults(self) -> None:
        if self._after_run and self.controller.first_run_s is not None:
            self._schedule += [_Scheduled(self.controller.first_run_s + (f.at_s or 0.0), f) for f in self._after_run]
            self._schedule.sort(key=lambda s: s.at_s)
            self._after_run = []
        while self._schedule and self._schedule[0].at_s <= self.t:
            item = self._schedule.pop(0)
            self._apply(item)

    def _later(self, at_s: float, fault: Fault) -> None:
        self._schedule.append(_Scheduled(at_s, fault, "end"))
        self._schedule.sort(key=lambda s: s.at_s)

    def _apply(self, item: _Scheduled) -> None:
        f, t = item.fault, self.t
        value = f.value or 0.0  # parse_fault gives a value to every kind that reads one below
        if item.action == "end":
            if f.kind == "modbus-down":
                self.modbus.start()
                self.log.record(t, "fault end: Modbus server back")
            elif f.kind == "hydraulic-loss":
                self.controller.supply_lost = False
                self.log.record(t, "fault end: hydraulic supply restored")
            return
        if f.kind == "corrupt":
            self.daq.corrupt_probability = value
            self.log.record(t, f"fault: DAQ byte corruption, probability {value:g} per byte")
        elif f.kind == "drop":
            self.daq.drop_probability = value
            self.log.record(t, f"fault: DAQ frames dropped on the line, probability {value:g}")
        elif f.kind == "overflow":
            self.daq.overflow_burst(int(value))
            self.log.record(t, f"fault: DAQ-internal overflow, {int(value)} samples lost")
        elif f.kind == "stall":
            self.daq.stall(t + value)
            self.log.record(t, f"fault: serial line stalls for {value:g} s")
        elif f.kind == "disconnect":
            self.daq.port.disconnect()
            self.log.record(t, "fault: DAQ link disconnected")
        elif f.kind == "modbus-down":
            self.modbus.stop()
            self.log.record(t, f"fault: Modbus server gone for {value:g} s")
            self._later(t + value, f)
        elif f.kind == "hydraulic-loss":
            self.controller.supply_lost = True
            self.log.record(t, "fault: hydraulic supply pressure lost")
            if value:
                self._later(t + value, f)
        elif f.kind == "estop":
            self.log.record(t, "fault: emergency stop pressed")
            self.controller.emergency_stop(t)
        elif f.kind == "servo-drift":
            self._servo_drift = (t, value * 1e-3)
            self.log.record(t, f"fault: servo valve null drifts, actuator creeps {value:g} mm/s")
        elif f.kind == "gain":
            assert f.channel is not None  # parse_fault sets it for every gain fault
            gains = list(self.sensors.gain_error)
            gains[f.channel] = value
            self.sensors.gain_error = tuple(gains)
            self.log.record(t, f"fault: channel {f.channel} gain off by {value:+g} (relative)")
        elif f.kind == "drift":
            assert f.channel is not None  # parse_fault sets it for every drift
            self.sensors.drift_per_s[f.channel] = value
            self.sensors.drift_start_s[f.channel] = t
            self.log.record(t, f"fault: channel {f.channel} drifts {value:g} units/s")
