"""The emergency stop: mode STOP and hydraulics off at once, no fade, on a Modbus
connection and a thread of its own, and a latch that keeps every motion command in
the program until the operator confirms a reset.

Its own connection, because a session or the status poll may hold the main link in a
slow transaction (a request timing out, a reconnect): the E-STOP never waits behind it.
Its own thread, because the press (a click, a key) must return at once; the writes are
made there.  Each press returns its own :class:`EstopStatus` (as ophyd's ``StatusBase``
does for a move): its writes, and its :class:`EstopDone` timed from that press.  A
second press during the first one's writes is queued behind them, sends both writes
again and gets its own result and timing, never the first one's.

Each of the two writes goes out on the first link that answers: the E-STOP's own line,
then the caller's active link (``fallback``), then a link opened for the occasion.  A
serial line takes one client: there the E-STOP has no line of its own.

The press trips the :class:`MotionLatch` before any write.  The drivers share it
(``Shaker(interlock=…)``): from the press on, hydraulics on, move, RUN and fade out
raise :class:`EStopLatched` before anything is sent, until :meth:`EStop.confirm_reset`.
STOP, hydraulics off and status reads always go through.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rig.config import Limits
from rig.drivers.clock import WALL_CLOCK, Clock
from rig.drivers.registers import RegisterMap
from rig.drivers.shaker import Shaker, ShakerError
from rig.events import Message

BUDGET_S = 0.3            # press to both writes answered by the controller
LINE_TIMEOUT_S = 0.25     # per request on the E-STOP's own line: a dead line falls back to the others quickly
SPARE_RECONNECT_S = 0.5   # a link opened for the occasion gets this long to answer


class EStopLatched(ShakerError):
    """A motion command refused, nothing sent: an E-STOP is latched until the operator
    confirms a reset."""


@dataclass(frozen=True)
class EstopDone(Message):
    """One press, handled: what failed (empty: both writes answered), the time from the
    press to the last answer, and which link(s) carried the writes."""

    failures: list[str]
    elapsed_s: float
    line: str

    @property
    def within_budget(self) -> bool:
        return not self.failures and self.elapsed_s <= BUDGET_S


class EstopStatus:
    """One press of the E-STOP, from the press to both writes answered (or failed): its
    own :class:`EstopDone`, which :meth:`wait` returns and each callback is given once."""

    def __init__(self, number: int, pressed_at: float) -> None:
        self.number = number                  # 1 for the E-STOP's first press, and so on
        self.pressed_at = pressed_at          # on the E-STOP's clock
        self.result: EstopDone | None = None
        self._finished = threading.Event()
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[EstopDone], object]] = []

    @property
    def done(self) -> bool:
        return self._finished.is_set()

    def wait(self, timeout_s: float | None = None) -> EstopDone | None:
        """This press's outcome once both writes are answered (or failed); None on timeout."""
        return self.result if self._finished.wait(timeout_s) else None

    def add_callback(self, callback: Callable[[EstopDone], object]) -> None:
        """``callback(result)`` once this press is handled (at once if it already is)."""
        with self._lock:
            if self.result is None:
                self._callbacks.append(callback)
                return
            result = self.result
        callback(result)

    def finish(self, result: EstopDone) -> None:
        with self._lock:
            self.result, callbacks = result, list(self._callbacks)
            self._finished.set()
        for callback in callbacks:
            callback(result)

    def __repr__(self) -> str:
        return f"EstopStatus(press {self.number}, {'done' if self.done else 'writing'})"


@dataclass(frozen=True)
class LatchChanged(Message):
    """The latch was tripped (``reason`` says by what) or reset by the operator."""

    latched: bool
    reason: str | None


