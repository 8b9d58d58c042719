"""Events of a session and the bus that carries them to subscribers (journal, dataset
writer, progress display, live view), in the spirit of Bluesky's documents.

Inline subscribers (the session log, the dataset writer) run in the publishing
thread because the data depend on them: their errors reach the publisher, and so the
session's error boundary.  Every other subscriber (a terminal progress display, the
GUI) gets its own queue and thread, so the acquisition never waits on it; its errors
are logged (``rig.events``) with their traceback, and the session goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any


class Phase(StrEnum):
    """The acquisition's states (rig.session.acquisition); a ``phase`` event enters one."""

    IDLE = "idle"
    MOVING = "moving"
    SETTLING = "settling"
    CAPTURING = "capturing"
    STOPPING = "stopping"
    ALARM = "alarm"


class Kind(StrEnum):
    """Every kind of event a session publishes, declared once with its fields
    (:data:`FIELDS`; a publisher that leaves one out is a bug, raised at once).
    Subscribers read the fields; ``message`` is prose for people only."""

    SESSION_START = "session-start"          # shaker, daq (addresses), identity (the DAQ's *IDN?)
    PHASE = "phase"                          # phase (Phase); moving: target_mm; capturing: cycles; stopping: reason;
    #                                          alarm: message
    PROGRESS = "progress"                    # phase; settling: cycles, change {channel: |Δ block mean|}
    #                                          [drift criterion: bias_sigma, ratio, drift]; capturing: fraction
    EXPERIMENT_DONE = "experiment-done"      # file, samples, lost (in the window), flags: on disk, in dataset.json
    EXPERIMENT_FAILED = "experiment-failed"  # message: skipped after an alarm (--on-alarm skip)
    ALARM = "alarm"                          # message: the controller's alarm, as it ended the experiment
    LINK = "link"                            # link ("controller", "DAQ"), state (LinkCondition), message
    PREDICTION = "prediction"                # rig_time_left_s: the rest of the plan predicted again (rig
    #                                          seconds), basis (what it was predicted from), message
    LOG = "log"                              # message: anything else worth a line
    SESSION_END = "session-end"              # message: the status written to session.json; exit_code


FIELDS: dict[Kind, tuple[str, ...]] = {
    Kind.SESSION_START: ("shaker", "daq", "identity"),
    Kind.PHASE: ("phase",),
    Kind.PROGRESS: ("phase",),
    Kind.EXPERIMENT_DONE: ("file", "samples", "lost", "flags"),
    Kind.EXPERIMENT_FAILED: ("message",),
    Kind.ALARM: ("message",),
    Kind.LINK: ("link", "state", "message"),
    Kind.PREDICTION: ("rig_time_left_s", "basis", "message"),
    Kind.LOG: ("message",),
    Kind.SESSION_END: ("message", "exit_code"),
}


class LinkCondition(StrEnum):
    LOST = "lost"                            # a request failed: reconnecting
    BACK = "back"
    GONE = "gone"                            # not back within the reconnect time
    HEARTBEAT_FAILING = "heartbeat-failing"  # the controller's watchdog will trip if it goes on
    HEARTBEAT_BACK = "heartbeat-back"
    WARNING = "warning"                      # anything else a link has to say (a STOP not answered)


class Message:
    """A record that one thread hands to another's queue: the bus's :class:`Event` and the
    console's own records (rig.gui.messages, rig.gui.qc, rig.drivers.estop).  Each is a frozen
    dataclass with named fields; a receiver dispatches on its type and reads the fields,
    never a sentence."""

    __slots__ = ()


@dataclass(frozen=True)
class LinkNotice:
    """What a driver (rig.drivers.shaker, rig.drivers.daq) says of its link, for whoever listens (``on_event``)."""

    link: str                                # "controller" or "DAQ"
    state: LinkCondition
    message: str

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class Event(Message):
    """One event of a session: its :class:`Kind`, the experiment's label (None: the
    session's), the kind's fields (:data:`FIELDS`) and the wall-clock time."""

    kind: Kind
    experiment: str | None = None
    data: dict[str, Any] = field(default_factory=dict)
    time: float = field(default_factory=time.time)


Subscriber = Callable[[Event], None]
log = logging.getLogger(__name__)


class EventBus:
    def __init__(self) -> None:
        self._inline: list[Subscriber] = []
        self._queued: list[tuple[queue.Queue, threading.Thread]] = []
        self._inline_lock = threading.Lock()  # publishers are several threads (acquisition, links' events)

    def subscribe(self, fn: Subscriber, *, inline: bool = False) -> None:
        if inline:
            self._inline.append(fn)
            return
        q: queue.Queue = queue.Queue()

        name = getattr(fn, "__qualname__", type(fn).__qualname__)

        def pump() -> None:
            failures = 0
            while (event := q.get()) is not None:
                try:
                    fn(event)
                except Exception:  # a broken display must not stop the session, but is said
                    failures += 1
                    if failures == 1:
                        log.exception("event subscriber %s failed on a %r event; it gets the next events, "
                                      "the session goes on", name, str(event.kind))
            if failures > 1:
                log.error("event subscriber %s failed on %d events in all", name, failures)

        thread = threading.Thread(target=pump, name="event-subscriber", daemon=True)
        thread.start()
        self._queued.append((q, thread))

    def publish(self, kind: str, experiment: str | None = None, **data: Any) -> Event:
        kind = Kind(kind)                    # an undeclared kind is a bug: ValueError
        missing = [f for f in FIELDS[kind] if f not in data]
        if missing:
            raise TypeError(f"{kind} event without {', '.join(missing)}")
        event = Event(kind, experiment, data)
        with self._inline_lock:
            for fn in self._inline:
                fn(event)
        for q, _ in self._queued:
            q.put(event)
        return event

    def publish_link(self, notice: LinkNotice) -> None:
        """A driver's notice of its link (``on_event`` of rig.drivers.shaker and rig.drivers.daq)."""
        self.publish(Kind.LINK, link=notice.link, state=notice.state.value, message=notice.message)

    def close(self, timeout_s: float = 2.0) -> None:
        """Let queued subscribers finish what they were given."""
        for q, _ in self._queued:
            q.put(None)
        for _, thread in self._queued:
            thread.join(timeout=timeout_s)
