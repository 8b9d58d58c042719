"""The virtual rig in the test's own process, on a simulated clock: deterministic tests
of the acquisition with no subprocess, no socket, no engine thread and no real sleep.

    rig.drivers.shaker ── InProcessModbusClient ──▶ simulator.modbus.ControllerContext ──▶ ShakerController
    rig.drivers.daq    ── SerialLine.host ══ SerialLine.device ──▶ simulator.daq.DaqDevice
    every wait of the rig (rig.drivers.clock.Clock) ── SimClock.sleep(dt) ──▶ VirtualRig.step_to(t + dt)

With ``line_baud``, each Modbus transaction and each DAQ command takes the time an RTU
line at that rate needs for its frames (11 bits a character, 3.5 characters of silence
after each frame): the driving thread spends it on the simulated clock.

Only the thread that drives the session (the test's) moves simulated time.  After each
step the clock waits until the DAQ device has put on the line what it emitted and the
rig's DAQ reader has consumed it and waits for more: when the acquisition looks at its
samples, they are exactly those of the simulated time up to now.  Timed actions
(faults, Ctrl-C, link outages, the watchdog's heartbeat) run in that same thread at
given simulated times, so a run is the same whatever the machine's load.
"""

from __future__ import annotations

import errno
import heapq
import itertools
import math
import threading
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymodbus.constants import ExcCodes

from rig.config import DEFAULT_RIG_CONFIG, load_rig_config
from rig.drivers.daq import Calibration, Daq
from rig.drivers.registers import load_register_map
from rig.drivers.shaker import Shaker
from rig.events import Event, EventBus
from rig.session.run import Links, RunOptions, RunResult, prepare, run_lifecycle
from simulator.controller import DEVICE_IDENTIFICATION, ShakerController
from simulator.engine import PHYSICS_RATE_HZ, VirtualRig
from simulator.faults import FaultLog, parse_fault
from simulator.modbus import ControllerContext
from simulator.physics import Damper
from simulator.plant.damper import PlantDamper
from simulator.truth import load_truth

# Steady-state criteria loose enough that j settles after about half a minute of simulated
# time (the default ones take 150 s), on the change criterion without conditioning holds
# (the machine, not the criterion, is tested here); a Modbus link may be away 3 s.
TEST_CONFIG = {'criterion = "drift"': 'criterion = "change"', "max_hold_s = 300.0": "max_hold_s = 0.0",
               "force_N = 5.0": "force_N = 50.0", "pressure_bar = 0.0005": "pressure_bar = 0.1",
               "gas_temperature_C = 0.003": "gas_temperature_C = 3.0", "max_cycles = 1500": "max_cycles = 200",
               "reconnect_s = 20.0": "reconnect_s = 3.0"}
SHAKER_URL = "tcp://virtual-rig:502"      # only named in messages: nothing listens there
DAQ_URL = "socket://virtual-rig:4001"
READ_POLL_S = 0.05      # a read with nothing to read gives up after this (wall) time, like pyserial in rig.drivers.daq
HANG_S = 10.0           # wall time after which a wait in the harness is a failure, never a delay
MAX_STEP_S = 0.25       # simulated time per step: bounds what the DAQ's FIFO must hold between two drains
_HALF_STEP_S = 0.5 / PHYSICS_RATE_HZ


def quick_rig_config(folder: Path) -> Path:
    """The default rig configuration with :data:`TEST_CONFIG`'s changes, written into ``folder``."""
    text = DEFAULT_RIG_CONFIG.read_text()
    for old, new in TEST_CONFIG.items():
        assert old in text, f"{DEFAULT_RIG_CONFIG} no longer has {old!r}"
        text = text.replace(old, new)
    path = folder / "rig.toml"
    path.write_text(text)
    return path


