"""The hydraulic shaker controller of the datasheet: its register file, the checks on
writes, the state machine and the setpoint it commands.

The register file is the controller's whole interface: Modbus (``modbus.py``) reads
and writes it, the rig engine (``engine.py``) asks it for the commanded stroke over a
block of simulated time and reports the measured stroke and force back.  All methods
take the controller's lock, because the Modbus server and the engine run in
different threads.

Setpoints written to the holding registers are armed by the next mode command
(STATIC or RUN), as on most servo controllers: a running waveform is never changed
under the specimen's feet.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from identify.move_profile import CONTROLLER_MOVE, MoveProfile


class State(IntEnum):
    OFF = 0
    IDLE = 1
    MOVING = 2
    AT_STATIC = 3
    RUNNING = 4
    ALARM = 5


class Alarm(IntEnum):
    NONE = 0
    STROKE_LIMIT = 1
    FORCE_LIMIT = 2
    LOW_HYDRAULIC_PRESSURE = 3
    WATCHDOG = 4
    EMERGENCY_STOP = 5


class Mode(IntEnum):
    STOP = 0
    STATIC = 1
    RUN = 2


# Datasheet addresses (docs/rig-interfaces.md §1).
HOLDING = ("mode", "waveform", "static_position", "amplitude", "frequency", "ramp_time",
           "stroke_limit_low", "stroke_limit_high", "force_limit", "watchdog_timeout", "heartbeat")
SIGNED_HOLDING = {"static_position", "stroke_limit_low", "stroke_limit_high"}
COILS = ("hydraulics_on", "alarm_reset")
INPUTS = ("state", "alarm", "position", "force", "cycles", "hydraulic_pressure", "firmware")
SIGNED_INPUTS = {"position", "force"}

FIRMWARE = 123                 # version 1.23
# What the simulator answers to Modbus Read Device Identification (0x2B/0x0E, basic and
# regular objects): it says it is a simulator, so that no record of a test on it can pass
# for one made on hardware.
DEVICE_IDENTIFICATION = {"VendorName": "damper-rig", "ProductCode": "SIMULATOR",
                         "MajorMinorRevision": f"{FIRMWARE // 100}.{FIRMWARE % 100:02d}",
                         "ProductName": "shaker controller simulator", "ModelName": "SIMULATOR"}
ACTUATOR_TRAVEL_M = 0.300      # ± mechanical travel of the actuator
FLOW_LIMIT_M_S = 0.6           # hydraulic flow: peak velocity of a waveform
MAX_FREQUENCY_HZ = 20.0
SUPPLY_PRESSURE_PA = 210e5
LOW_PRESSURE_TRIP_PA = 150e5
AT_STATIC_TOLERANCE_M = 20e-6
AT_STATIC_SPEED_M_S = 1e-3

DEFAULT_HOLDING = {"mode": 0, "waveform": 0, "static_position": 0, "amplitude": 0, "frequency": 1000,
                   "ramp_time": 20, "stroke_limit_low": -1000, "stroke_limit_high": 27000,
                   "force_limit": 5000, "watchdog_timeout": 0, "heartbeat": 0}


class RegisterError(ValueError):
    """A write the controller refuses (Modbus exception 3, illegal data value)."""


class AddressError(LookupError):
    """An address outside the register map (Modbus exception 2)."""


def to_signed(value: int) -> int:
    return value - 0x10000 if value >= 0x8000 else value


def to_unsigned(value: int) -> int:
    return int(value) & 0xFFFF


@dataclass
class _Segment:
    """The commanded stroke as a function of simulated time (SI)."""

    kind: str                       # "hold", "move", "run"
    t0: float
    start_m: float
    target_m: float = 0.0
    duration_s: float = 0.0
    amplitude_m: float = 0.0
    frequency_hz: float = 0.0
    waveform: int = 0
    ramp_s: float = 0.0
    fade_from_s: float | None = None    # start of the fade-out of a run
    fade_level: float = 1.0             # envelope when the fade-out began

    def envelope(self, t: np.ndarray) -> np.ndarray:
        ramp = max(self.ramp_s, 1e-9)
        env = np.clip((t - self.t0) / ramp, 0.0, 1.0)
        if self.fade_from_s is not None:
            env = np.minimum(env, self.fade_level * np.clip(1.0 - (t - self.fade_from_s) / ramp, 0.0, 1.0))
        return env

    def setpoint(self, t: np.ndarray) -> np.ndarray:
        if self.kind == "hold":
            return np.full(t.shape, self.start_m)
        if self.kind == "move":
            return MoveProfile.stroke(self.start_m, self.target_m, self.duration_s, t - self.t0)[0]
        phase = 2 * np.pi * self.frequency_hz * (t - self.t0)
        wave = np.sin(phase) if self.waveform == 0 else (2 / np.pi) * np.arcsin(np.sin(phase))
        return self.start_m + self.amplitude_m * self.envelope(t) * wave

    def finished(self, t: float) -> bool:
        if self.kind == "move":
            return t >= self.t0 + self.duration_s
        if self.kind == "run":
            return self.fade_from_s is not None and float(self.envelope(np.array([t]))[0]) <= 0.0
        return True


@dataclass
class ControllerStatus:
    """A consistent snapshot of the controller (engineering-free, SI)."""

    state: State
    alarm: Alarm
    position_m: float
    force_n: float
    cycles: int
    hydraulic_pressure_pa: float


@dataclass
class ShakerController:
    """The controller's register file, checks, state machine and setpoint generator."""

    initial_position_m: float = 0.0
    wall_clock: Callable[[], float] = time.monotonic
    on_event: Callable[[str], None] = lambda message: None
    on_hydraulics: Callable[[bool], None] = lambda on: None  # the switching as data (the state file)
    holding: dict[str, int] = field(default_factory=lambda: dict(DEFAULT_HOLDING))
    hydraulics_on: bool = False
    alarm: Alarm = Alarm.NONE
    position_m: float = 0.0
    velocity_m_s: float = 0.0
    force_n: float = 0.0
    sim_time_s: float = 0.0
    supply_lost: bool = False       # hydraulic supply failure (fault injection)

    def __post_init__(self) -> None:
        self._lock = threading.RLock()
        self.position_m = self.initial_position_m
        self.holding["static_position"] = round(self.initial_position_m * 1e5)
        self._segment = _Segment("hold", 0.0, self.initial_position_m)
        self._run_started_s: float | None = None
        self.first_run_s: float | None = None   # simulated time of the first RUN (faults @run+T count from it)
        self._heartbeat_wall = self.wall_clock()

    # ----- register access (Modbus side) -------------------------------------------------
    def read_holding(self, address: int, count: int) -> list[int]:
        with self._lock:
            names = self._names(HOLDING, address, count)
            return [to_unsigned(self.holding[n]) for n in names]

    def read_coils(self, address: int, count: int) -> list[bool]:
        with self._lock:
            self._names(COILS, address, count)
            return [self.hydraulics_on, False][address:address + count]

    def read_inputs(self, address: int, count: int) -> list[int]:
        with self._lock:
            self._names(INPUTS, address, count)
            values = {"state": int(self.state), "alarm": int(self.alarm),
                      "position": round(self.position_m * 1e5), "force": round(self.force_n / 10.0),
                      "cycles": self.cycles() & 0xFFFF, "hydraulic_pressure": round(self.supply_pressure_pa / 1e4),
                      "firmware": FIRMWARE}
            return [to_unsigned(values[n]) for n in INPUTS[address:address + count]]

    def write_holding(self, address: int, values: list[int]) -> None:
        """Write registers atomically: all checked first, nothing changed on refusal."""
        with self._lock:
            names = self._names(HOLDING, address, len(values))
            proposed = dict(self.holding)
            for name, raw in zip(names, values, strict=True):
                proposed[name] = to_signed(raw) if name in SIGNED_HOLDING else int(raw)
            self._check(proposed, mode_written="mode" in names)
            old_mode = self.holding["mode"]
            self.holding = proposed
            if "heartbeat" in names or "watchdog_timeout" in names:
                self._heartbeat_wall = self.wall_clock()
            if "mode" in names and (proposed["mode"] != old_mode or proposed["mode"] != Mode.RUN):
                self._apply_mode(Mode(proposed["mode"]))

    def write_coils(self, address: int, values: list[bool]) -> None:
        with self._lock:
            names = self._names(COILS, address, len(values))
            for name, value in zip(names, values, strict=True):
                if name == "hydraulics_on":
                    self._set_hydraulics(bool(value))
                elif value:
                    self._reset_alarm()

    # ----- engine side -------------------------------------------------------------------
    def setpoint(self, t: np.ndarray) -> np.ndarray:
        """Commanded stroke [m] at simulated times ``t`` within the current segment."""
        with self._lock:
            return self._segment.setpoint(t)

    def update(self, t: float, position_m: float, velocity_m_s: float, force_n: float) -> None:
        """Measured actuator state at simulated time ``t``: checks trips and advances states."""
        with self._lock:
            self.sim_time_s, self.position_m, self.velocity_m_s, self.force_n = t, position_m, velocity_m_s, force_n
            seg = self._segment
            if seg.kind == "move" and seg.finished(t) and self.holding["mode"] == Mode.RUN and self.alarm == Alarm.NONE:
                self._start_run(t)
            elif seg.kind == "run" and seg.finished(t):
                self._segment = _Segment("hold", t, seg.start_m)
                self._run_started_s = None
            self._check_trips(t)

    def trip_index(self, position_m: np.ndarray, force_n: np.ndarray) -> tuple[int, Alarm] | None:
        """First sample of a block that trips the stroke or force limit, and which."""
        with self._lock:
            low, high = self.holding["stroke_limit_low"] * 1e-5, self.holding["stroke_limit_high"] * 1e-5
            stroke_bad = (position_m < low) | (position_m > high)
            force_bad = np.abs(force_n) > self.holding["force_limit"] * 10.0
            bad = stroke_bad | force_bad
            if not bad.any():
                return None
            i = int(np.argmax(bad))
            return i, (Alarm.STROKE_LIMIT if stroke_bad[i] else Alarm.FORCE_LIMIT)

    def trip_on_limit(self, alarm: Alarm, t: float, position_m: float, force_n: float, detail: str) -> None:
        """Latch a limit trip that a block found, unless a client rewrote the limits or
        reset an alarm while the block was computed (the trip would be a stale one)."""
        with self._lock:
            if self.trip_index(np.array([position_m]), np.array([force_n])) is not None:
                self.trip(alarm, t, detail)

    def trip(self, alarm: Alarm, t: float, detail: str = "") -> None:
        """Latch an alarm: stop motion and hold the present position."""
        with self._lock:
            if self.alarm != Alarm.NONE:
                return
            self.alarm = alarm
            self.holding["mode"] = Mode.STOP
            self._segment = _Segment("hold", t, self.position_m)
            self._run_started_s = None
            self.on_event(f"trip {alarm.name.lower()} at stroke {self.position_m * 1e3:.2f} mm"
                          + (f" ({detail})" if detail else ""))

    def status(self) -> ControllerStatus:
        with self._lock:
            return ControllerStatus(self.state, self.alarm, self.position_m, self.force_n, self.cycles(),
                                    self.supply_pressure_pa)

    # ----- derived quantities ------------------------------------------------------------
    @property
    def supply_pressure_pa(self) -> float:
        return SUPPLY_PRESSURE_PA if self.hydraulics_on and not self.supply_lost else 0.0

    @property
    def state(self) -> State:
        if self.alarm != Alarm.NONE:
            return State.ALARM
        if not self.hydraulics_on:
            return State.OFF
        mode, seg = self.holding["mode"], self._segment
        if mode == Mode.STOP:
            return State.IDLE
        if seg.kind == "run":
            return State.RUNNING
        if seg.kind == "move" and not seg.finished(self.sim_time_s):
            return State.MOVING
        settled = (abs(self.position_m - seg.target_m if seg.kind == "move" else self.position_m - seg.start_m)
                   < AT_STATIC_TOLERANCE_M and abs(self.velocity_m_s) < AT_STATIC_SPEED_M_S)
        return State.AT_STATIC if settled and mode == Mode.STATIC else State.MOVING

    def cycles(self) -> int:
        if self._run_started_s is None:
            return 0
        return int(np.floor((self.sim_time_s - self._run_started_s) * self._segment.frequency_hz))

    # ----- internals ---------------------------------------------------------------------
    @staticmethod
    def _names(table: tuple[str, ...], address: int, count: int) -> tuple[str, ...]:
        if address < 0 or count < 1 or address + count > len(table):
            raise AddressError(f"addresses {address}…{address + count - 1} outside 0…{len(table) - 1}")
        return table[address:address + count]

    def _check(self, r: dict[str, int], mode_written: bool) -> None:
        low, high = r["stroke_limit_low"] * 1e-5, r["stroke_limit_high"] * 1e-5
        travel = ACTUATOR_TRAVEL_M
        if r["mode"] not in (0, 1, 2):
            raise RegisterError(f"mode {r['mode']} is not 0, 1 or 2")
        if r["waveform"] not in (0, 1):
            raise RegisterError(f"waveform {r['waveform']} is not 0 (sine) or 1 (triangle)")
        if not -travel <= low < high <= travel:
            raise RegisterError(f"stroke limits {low * 1e3:.2f}…{high * 1e3:.2f} mm are not an interval "
                                f"inside the actuator travel ±{travel * 1e3:.0f} mm")
        if not low <= self.position_m <= high:
            raise RegisterError(f"stroke limits {low * 1e3:.2f}…{high * 1e3:.2f} mm exclude the present "
                                f"position {self.position_m * 1e3:.2f} mm")
        if r["force_limit"] < 1:
            raise RegisterError("force limit 0")
        static = r["static_position"] * 1e-5
        if not low <= static <= high:
            raise RegisterError(f"static position {static * 1e3:.2f} mm outside the stroke limits")
        if r["frequency"] > MAX_FREQUENCY_HZ * 1e3:
            raise RegisterError(f"frequency {r['frequency'] / 1e3:g} Hz above {MAX_FREQUENCY_HZ:g} Hz")
        if r["mode"] != Mode.STOP and (mode_written and not self.hydraulics_on):
            raise RegisterError("mode STATIC/RUN needs hydraulics on")
        if r["mode"] != Mode.STOP and mode_written and self.alarm != Alarm.NONE:
            raise RegisterError("alarm latched: reset it first")
        if r["mode"] == Mode.RUN:
            amp, f = r["amplitude"] * 1e-5, r["frequency"] * 1e-3
            if f <= 0:
                raise RegisterError("frequency 0 in RUN")
            if static - amp < low or static + amp > high:
                raise RegisterError(f"amplitude {amp * 1e3:.2f} mm around {static * 1e3:.2f} mm crosses the "
                                    "stroke limits")
            peak = amp * f * (2 * np.pi if r["waveform"] == 0 else 4.0)
            if peak > FLOW_LIMIT_M_S:
                raise RegisterError(f"peak velocity {peak:.3f} m/s above the hydraulic flow limit "
                                    f"{FLOW_LIMIT_M_S} m/s")

    def _apply_mode(self, mode: Mode) -> None:
        t, seg = self.sim_time_s, self._segment
        static = self.holding["static_position"] * 1e-5
        if mode == Mode.STOP:
            self._segment = _Segment("hold", t, self.position_m)
            self._run_started_s = None
        elif seg.kind == "run":
            # Leaving RUN (for STATIC) fades the amplitude out around the running static position.
            if seg.fade_from_s is None:
                seg.fade_level = float(seg.envelope(np.array([t]))[0])
                seg.fade_from_s = t
                self.on_event(f"fade out after {self.cycles()} cycles")
        else:
            self._move_to(static, t)
            if mode == Mode.RUN and self._segment.finished(t):
                self._start_run(t)

    def _move_to(self, target: float, t: float) -> None:
        start = float(self._segment.setpoint(np.array([t]))[0])
        duration = CONTROLLER_MOVE.duration_s(target - start)
        self._segment = _Segment("move", t, start, target_m=target, duration_s=duration)

    def _start_run(self, t: float) -> None:
        r = self.holding
        self._segment = _Segment("run", t, r["static_position"] * 1e-5, amplitude_m=r["amplitude"] * 1e-5,
                                 frequency_hz=r["frequency"] * 1e-3, waveform=r["waveform"],
                                 ramp_s=r["ramp_time"] * 0.1)
        self._run_started_s = t
        self.on_event(f"RUN: {('sine', 'triangle')[r['waveform']]} {r['amplitude'] * 1e-2:.2f} mm at "
                      f"{r['frequency'] * 1e-3:g} Hz about {r['static_position'] * 1e-2:.2f} mm")
        if self.first_run_s is None:
            self.first_run_s = t

    def _set_hydraulics(self, on: bool) -> None:
        if on == self.hydraulics_on:
            return
        self.hydraulics_on = on
        self.holding["mode"] = Mode.STOP
        self._segment = _Segment("hold", self.sim_time_s, self.position_m)
        self._run_started_s = None
        self._heartbeat_wall = self.wall_clock()
        self.on_event(f"hydraulics {'on' if on else 'off'}")
        self.on_hydraulics(on)

    def _reset_alarm(self) -> None:
        if self.alarm == Alarm.NONE:
            return
        if self.alarm == Alarm.LOW_HYDRAULIC_PRESSURE and self.supply_lost:
            self.on_event("alarm reset refused: hydraulic supply pressure still low")
            return
        self.on_event(f"alarm {self.alarm.name.lower()} reset")
        self.alarm = Alarm.NONE
        self.holding["mode"] = Mode.STOP
        self._heartbeat_wall = self.wall_clock()

    def _check_trips(self, t: float) -> None:
        if self.alarm != Alarm.NONE or not self.hydraulics_on:
            return
        if self.supply_pressure_pa < LOW_PRESSURE_TRIP_PA:
            self.trip(Alarm.LOW_HYDRAULIC_PRESSURE, t, f"supply {self.supply_pressure_pa / 1e5:.0f} bar")
            return
        timeout = self.holding["watchdog_timeout"] * 0.1
        silent = self.wall_clock() - self._heartbeat_wall
        if timeout > 0 and silent > timeout:
            self.trip(Alarm.WATCHDOG, t, f"no heartbeat for {silent:.2f} s, timeout {timeout:g} s")
            # The program that fed it is gone, and with it the safe stop: the controller
            # switches the pump and the servo valve off itself.
            self._set_hydraulics(False)

    def emergency_stop(self, t: float) -> None:
        """The e-stop button: latch alarm 5 and switch the hydraulics off."""
        with self._lock:
            self.trip(Alarm.EMERGENCY_STOP, t)
            self.hydraulics_on = False
