"""Driver of the hydraulic shaker controller over Modbus (TCP or RTU).

The register map is data (:mod:`rig.drivers.registers`); this module offers a typed API in
SI units, checks every value against the rig's limits before anything is sent,
turns Modbus exceptions into errors that say what was refused, feeds the
controller's watchdog from a heartbeat thread, and reconnects with back-off when
the link drops.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import urlparse

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerType

from rig.config import Limits
from rig.drivers.clock import WALL_CLOCK, Clock
from rig.drivers.peer_identity import OBJECT_NAMES
from rig.drivers.registers import ControllerState, Mode, RegisterMap, load_register_map
from rig.errors import AddressError, BadInput, RigFault
from rig.events import LinkCondition, LinkNotice

EXCEPTION_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                   4: "device failure", 6: "device busy"}
RTU_BAUDRATE = 115200


# Once a request has waited a lost link's whole reconnect time in vain, each later one in
# the same outage gets this long: a safe stop's steps after an abort on a lost link took a
# reconnect time each, and the console said the stop had not completed 1 min 47 s after the loss.
GIVEN_UP_TRY_S = 0.5

class ShakerError(RigFault):
    """The controller refused a command or reported an alarm."""


class ShakerLinkError(ShakerError):
    """The Modbus link is gone and did not come back within the reconnect time."""


class ShakerTimeout(ShakerError):
    """The controller did not reach the awaited state in time."""


class AlarmError(ShakerError):
    """The controller tripped (state ALARM)."""

    def __init__(self, status: ShakerStatus) -> None:
        super().__init__(f"shaker alarm: {status.alarm} (stroke {status.position_m * 1e3:.2f} mm, "
                         f"force {status.force_n / 1e3:.2f} kN)")
        self.status = status


class LimitError(BadInput):
    """A command outside the rig's limits, refused before anything is sent."""


class MotionInterlock(Protocol):
    """What may veto a command that can set the actuator moving (an E-STOP's latch,
    :class:`rig.drivers.estop.MotionLatch`): ``check`` raises, naming ``what``, to refuse it."""

    def check(self, what: str) -> None: ...


@dataclass(frozen=True)
class ShakerAddress:
    """Where the controller is: Modbus TCP (host, port) or Modbus RTU (device path)."""

    url: str
    host: str | None = None
    port: int | None = None
    device: str | None = None

    @classmethod
    def parse(cls, url: str) -> ShakerAddress:
        """Checks the form only; whether anything answers there is :meth:`Shaker.connect`'s business."""
        parsed = urlparse(url)
        try:
            port = parsed.port
        except ValueError:
            if parsed.scheme == "tcp":
                port_text = parsed.netloc.rpartition(":")[2]
                raise AddressError(f"shaker address {url!r}: port {port_text!r} is not a TCP port (1-65535)") from None
            port = None
        if parsed.scheme == "tcp" and parsed.hostname and port:
            return cls(url, host=parsed.hostname, port=port)
        if parsed.scheme == "rtu" and parsed.path:
            return cls(url, device=parsed.path)
        raise AddressError(f"shaker address {url!r}: expected tcp://HOST:PORT or rtu:///dev/DEVICE")


@dataclass(frozen=True)
class ShakerStatus:
    state: ControllerState
    alarm: str
    position_m: float
    force_n: float
    cycles: int
    hydraulic_pressure_pa: float


def modbus_client(address: ShakerAddress, timeout_s: float) -> ModbusTcpClient | ModbusSerialClient:
    if address.device:
        return ModbusSerialClient(address.device, framer=FramerType.RTU, baudrate=RTU_BAUDRATE, timeout=timeout_s,
                                  retries=0)
    assert address.host is not None and address.port is not None  # parse() gives one or the other
    return ModbusTcpClient(address.host, port=address.port, timeout=timeout_s, retries=0)