# ----- the DAQ's serial line ---------------------------------------------------------------------------
class SerialLine:
    """A serial line in memory: :attr:`host` is what rig.drivers.daq reads and writes (pyserial's
    read/write/close), :attr:`device` the simulator's :class:`simulator.daq.Port`."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._to_host = bytearray()
        self._to_device = bytearray()
        self._host_waiting = 0          # host reads blocked on an empty line
        self.charge: Callable[[bytes | None, bytes | None], None] | None = None   # (command, answer): line time
        self.host = _HostEnd(self)
        self.device = _DeviceEnd(self)

    def wait_host_caught_up(self, timeout_s: float) -> bool:
        """Wait until the host has read all that was sent to it and waits for more: its
        reader thread has handled what it read (it only reads again once it has)."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._to_host and self._host_waiting > 0, timeout_s)


class _HostEnd:
    """pyserial as rig.drivers.daq uses it: ``read(size)`` returns what has arrived, waiting up to
    :data:`READ_POLL_S` for the first byte."""

    def __init__(self, line: SerialLine) -> None:
        self._line = line

    def read(self, size: int = 1) -> bytes:
        line = self._line
        with line._cond:
            if not line._to_host:
                line._host_waiting += 1
                line._cond.notify_all()
                line._cond.wait_for(lambda: bool(line._to_host), READ_POLL_S)
                line._host_waiting -= 1
            data = bytes(line._to_host[:size])
            del line._to_host[:size]
        return data

    def write(self, data: bytes) -> int:
        if self._line.charge is not None:
            self._line.charge(data, None)
        with self._line._cond:
            self._line._to_device += data
            self._line._cond.notify_all()
        return len(data)

    def close(self) -> None:
        pass  # nothing to release


class _DeviceEnd:
    """The simulator's side of the line (:class:`simulator.daq.Port`)."""

    url = "memory://daq"

    def __init__(self, line: SerialLine) -> None:
        self._line = line

    def read(self, timeout_s: float) -> bytes:
        line = self._line
        with line._cond:
            line._cond.wait_for(lambda: bool(line._to_device), timeout_s)
            data = bytes(line._to_device)
            line._to_device.clear()
        return data

    def write(self, data: bytes) -> None:
        if self._line.charge is not None:
            self._line.charge(None, data)
        with self._line._cond:
            self._line._to_host += data
            self._line._cond.notify_all()

    def disconnect(self) -> None:
        # rig.drivers.daq reopens a lost line by its URL, which an in-memory line does not have.
        raise NotImplementedError("the in-memory DAQ line cannot be unplugged; use simulator serve for disconnects")

    def close(self) -> None:
        pass


# ----- the controller's Modbus link --------------------------------------------------------------------
# Read Device Identification's object ids (Modbus application protocol 6.21)
OBJECT_IDS = {"VendorName": 0, "ProductCode": 1, "MajorMinorRevision": 2, "VendorUrl": 3, "ProductName": 4,
              "ModelName": 5}


@dataclass
class ModbusResponse:
    """The parts of a pymodbus response that rig.drivers.shaker reads."""

    registers: list[int] = field(default_factory=list)
    bits: list[bool] = field(default_factory=list)
    exception_code: int | None = None
    information: dict[int, bytes] = field(default_factory=dict)

    def isError(self) -> bool:  # noqa: N802 — pymodbus's name
        return self.exception_code is not None


def _complete(coroutine: Coroutine[Any, Any, Any]) -> Any:
    """Run a coroutine that never awaits (the server context's methods) to its result."""
    try:
        coroutine.send(None)
    except StopIteration as done:
        return done.value
    coroutine.close()
    raise RuntimeError("ControllerContext awaited: it no longer answers synchronously")


BITS_PER_CHAR = 11          # RTU: start, 8 data, parity (or a second stop), stop
RTU_GAP_CHARS = 3.5         # the silence that ends an RTU frame


@dataclass
class LineTime:
    """What an RTU line at ``baud`` costs: each frame's characters and its end gap."""

    baud: float
    transactions: int = 0
    seconds: float = 0.0

    def frames(self, *sizes: int) -> float:
        """The line time of one transaction made of frames of these sizes (bytes)."""
        t = sum(n + RTU_GAP_CHARS for n in sizes) * BITS_PER_CHAR / self.baud
        self.transactions += 1
        self.seconds += t
        return t


def _device_id_answer_bytes(objects: dict[str, str]) -> int:
    """Read Device Identification's answer: unit, function, MEI type, read code, conformity,
    more follows, next object, object count, (id, length, text) per object, CRC."""
    return 8 + sum(2 + len(text.encode()) for text in objects.values()) + 2


