"""The status poller (no Qt here): the controller's status and the DAQ's counters, read
4 times a second on the ``rig-status`` thread from whichever links hold the rig — the
console's own outside sessions, the session's (a plain or a QC session) while one
runs — and posted as a :class:`~rig.gui.messages.Snapshot`.  Every sentence the window
says about the rig's state comes from these reads."""

from __future__ import annotations

import threading
from collections.abc import Callable

from rig.drivers.daq import Daq
from rig.drivers.shaker import Shaker
from rig.events import Message
from rig.gui.messages import Snapshot

STATUS_PERIOD_S = 0.25
# A read neither waits out another thread's reconnect (the session's command holds the link
# for up to its reconnect time, 20 s) nor reconnects for long itself: the poll is what the
# window shows, and a read stuck for 20 s left it showing nothing new while the session's
# safe stop waited on the poll's reconnect in turn.
POLL_PATIENCE_S = 0.5
CONTROLLER_NOT_CONNECTED = "the controller is not connected; the DAQ alone is read"

# Which links to read: (the controller, the DAQ, whether they are a session's); None: none held.
Source = Callable[[], tuple[Shaker | None, Daq | None, bool]]


class StatusPoller:
    def __init__(self, source: Source, post: Callable[[Message], None], heartbeat_ok: Callable[[], bool],
                 period_s: float = STATUS_PERIOD_S) -> None:
        self.source, self.post, self.heartbeat_ok, self.period_s = source, post, heartbeat_ok, period_s
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="rig-status", daemon=True)
        self._thread.start()

    def read(self) -> Snapshot | None:
        """One read of the links that hold the rig now (None: no links held)."""
        shaker, daq, session = self.source()
        if shaker is None and daq is None:
            return None
        status = None
        error: str | None = CONTROLLER_NOT_CONNECTED
        if shaker is not None:
            error = None
            try:
                status = shaker.status(patience_s=POLL_PATIENCE_S)
            except Exception as exc:  # noqa: BLE001 — shown as the link's state
                error = str(exc)
        if daq is None:
            return Snapshot(status, error, heartbeat_ok=self.heartbeat_ok(), session=session)
        c = daq.counters
        # the parser's index restarts at START itself; the ring holds the last stream's samples
        # until the first frames of the new one arrive
        return Snapshot(status, error, received=daq.parser.received, lost=c.lost_samples, crc_errors=c.crc_errors,
                        over_range=c.over_range, overflow_flags=c.overflow_flags, samples=daq.parser.next_index,
                        heartbeat_ok=self.heartbeat_ok(), session=session, streaming=daq.streaming)

    def _poll(self) -> None:
        while not self._closed.wait(self.period_s):
            # No links held (between a session's end and the console's taking its links back,
            # or disconnected): said as such, so that no older reading stays on screen as if now.
            self.post(self.read() or Snapshot(None, None))

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=2)
