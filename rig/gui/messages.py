"""What the console's rig side posts to the window: each a small typed record (a
:class:`rig.events.Message`, as the session's events are), handled by its type in the
window's queue (docs/architecture.md, "The console's window queue")."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from rig.drivers.shaker import ShakerStatus
from rig.events import Message
from rig.gui.fits import FitSummary
from rig.gui.plan_state import PlanProgress
from rig.session.outcome import RunResult
from rig.session.preparation import RunOptions


@dataclass(frozen=True)
class Snapshot(Message):
    """The controller and the DAQ as last read (status None: not connected or unreadable)."""

    status: ShakerStatus | None
    error: str | None
    received: int = 0
    lost: int = 0
    crc_errors: int = 0
    over_range: int = 0
    overflow_flags: int = 0
    heartbeat_ok: bool = True
    samples: int = -1                       # the DAQ stream's samples since START, read with the status (-1: none)
    time: float = field(default_factory=time.monotonic)
    session: bool = False                   # read on a session's links (the session feeds the watchdog)
    streaming: bool = False                 # a DAQ link was there to read (its counters are this stream's)


@dataclass(frozen=True)
class Notice(Message):
    text: str
    level: str = "info"                    # info, refused, error


@dataclass(frozen=True)
class LinkState(Message):
    connected: bool
    text: str
    simulated: bool = False     # a peer named itself a simulator (rig.drivers.peer_identity)


@dataclass(frozen=True)
class SessionOpened(Message):
    path: Path
    progress: PlanProgress
    options: RunOptions
    qc: bool = False            # a unit's QC test (the QC panel follows it)


@dataclass(frozen=True)
class SessionClosed(Message):
    result: RunResult | None               # None: refused or failed before the session folder existed
    text: str


@dataclass(frozen=True)
class SafeStopIncomplete(Message):
    """A session's (a plan's or a QC test's) safe stop left steps undone: no reading says the
    rig is at rest."""

    failures: tuple[str, ...]              # "step: why", as the session's record has them


@dataclass(frozen=True)
class FitProgress(Message):
    title: str
    iteration: int
    objective: float


@dataclass(frozen=True)
class FitDone(Message):
    title: str
    result: FitSummary
    folder: Path


@dataclass(frozen=True)
class ComparisonDone(Message):
    results: dict[str, FitSummary]
    folder: Path