class InProcessModbusClient:
    """The calls rig.drivers.shaker makes of a pymodbus client, answered in the caller's thread by
    the simulator's own server context (the same tables and exceptions as ``simulator
    serve``: 2 for an address outside the map, 3 for a write the controller refuses).

    :meth:`cut` takes the link away for a while of simulated time: every request then
    raises ``ConnectionResetError``, as a client on a dead TCP peer does."""

    def __init__(self, controller: ShakerController, clock: SimClock, line: LineTime | None = None) -> None:
        self._context = ControllerContext(controller)
        self._clock = clock
        self._outages: list[tuple[float, float]] = []
        self.line = line

    def _on_line(self, request_bytes: int, answer_bytes: int) -> None:
        if self.line is not None:
            self._clock.spend(self.line.frames(request_bytes, answer_bytes))

    def cut(self, duration_s: float) -> None:
        """No answer from now on for ``duration_s`` of simulated time."""
        t = self._clock.monotonic()
        self._outages.append((t, t + duration_s))

    @property
    def link_up(self) -> bool:
        t = self._clock.monotonic()
        return not any(a <= t < b for a, b in self._outages)

    def connect(self) -> bool:
        return self.link_up

    def close(self) -> None:
        pass

    # Frame sizes (Modbus over serial line, RTU): unit id, function, the PDU, CRC (2).
    def read_input_registers(self, address: int, *, count: int = 1, device_id: int = 1) -> ModbusResponse:
        self._on_line(8, 5 + 2 * count)
        return self._read(4, address, count, device_id)

    def read_holding_registers(self, address: int, *, count: int = 1, device_id: int = 1) -> ModbusResponse:
        self._on_line(8, 5 + 2 * count)
        return self._read(3, address, count, device_id)

    def write_registers(self, address: int, values: Sequence[int], *, device_id: int = 1) -> ModbusResponse:
        self._on_line(9 + 2 * len(values), 8)
        return self._write(16, address, list(values), device_id)

    def write_coil(self, address: int, value: bool, *, device_id: int = 1) -> ModbusResponse:
        self._on_line(8, 8)
        return self._write(5, address, [value], device_id)

    def read_device_information(self, *, read_code: int | None = None, object_id: int = 0,
                                device_id: int = 1) -> ModbusResponse:
        """What ``simulator serve`` answers (0x2B/0x0E): the basic and regular objects."""
        self._on_line(7, _device_id_answer_bytes(DEVICE_IDENTIFICATION))
        self._check_link()
        return ModbusResponse(information={OBJECT_IDS[name]: text.encode()
                                           for name, text in DEVICE_IDENTIFICATION.items()})

    def _read(self, func_code: int, address: int, count: int, device_id: int) -> ModbusResponse:
        self._check_link()
        values = _complete(self._context.async_getValues(device_id, func_code, address, count))
        if isinstance(values, ExcCodes):
            return ModbusResponse(exception_code=int(values))
        return ModbusResponse(registers=list(values))

    def _write(self, func_code: int, address: int, values: list, device_id: int) -> ModbusResponse:
        self._check_link()
        code = _complete(self._context.async_setValues(device_id, func_code, address, values))
        if code is not None:
            return ModbusResponse(exception_code=int(code))
        return ModbusResponse(bits=[bool(v) for v in values] if func_code == 5 else [])

    def _check_link(self) -> None:
        if not self.link_up:
            raise ConnectionResetError(errno.ECONNRESET, "Connection reset by peer")