class MotionLatch:
    """Tripped by an E-STOP; while tripped, :meth:`check` refuses every motion command
    (the :class:`rig.drivers.shaker.MotionInterlock` of the drivers that share it)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._reason: str | None = None
        self._listeners: list[Callable[[LatchChanged], object]] = []

    @property
    def latched(self) -> bool:
        return self._reason is not None

    @property
    def reason(self) -> str | None:
        return self._reason

    def subscribe(self, listener: Callable[[LatchChanged], object]) -> None:
        """Call ``listener`` on every trip and reset, from the thread that made it (keep it quick)."""
        with self._lock:
            self._listeners.append(listener)

    def trip(self, reason: str) -> None:
        with self._lock:
            self._reason = reason
            listeners = list(self._listeners)
        for listener in listeners:
            listener(LatchChanged(True, reason))

    def confirm_reset(self) -> None:
        """The operator has seen why and says the rig is safe: motion commands go out again."""
        with self._lock:
            was, self._reason = self._reason, None
            listeners = list(self._listeners)
        if was is not None:
            for listener in listeners:
                listener(LatchChanged(False, None))

    def check(self, what: str) -> None:
        reason = self._reason
        if reason is not None:
            raise EStopLatched(f"{what} refused, nothing sent: {reason}; the operator must confirm the reset first")


class EStop:
    """The E-STOP of one controller.  ``press`` returns at once with the press's own
    :class:`EstopStatus`; :meth:`wait` gives the outcome of the latest press, ``on_done``
    is told each press's.  ``fallback`` returns the caller's active link (or
    None); ``clock`` times the press to the answers (tests inject a fake one)."""

    def __init__(self, limits: Limits, register_map: RegisterMap, *,
                 fallback: Callable[[], Shaker | None] = lambda: None,
                 on_done: Callable[[EstopDone], object] = lambda done: None,
                 latch: MotionLatch | None = None, clock: Clock = WALL_CLOCK) -> None:
        self.limits, self.register_map, self.clock = limits, register_map, clock
        self.fallback, self.on_done = fallback, on_done
        self.latch = latch or MotionLatch()
        self.url: str | None = None           # the controller's address, for a link opened for the occasion
        self.last: EstopDone | None = None    # the latest press handled
        self._line: Shaker | None = None
        self._lock = threading.Lock()         # the line is swapped, never used, under it
        self._presses: queue.Queue[EstopStatus | None] = queue.Queue()   # None: closed
        self._numbers = itertools.count(1)
        self._latest: EstopStatus | None = None
        self._thread = threading.Thread(target=self._loop, name="e-stop", daemon=True)
        self._thread.start()

    # ----- the latch ------------------------------------------------------------------------------------
    @property
    def latched(self) -> bool:
        return self.latch.latched

    def confirm_reset(self) -> None:
        self.latch.confirm_reset()

    def subscribe(self, listener: Callable[[LatchChanged], object]) -> None:
        self.latch.subscribe(listener)

    # ----- the line -------------------------------------------------------------------------------------
    def open(self, url: str, *, client: Any = None) -> None:
        """The E-STOP's own connection to the controller at ``url`` (no heartbeat, used
        for nothing else), kept open until :meth:`close`; kept as it is when already open
        there.  Raises :class:`ShakerError` where nothing answers: the E-STOP then uses the
        other links.  ``client``: a pymodbus-like client (tests)."""
        self.url = url
        if url.startswith("rtu:") and client is None:
            return
        with self._lock:
            line = self._line
            if line is not None and line.url == url:
                return
            self._line = None
        if line is not None:
            line.close()
        line = Shaker(url, self.limits, self.register_map, timeout_s=LINE_TIMEOUT_S, reconnect_s=LINE_TIMEOUT_S,
                      client=client)
        try:
            line.connect(heartbeat=False)
        except BaseException:
            line.close()
            raise
        with self._lock:
            self._line = line

    # ----- the press ------------------------------------------------------------------------------------
    def press(self) -> EstopStatus:
        """Latch at once, then STOP and hydraulics off on the E-STOP's thread; this press's status."""
        status = self._latest = EstopStatus(next(self._numbers), self.clock.monotonic())
        try:
            self.latch.trip(f"E-STOP pressed at {_dt.datetime.now():%H:%M:%S}")
        finally:
            self._presses.put(status)      # the writes go out even if a listener of the latch failed
        return status

    def wait(self, timeout_s: float | None = None) -> EstopDone | None:
        """The outcome of the latest press once both writes are answered (or failed); None
        on timeout or before any press."""
        latest = self._latest
        return latest.wait(timeout_s) if latest is not None else None

    def close(self) -> None:
        self._presses.put(None)
        self._thread.join(timeout=2)
        with self._lock:
            line, self._line = self._line, None
        if line is not None:
            line.close()

    def _loop(self) -> None:
        while (status := self._presses.get()) is not None:
            done = self._stop_all(status.pressed_at)
            self.last = done
            status.finish(done)
            self.on_done(done)

    def _stop_all(self, pressed_at: float) -> EstopDone:
        """Each write on the first link that answers: the E-STOP's line, the active link, a new one."""
        failures: list[str] = []
        used: list[str] = []
        with self._lock:
            line = self._line
        spare: Shaker | None = None

        def new_link() -> Shaker | None:
            nonlocal spare
            if spare is None and self.url:
                spare = Shaker(self.url, self.limits, self.register_map, reconnect_s=SPARE_RECONNECT_S)
                spare.connect(heartbeat=False)
            return spare

        candidates: list[tuple[str, Callable[[], Shaker | None]]] = [
            ("E-STOP line", lambda: line), ("session/console link", self.fallback), ("new link", new_link)]
        try:
            for name, write in (("STOP", Shaker.stop), ("hydraulics off", lambda s: s.hydraulics(False))):
                errors = []
                for which, get in candidates:
                    try:
                        link = get()
                        if link is None:
                            continue
                        write(link)
                    except Exception as exc:  # noqa: BLE001 — the next link is tried; the watchdog is the last guard
                        errors.append(f"{which}: {exc}")
                        continue
                    used.append(which)
                    break
                else:
                    failures.append(f"{name}: " + ("; ".join(errors) or "no controller address"))
        finally:
            if spare is not None:
                spare.close()
        return EstopDone(failures, self.clock.monotonic() - pressed_at, ", ".join(dict.fromkeys(used)))
