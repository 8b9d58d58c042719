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
    IDLE = "idle"
    MOVING = "moving"
    SETTLING = "settling"
    CAPTURING = "capturing"
    STOPPING = "stopping"
    ALARM = "alarm"


@dataclass(frozen=True)
class Event:
    """``kind``: session-start, phase, progress, captured, experiment-done,
    experiment-failed, alarm, log, identified, session-end."""

    kind: str
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
                                      "the session goes on", name, event.kind)
            if failures > 1:
                log.error("event subscriber %s failed on %d events in all", name, failures)

        thread = threading.Thread(target=pump, name="event-subscriber", daemon=True)
        thread.start()
        self._queued.append((q, thread))

    def publish(self, kind: str, experiment: str | None = None, **data: Any) -> Event:
        event = Event(kind, experiment, data)
        with self._inline_lock:
            for fn in self._inline:
                fn(event)
        for q, _ in self._queued:
            q.put(event)
        return event

    def publish_link(self, message: str) -> None:
        """A link's notice (lost, back, heartbeat) as a log event."""
        self.publish("log", message=message)

    def close(self, timeout_s: float = 2.0) -> None:
        """Let queued subscribers finish what they were given."""
        for q, _ in self._queued:
            q.put(None)
        for _, thread in self._queued:
            thread.join(timeout=timeout_s)