# ----- simulated time ----------------------------------------------------------------------------------
class SimClock:
    """:class:`rig.drivers.clock.Clock` on the virtual rig's simulated time.

    ``sleep(dt)`` advances the rig by ``dt`` in steps of at most :data:`MAX_STEP_S`,
    stopping at each timed action, and after each step waits until the rig's DAQ reader
    has consumed the stream so far.  Only the thread that made the clock may sleep on it:
    a second thread moving time would make runs depend on scheduling."""

    def __init__(self, sim: VirtualRig, line: SerialLine) -> None:
        self.sim, self.line = sim, line
        self._owner = threading.current_thread()
        self._actions: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()     # actions due at the same time run in the order given
        self._debt_s = 0.0                  # line time spent where time cannot move: paid by the next sleep
        self._sleeping = False              # inside sleep (a timed action, the device's writes): time cannot move
        self._debt_lock = threading.Lock()

    def spend(self, seconds: float) -> None:
        """Time a link takes (a line's frames): slept at once by the driving thread, or,
        from another thread or inside a sleep (a timed action), added to the next sleep."""
        if threading.current_thread() is self._owner and not self._sleeping:
            self.sleep(seconds)
        else:
            with self._debt_lock:
                self._debt_s += seconds

    def monotonic(self) -> float:
        return self.sim.t

    def at(self, t_s: float, action: Callable[[], None]) -> None:
        """Run ``action`` (in the driving thread) once simulated time reaches ``t_s``."""
        heapq.heappush(self._actions, (t_s, next(self._order), action))

    def after(self, delay_s: float, action: Callable[[], None]) -> None:
        self.at(self.sim.t + delay_s, action)

    def every(self, period_s: float, action: Callable[[], None]) -> None:
        def repeat() -> None:
            action()
            self.after(period_s, repeat)

        self.after(period_s, repeat)

    def sleep(self, seconds: float) -> None:
        if threading.current_thread() is not self._owner:
            raise RuntimeError(f"{threading.current_thread().name} slept on the simulated clock: only the thread "
                               "driving the session may move simulated time")
        outer, self._sleeping = self._sleeping, True
        try:
            self._sleep(self.sim.t + seconds)
        finally:
            self._sleeping = outer

    def _sleep(self, target: float) -> None:
        while True:
            with self._debt_lock:
                target, self._debt_s = target + self._debt_s, 0.0
            due = min(target, self.sim.t + MAX_STEP_S, self._actions[0][0] if self._actions else math.inf)
            self.sim.step_to(due)
            self._catch_up()
            while self._actions and self._actions[0][0] <= self.sim.t + _HALF_STEP_S:
                heapq.heappop(self._actions)[2]()
            if self.sim.t + _HALF_STEP_S >= target and not self._debt_s:
                return

    def _catch_up(self) -> None:
        """While the DAQ streams: wait until what it emitted is on the line and read."""
        if not self.sim.daq.streaming:
            return
        if not (self.sim.daq.wait_sent(HANG_S) and self.line.wait_host_caught_up(HANG_S)):
            raise RuntimeError(f"the rig's DAQ reader did not take the stream within {HANG_S:g} s of wall time "
                               f"(simulated t = {self.sim.t:.3f} s)")