def probe_controller(address: ShakerAddress, register_map: RegisterMap, timeout_s: float = 1.0) -> str | None:
    """What answers Modbus at ``address``, in words ("a Modbus controller in state OFF");
    None where nothing does.  Reads the state register only: nothing is written."""
    client = modbus_client(address, timeout_s)
    state = register_map.field("state")
    try:
        if not client.connect():
            return None
        answer = client.read_input_registers(state.address, count=1, device_id=register_map.unit_id)
    except (ModbusException, OSError):
        return None
    finally:
        client.close()
    if answer.isError():
        code = int(getattr(answer, "exception_code", 0) or 0)
        return f"a Modbus device (exception {code}: {EXCEPTION_NAMES.get(code, 'unknown')})"
    word = int(answer.registers[0])
    states = register_map.states
    return f"a Modbus controller in state {states[word] if word < len(states) else word}"


def check_waveform(limits: Limits, static_m: float, amplitude_m: float, frequency_hz: float,
                   waveform: str = "sine") -> list[str]:
    """Every way a waveform breaks the limits (empty when it is fine)."""
    problems = []
    low, high = limits.stroke_low_m, limits.stroke_high_m
    if not low <= static_m <= high:
        problems.append(f"static position {static_m * 1e3:.2f} mm outside the stroke limits "
                        f"{low * 1e3:.1f}…{high * 1e3:.1f} mm")
    if static_m - amplitude_m < low or static_m + amplitude_m > high:
        problems.append(f"stroke {(static_m - amplitude_m) * 1e3:.1f}…{(static_m + amplitude_m) * 1e3:.1f} mm "
                        f"crosses the stroke limits {low * 1e3:.1f}…{high * 1e3:.1f} mm")
    if not 0 < frequency_hz <= limits.max_frequency_hz:
        problems.append(f"frequency {frequency_hz:g} Hz outside 0…{limits.max_frequency_hz:g} Hz")
    if waveform not in ("sine", "triangle"):
        problems.append(f"waveform {waveform!r} is not sine or triangle")
    peak = amplitude_m * frequency_hz * (2 * math.pi if waveform == "sine" else 4.0)
    if peak > limits.max_velocity_m_s:
        problems.append(f"peak velocity {peak:.3f} m/s above the hydraulic flow limit {limits.max_velocity_m_s} m/s")
    return problems