# ----- the whole rig -----------------------------------------------------------------------------------
class InProcessRig:
    """A virtual rig and the rig package's drivers joined in memory, on one simulated clock.

    ``events`` holds every event published on ``bus`` with the simulated time it was
    published at.  The watchdog runs on simulated time too; the harness feeds it the
    heartbeat rig.drivers.shaker's thread would send (that thread waits on the wall clock), and
    the heartbeat gets through only while the Modbus link is up."""

    def __init__(self, rig_config: Path, seed: int = 0, truth: Damper | PlantDamper | None = None,
                 line_baud: float | None = None) -> None:
        """``truth``: the simulated damper, either tier (default: the nominal model); ``line_baud``: each
        Modbus transaction and DAQ command takes an RTU line's time at this rate."""
        self.rig_config = rig_config
        self.config = load_rig_config(rig_config)
        self.fault_log = FaultLog(sink=lambda line: None)
        self.line_time = LineTime(line_baud) if line_baud else None
        self.line = SerialLine()
        self.sim = VirtualRig(truth or load_truth(), self.line.device, seed=seed, log=self.fault_log)
        self.clock = SimClock(self.sim, self.line)
        if self.line_time is not None:
            self.line.charge = self._charge_daq
        self.sim.controller.wall_clock = self.clock.monotonic
        self.client = InProcessModbusClient(self.sim.controller, self.clock, self.line_time)
        self.bus = EventBus()
        self.events: list[tuple[float, Event]] = []
        self.bus.subscribe(lambda e: self.events.append((self.clock.monotonic(), e)), inline=True)
        self.register_map = load_register_map()
        self.shaker = Shaker(SHAKER_URL, self.config.limits, self.register_map, reconnect_s=self.config.reconnect_s,
                             on_event=self.bus.publish_link, client=self.client, clock=self.clock)
        self.daq = Daq(DAQ_URL, Calibration.from_file(), rate_hz=self.config.daq_rate_hz, port=self.line.host,
                       reconnect_s=self.config.reconnect_s, on_event=self.bus.publish_link)
        self.identity = ""
        self._beat = 0


    def _charge_daq(self, command: bytes | None, answer: bytes | None) -> None:
        """A DAQ command line (host to device) or its answer line (device to host, while
        not streaming) on the line: its characters and an end gap, as a frame."""
        assert self.line_time is not None
        if answer is not None and self.sim.daq.streaming:
            return                                  # frames of the stream: their own line, paced by the device
        self.clock.spend(self.line_time.frames(len(command or answer or b"")))

    def connect(self) -> None:
        """What rig.session.run.connect does, with the heartbeat on simulated time."""
        self.sim.daq.start()
        self.shaker.connect(heartbeat=False)
        timeout = self.config.limits.watchdog_timeout_s
        watchdog = self.register_map.field("watchdog_timeout")
        self.client.write_registers(watchdog.address, [watchdog.encode(timeout)], device_id=self.register_map.unit_id)
        self.clock.every(max(timeout / 4, 0.05), self._heartbeat)
        self.identity = self.daq.open()

    def _heartbeat(self) -> None:
        self._beat = (self._beat + 1) & 0xFFFF
        try:
            self.client.write_registers(self.register_map.field("heartbeat").address, [self._beat],
                                        device_id=self.register_map.unit_id)
        except ConnectionResetError:
            pass  # lost with the link: the watchdog is there for exactly that

    def inject(self, fault: str) -> None:
        """A simulator fault (``KIND[=VALUE]``, see simulator.faults), applied now.  A Modbus
        outage is :meth:`InProcessModbusClient.cut` (modbus-down would start a real server)."""
        self.sim.inject(parse_fault(f"{fault}@{self.sim.t}"))

    def when(self, phase: str, after_s: float, action: Callable[[], None], experiment: str | None = None) -> None:
        """Run ``action`` ``after_s`` simulated seconds after the acquisition first enters
        ``phase`` (of ``experiment``, or of any)."""
        armed = True

        def watch(event: Event) -> None:
            nonlocal armed
            if armed and event.kind == "phase" and event.data.get("phase") == phase and \
                    experiment in (None, event.experiment):
                armed = False
                self.clock.after(after_s, action)

        self.bus.subscribe(watch, inline=True)

    def phases(self) -> list[tuple[float, str | None, str]]:
        """(simulated time, experiment, phase) of every phase entered."""
        return [(t, e.experiment, e.data["phase"]) for t, e in self.events if e.kind == "phase"]

    def messages(self, *kinds: str) -> list[str]:
        """The messages of events of these kinds, in order (default: log lines and link notices)."""
        kinds = kinds or ("log", "link")
        return [e.data.get("message", "") for _, e in self.events if e.kind in kinds]

    def run_session(self, out: Path, letters: list[str], on_alarm: str = "abort", **hooks: Any) -> RunResult:
        """``rig run`` from ``prepare`` on, through :func:`rig.session.run.run_lifecycle`, on these
        links and this bus (both stay open: the harness closes them)."""
        prep = prepare(RunOptions(plan="standard", shaker=SHAKER_URL, daq=DAQ_URL, out=out, experiments=letters,
                                  on_alarm=on_alarm, rig_config=str(self.rig_config), date="261122"))
        return run_lifecycle(prep, links=Links(self.shaker, self.daq, self.identity, None), bus=self.bus, **hooks)

    def close(self) -> None:
        """Links first (their threads publish), then the bus and the log, then the simulator."""
        self.shaker.close()
        self.daq.close()
        self.bus.close()
        self.sim.close()