class Shaker:
    """Typed, limit-checked access to the shaker controller."""

    def __init__(self, url: str, limits: Limits, register_map: RegisterMap | None = None, *,
                 timeout_s: float = 1.0, reconnect_s: float = 20.0,
                 on_event: Callable[[LinkNotice], object] = lambda notice: None,
                 client: Any = None, clock: Clock = WALL_CLOCK, interlock: MotionInterlock | None = None) -> None:
        """``client``: a pymodbus-like client to use instead of one made from ``url``
        (tests inject faults through it).  ``interlock``: asked before every command that
        can start motion (hydraulics on, move, RUN, fade out); STOP, hydraulics off and
        reads are never vetoed."""
        address = self.address = ShakerAddress.parse(url)
        self.url, self.limits, self.clock, self.interlock = url, limits, clock, interlock
        self.map = register_map or load_register_map()
        self.reconnect_s, self.on_event = reconnect_s, on_event
        self._client = client if client is not None else modbus_client(address, timeout_s)
        self._lock = threading.RLock()
        # One outage, said once: when it began (the shaker's clock; None while the link
        # answers) and whether a request has given up on it yet.  Every later request that
        # fails in the same outage says how long it has lasted, never a shorter patience.
        self._lost_since: float | None = None
        self._given_up = False
        self._heartbeat_stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        self._beat = 0

    # ----- connection --------------------------------------------------------------------
    def _unresolved(self) -> str:
        """Why nothing answered, where the name says it: a host name that does not resolve
        (pymodbus only reports that no connection was made)."""
        if self.address.host is None:
            return ""
        try:
            socket.getaddrinfo(self.address.host, self.address.port)
        except OSError:
            return f" (the host name {self.address.host!r} is not known here)"
        return ""

    def connect(self, heartbeat: bool = True) -> None:
        """Open the link, write the rig's limits and watchdog, start the heartbeat."""
        with self._lock:
            try:
                answered = self._client.connect()
            except OSError as exc:
                answered, why = False, f" ({exc})"
            else:
                why = ""
            if not answered:
                raise ShakerLinkError(f"no Modbus controller answers at {self.url}{why or self._unresolved()}")
        lim = self.limits
        try:
            # The link was never up: no reconnect time to wait out (something else may have
            # answered the connection, e.g. the DAQ on a swapped address).
            self._write_holding({"stroke_limit_low": lim.stroke_low_m, "stroke_limit_high": lim.stroke_high_m,
                                 "force_limit": lim.force_limit_n}, patience_s=0.0)
        except ShakerLinkError:
            raise ShakerLinkError(f"no Modbus controller answers at {self.url}: the line opened, but its first "
                                  f"request (unit {self.map.unit_id}) got no Modbus answer") from None
        if heartbeat:
            self._write_holding({"watchdog_timeout": lim.watchdog_timeout_s, "heartbeat": 0})
            self._heartbeat = threading.Thread(target=self._heartbeat_loop, name="shaker-heartbeat", daemon=True)
            self._heartbeat.start()

    def disable_watchdog(self) -> None:
        """For manual commands: no program will feed the watchdog after they return."""
        self._write_holding({"watchdog_timeout": 0.0})

    def close(self) -> None:
        self._heartbeat_stop.set()
        if self._heartbeat is not None:
            self._heartbeat.join(timeout=2)
        with self._lock:
            self._client.close()

    @contextmanager
    def link_patience(self, reconnect_s: float) -> Iterator[None]:
        """Within the block, a lost link is given ``reconnect_s`` to come back."""
        saved, self.reconnect_s = self.reconnect_s, reconnect_s
        try:
            yield
        finally:
            self.reconnect_s = saved

    def __enter__(self) -> Shaker:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ----- commands ----------------------------------------------------------------------
    def status(self, patience_s: float | None = None) -> ShakerStatus:
        """The controller's state; ``patience_s``: how long a lost link is reconnected for
        (default the reconnect time; a status poll's is short: it must not hold the link's
        lock against the session's commands for a whole reconnect time)."""
        raw = self._read("inputs", patience_s, lock_timeout_s=patience_s)
        state, alarm = int(raw["state"]), int(raw["alarm"])
        if state >= len(self.map.states):
            raise ShakerError(f"the controller at {self.url} reports state word {state}, which its register map "
                              f"{self.map.source} does not name (states has {len(self.map.states)})")
        return ShakerStatus(self.map.states[state],
                            self.map.alarms[alarm] if alarm < len(self.map.alarms) else f"alarm {alarm}",
                            raw["position"], raw["force"], int(raw["cycles"]), raw["hydraulic_pressure"])

    def identify(self) -> dict[str, str]:
        """Who the controller says it is: the Modbus device identification objects where it
        offers them (basic and regular), and the map's firmware register."""
        found: dict[str, str] = {}
        try:
            info = self._call("read_device_information", read_code=0x02, object_id=0x00,
                              what="read device identification")
        except ShakerLinkError:
            raise
        except ShakerError:
            info = {}   # not offered (illegal function): the firmware register alone identifies it
        for key, value in info.items():
            text = value.decode("ascii", "replace") if isinstance(value, bytes) else str(value)
            found[OBJECT_NAMES.get(key, f"object_{key}")] = text.strip()
        if "firmware" in {f.name for f in self.map.table("inputs")}:
            found["firmware"] = f"{self._read('inputs')['firmware']:.2f}"
        return found

    def hydraulics(self, on: bool) -> None:
        if on:
            self._may_move("hydraulics on")
        self._write_coil("hydraulics_on", on)

    def reset_alarm(self) -> None:
        self._write_coil("alarm_reset", True)

    def move_to(self, static_m: float, switch_on: bool = False) -> None:
        """Move to a static position (state MOVING, then AT_STATIC); with ``switch_on``
        the hydraulics are switched on first where they are off.  A position outside
        the limits is refused before anything is sent, hydraulics included."""
        lim = self.limits
        if not lim.stroke_low_m <= static_m <= lim.stroke_high_m:
            raise LimitError(f"static position {static_m * 1e3:.2f} mm outside the stroke limits "
                             f"{lim.stroke_low_m * 1e3:.1f}…{lim.stroke_high_m * 1e3:.1f} mm")
        self._may_move(f"move to {static_m * 1e3:.2f} mm")
        if switch_on and self.status().state is ControllerState.OFF:
            self.hydraulics(True)
        self._write_holding({"static_position": static_m})
        self._write_holding({"mode": self.map.modes[Mode.STATIC]})

    def run(self, static_m: float, amplitude_m: float, frequency_hz: float, waveform: str = "sine",
            ramp_s: float = 2.0) -> None:
        """Start a waveform around a static position, faded in over ``ramp_s``."""
        problems = check_waveform(self.limits, static_m, amplitude_m, frequency_hz, waveform)
        if problems:
            raise LimitError("; ".join(problems))
        self._may_move("RUN")
        self._write_holding({"waveform": self.map.waveforms[waveform], "static_position": static_m,
                             "amplitude": amplitude_m, "frequency": frequency_hz, "ramp_time": ramp_s})
        self._write_holding({"mode": self.map.modes[Mode.RUN]})

    def fade_out(self) -> None:
        """Fade the waveform out over its ramp time and stay at the static position."""
        self._may_move("fade out")   # a move to the static position: after an E-STOP only STOP holds
        self._write_holding({"mode": self.map.modes[Mode.STATIC]})

    def stop(self) -> None:
        """Stop motion and hold the present position."""
        self._write_holding({"mode": self.map.modes[Mode.STOP]})

    def wait_for(self, states: set[ControllerState], timeout_s: float, poll_s: float = 0.02) -> ShakerStatus:
        """Poll until the controller is in one of ``states``; an alarm raises :class:`AlarmError`."""
        deadline = self.clock.monotonic() + timeout_s
        while True:
            st = self.status()
            if st.state in states:
                return st
            if st.state is ControllerState.ALARM:
                raise AlarmError(st)
            if self.clock.monotonic() > deadline:
                raise ShakerTimeout(f"controller still {st.state} after {timeout_s:g} s (waiting for "
                                    f"{' or '.join(sorted(states))})")
            self.clock.sleep(poll_s)

    def veto(self, what: str) -> str | None:
        """Why the interlock would refuse ``what`` now (None: it would go out)."""
        try:
            self._may_move(what)
        except ShakerError as exc:
            return str(exc)
        return None

    def _may_move(self, what: str) -> None:
        """Ask the interlock before anything that can set the actuator moving is sent."""
        if self.interlock is not None:
            self.interlock.check(what)

    # ----- register access ---------------------------------------------------------------
    def _read(self, table: str, patience_s: float | None = None, lock_timeout_s: float | None = None
              ) -> dict[str, float]:
        fields = self.map.table(table)
        first, last = fields[0].address, fields[-1].address
        reader = {"inputs": "read_input_registers", "holding": "read_holding_registers"}[table]
        words = self._call(reader, first, count=last - first + 1, patience_s=patience_s, lock_timeout_s=lock_timeout_s)
        return {f.name: f.decode(words[f.address - first]) for f in fields}

    def _write_holding(self, values: dict[str, float], patience_s: float | None = None) -> None:
        fields = sorted((self.map.field(n) for n in values), key=lambda f: f.address)
        words = {f.address: f.encode(values[f.name]) for f in fields}
        # Contiguous runs go out as one write-multiple request, so the controller checks
        # them together (e.g. a new static position with its amplitude).
        run: list[int] = []
        for addr in sorted(words) + [None]:
            if run and (addr is None or addr != run[-1] + 1):
                self._call("write_registers", run[0], [words[a] for a in run], patience_s=patience_s,
                           what=", ".join(f"{f.name}={values[f.name]:g}" for f in fields if f.address in run))
                run = []
            if addr is not None:
                run.append(addr)

    def _write_coil(self, name: str, value: bool) -> None:
        self._call("write_coil", self.map.field(name).address, bool(value), what=f"{name}={int(value)}")

    def _call(self, method: str, *args, what: str = "", patience_s: float | None = None,
              lock_timeout_s: float | None = None, **kwargs):
        """One request; a lost link is reconnected for ``patience_s`` (default: the
        reconnect time), 0 giving up at once without a word (the heartbeat's way).
        ``lock_timeout_s``: how long to wait for another thread's request (default: as
        long as it takes; a status poll does not wait out another's reconnect)."""
        patience = self.reconnect_s if patience_s is None else patience_s
        if not self._lock.acquire(timeout=-1 if lock_timeout_s is None else max(lock_timeout_s, 0.0)):
            lost = self._lost_since
            # Said the same way each time, so that a window logs it once, not once a second
            raise ShakerLinkError(f"Modbus link to {self.url} busy with another request" if lost is None else
                                  f"Modbus link to {self.url} lost: another request is reconnecting it")
        try:
            if self._given_up:   # this outage has had its whole reconnect time already: one quick try each
                patience = min(patience, GIVEN_UP_TRY_S)
            deadline = None
            delay = 0.05
            while True:
                try:
                    result = getattr(self._client, method)(*args, device_id=self.map.unit_id, **kwargs)
                except (ModbusException, OSError) as exc:
                    # pymodbus reports a dead peer either way (ConnectionResetError, broken
                    # pipe, timeouts): all of them are a lost link, never a crash.
                    now = self.clock.monotonic()
                    if self._lost_since is None and patience > 0:   # the heartbeat's one try says nothing
                        self._lost_since = now
                        self.on_event(LinkNotice("controller", LinkCondition.LOST,
                                                  f"Modbus link to {self.url} lost ({exc}); reconnecting"))
                    deadline = deadline or now + patience
                    if now >= deadline:
                        raise ShakerLinkError(self._not_back(patience, now, exc)) from None
                    self._reconnect()
                    self.clock.sleep(delay)
                    delay = min(2 * delay, 1.0)
                    continue
                if self._lost_since is not None:
                    self._lost_since, self._given_up = None, False
                    self.on_event(LinkNotice("controller", LinkCondition.BACK, f"Modbus link to {self.url} back"))
                if result.isError():
                    code = int(getattr(result, "exception_code", 0) or 0)
                    raise ShakerError(f"controller refused {what or method} "
                                      f"(Modbus exception {code}: {EXCEPTION_NAMES.get(code, 'unknown')})")
                if method == "read_device_information":
                    return result.information
                return result.bits if method.endswith("coils") else result.registers
        finally:
            self._lock.release()

    def _not_back(self, patience: float, now: float, exc: BaseException) -> str:
        """Why a request gave up: the first time in an outage, the reconnect time it waited;
        after that, how long the outage has lasted (a safe stop's quick tries said "not back
        within 0.5 s" beside "within 20 s", as if the link had been waited for less)."""
        if self._lost_since is None:      # patience 0 (the heartbeat) tried once: no reconnect time to speak of
            return f"Modbus link to {self.url} lost ({exc})"
        if not self._given_up and patience >= self.reconnect_s:    # a poll's short patience is not giving up
            self._given_up = True
            return f"Modbus link to {self.url} lost and not back within {patience:g} s ({exc})"
        if not self._given_up:
            return f"Modbus link to {self.url} lost {now - self._lost_since:.0f} s ago, not back yet ({exc})"
        return f"Modbus link to {self.url} still not back, {now - self._lost_since:.0f} s after it was lost ({exc})"

    def _reconnect(self) -> None:
        try:
            self._client.close()
            self._client.connect()
        except OSError:
            pass  # the next request tells whether the link is back

    def _heartbeat_loop(self) -> None:
        period = max(self.limits.watchdog_timeout_s / 4, 0.05)
        failing = False
        while not self._heartbeat_stop.wait(period):
            self._beat = (self._beat + 1) & 0xFFFF
            try:
                # One try per beat: reconnecting is the business of the commands, and a
                # beat that waited would hold the link's lock against them.
                self._write_holding({"heartbeat": self._beat}, patience_s=0.0)
            except Exception as exc:  # noqa: BLE001 — a failing heartbeat is said once; the watchdog then trips
                if not failing:
                    self.on_event(LinkNotice("controller", LinkCondition.HEARTBEAT_FAILING,
                                             f"heartbeat failing: {exc}; the controller's watchdog stops the "
                                             f"shaker {self.limits.watchdog_timeout_s:g} s after the last beat"))
                failing = True
            else:
                if failing:
                    self.on_event(LinkNotice("controller", LinkCondition.HEARTBEAT_BACK, "heartbeat back"))
                failing = False
