"""Store and forward: the station's own journal of its records, and of the runs it has
on the rig, in ``OUT/qc-queue/``.

- ``pending/``  every record is written here first (fsync'd file, renamed into place,
  the folder fsync'd), with the name of the database it is for, then sent to that
  database; a record the database did not take (unreachable, refused) stays here and
  goes with the next run, ``qc sync`` or the console's next QC run — to the database it
  was queued for only (``qc sync`` asks before sending it to another).  The database's
  unique uid makes a second send harmless.  Records queued too long, or too many of them
  (station.toml's ``queue_max_age_h``, ``queue_max_records``), warn on every run
  (:func:`queue_warning`, data the console shows too).
- ``sent/``     a record moves here once the database holds it: the station's own copy.
- ``running/``  one file per run on the rig, locked (flock) by its process for the
  whole run.  The kernel lets go of the lock when the process ends however it ends, so
  a file whose lock is free belongs to a process that is gone without finishing — a
  crash, the OOM killer, SIGKILL, a power cut of the PC.  On the next start, before
  anything moves, such a run is recorded as ABORTED and the operator is told.

Only :mod:`rig.qc.records` talks to the database.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import socket
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from rig.qc.records import QcRecord, Records, RecordsError, RecordStatus, Unreachable, default_url
from rig.qc.station import StationConfig, load_station_config
from rig.qc.trace import measuring_equipment, now_utc, software_version, trace_session
from rig.session.outcome import ExitStatus, RunResult, stored_exit_status
from rig.session.storage import SESSION_FILE, Session

QUEUE_DIR = "qc-queue"
KILLED = "process ended without a safe stop"


def _write_synced(path: Path, doc: dict[str, Any], handle: IO[str] | None = None) -> None:
    """``doc`` as JSON at ``path``, on the disk before this returns: a temporary file,
    fsync, rename, fsync of the folder.  ``handle``: an open (locked) temporary to use."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    f = handle or open(tmp, "w")
    try:
        f.write(json.dumps(doc, indent=1) + "\n")
        f.flush()
        os.fsync(f.fileno())
        os.replace(f.name, path)
    finally:
        if handle is None:
            f.close()
    _sync_dir(path.parent)


def _sync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass(frozen=True)
class Sent:
    """What one sending of the queue did."""
    sent: int = 0           # added to the database
    present: int = 0        # the database had them already (sent before, the queue not yet told)
    left: int = 0           # still queued
    why: str | None = None  # why they are left (the database's words, without a password)
    elsewhere: tuple[str, ...] = ()   # the databases that records left queued were queued for, if not this one


class RecordQueue:
    """The journal files of one station folder."""

    def __init__(self, folder: Path) -> None:
        self.root = Path(folder) / QUEUE_DIR
        self.pending_dir, self.sent_dir, self.running_dir = (self.root / n for n in ("pending", "sent", "running"))

    def pending(self) -> list[Path]:
        """The queued records, oldest first."""
        return sorted(self.pending_dir.glob("*.json")) if self.pending_dir.is_dir() else []

    def put(self, record: QcRecord, database: str) -> Path:
        """``database``: the name (rig.qc.records.safe_url) of the database it is for."""
        self.pending_dir.mkdir(parents=True, exist_ok=True)
        path = self.pending_dir / f"{record.judged.replace(':', '')}-{record.uid}.json"
        _write_synced(path, {**record.to_journal(), "queued_for": database})
        return path

    def entries(self) -> list[Queued]:
        """What is queued, oldest first, as data."""
        out = []
        for path in self.pending():
            try:
                doc = json.loads(path.read_text())
            except FileNotFoundError:
                continue
            out.append(Queued(path, doc["uid"], doc["serial"], doc["verdict"], doc["status"], doc["judged"],
                              doc.get("queued_for")))
        return out

    def mark_sent(self, path: Path) -> None:
        self.sent_dir.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(path, self.sent_dir / path.name)
        except FileNotFoundError:    # another process of this station sent it at the same time
            return
        _sync_dir(self.sent_dir)

    def send(self, records: Records, anywhere: bool = False) -> Sent:
        """Every queued record for this database to it, oldest first; stops at the first
        one the database does not take (the rest would fare no better).  A record queued
        for another database stays (``anywhere``: sent here all the same, as the operator
        of ``qc sync`` decided)."""
        sent = present = 0
        queued = self.pending()
        elsewhere: dict[str, None] = {}
        for i, path in enumerate(queued):
            try:
                doc = json.loads(path.read_text())
            except FileNotFoundError:
                continue            # sent by another process of this station meanwhile
            meant = doc.get("queued_for")
            if meant is not None and meant != records.name and not anywhere:
                elsewhere[meant] = None
                continue
            record = QcRecord.from_journal(doc)
            try:
                added = records.add(record)
            except RecordsError as exc:
                return Sent(sent, present, len(queued) - i, _why(exc), tuple(elsewhere))
            sent, present = sent + added, present + (not added)
            if meant != records.name:    # the station's copy says where it went
                _write_synced(path, {**doc, "queued_for": records.name})
            self.mark_sent(path)
        left = len(self.pending())
        return Sent(sent, present, left, "queued for another database" if left else None, tuple(elsewhere))


@dataclass(frozen=True)
class Queued:
    """One queued record, as ``qc history`` lists it while the database is down."""
    path: Path
    uid: str
    serial: str
    verdict: str | None
    status: str
    judged: str
    queued_for: str | None


@dataclass(frozen=True)
class QueueWarning:
    """A queue that has grown past the station's limits: said on every run and in the console."""
    count: int
    oldest_h: float                 # how long the oldest record has waited
    max_age_h: float
    max_records: int
    folder: Path

    def sentence(self) -> str:
        return (f"{self.count} record{'s' * (self.count != 1)} queued in {self.folder}, the oldest "
                f"{self.oldest_h:.1f} h (limits: {self.max_age_h:g} h, {self.max_records} records): the database "
                f"has not had them; check its connection and run python -m rig qc sync --out "
                f"{self.folder.parent.parent}")


def queue_warning(folder: Path, config: StationConfig | None = None,
                  now: _dt.datetime | None = None) -> QueueWarning | None:
    """The station's queue as a warning when a record has waited longer than
    ``queue_max_age_h`` or more than ``queue_max_records`` wait; None otherwise."""
    config = config or load_station_config(folder)
    queue = RecordQueue(folder)
    entries = queue.entries()
    if not entries:
        return None
    now = now or _dt.datetime.now(_dt.UTC)
    oldest_h = max(0.0, (now - _dt.datetime.fromisoformat(entries[0].judged)).total_seconds() / 3600)
    if oldest_h <= config.queue_max_age_h and len(entries) <= config.queue_max_records:
        return None
    return QueueWarning(len(entries), oldest_h, config.queue_max_age_h, config.queue_max_records, queue.pending_dir)


class Run:
    """A run on the rig, in the journal and locked for as long as its process lives."""

    def __init__(self, path: Path, handle: IO[str]) -> None:
        self.path, self._handle = path, handle

    def end(self) -> None:
        """The run ended in this process (its record, if any, is in the queue): gone from the journal."""
        try:
            self.path.unlink(missing_ok=True)
            _sync_dir(self.path.parent)
        finally:
            self._handle.close()       # and with it the lock


class Outbox:
    """A QC run's way to the records: the station's journal first, then the database."""

    def __init__(self, folder: Path, records: Records, station: str | None, say: Callable[[str], None],
                 config: StationConfig | None = None) -> None:
        """``say``: how the operator is told (a sentence, rich markup allowed): the terminal or the console."""
        self.queue, self.records, self.station, self.say = RecordQueue(folder), records, station, say
        self.config = config or StationConfig()
        self.queued_because: str | None = None     # why the last record is queued, not in the database
        self._run: Run | None = None

    @classmethod
    def open(cls, folder: Path, db: str | None, say: Callable[[str], None]) -> Outbox:
        """The station at ``folder``: its configuration, its database (``db`` overrides the
        configuration's), and — before anything moves — runs a killed process left on
        the rig recorded as ABORTED, and what is queued sent."""
        config = load_station_config(folder)
        records = Records.open(db or config.db or default_url(folder), create=True, defer=True,
                               password=config.password, reach_later=True, writer=True)
        outbox = cls(folder, records, config.name, say, config)
        if records.unreachable:
            say(f"[yellow]records database {records.name} unreachable ({records.unreachable}): the records of this "
                f"station are queued in {outbox.queue.pending_dir}[/yellow]")
        try:
            outbox.recover()
            outbox.send()
            warning = queue_warning(folder, config)
            if warning is not None:
                say(f"[red]warning: {warning.sentence()}[/red]")
        except BaseException:
            records.close()
            raise
        return outbox

    @property
    def name(self) -> str:
        """Where the last record went, as the summary names it."""
        if self.queued_because is not None:
            return f"the station's queue {self.queue.pending_dir} (for {self.records.name})"
        return self.records.name

    def add(self, record: QcRecord) -> None:
        """The record in the journal (on disk), then in the database; if the database does
        not take it, it stays queued and the operator is told why — the run's verdict and
        exit status stand."""
        path = self.queue.put(record, self.records.name)
        try:
            self.records.add(record)
        except RecordsError as exc:
            what = "database unreachable" if isinstance(exc, Unreachable) else "the database refused it"
            self.queued_because = f"{what}: {_why(exc)}"
            return
        self.queued_because = None
        self.queue.mark_sent(path)

    def send(self, anywhere: bool = False) -> Sent:
        """What is queued, to the database; the operator is told what was sent and what is left."""
        result = self.queue.send(self.records, anywhere)
        if result.sent or result.present:
            self.say(f"{result.sent} queued record{'s' * (result.sent != 1)} sent to {self.records.name}"
                     + (f" ({result.present} were there already)" if result.present else ""))
        if result.elsewhere:
            self.say(f"[yellow]records queued for {', '.join(result.elsewhere)} are not sent to "
                     f"{self.records.name}: python -m rig qc sync --out {self.queue.root.parent} asks[/yellow]")
        elif result.left:
            self.say(f"[yellow]{result.left} record{'s' * (result.left != 1)} still queued in "
                     f"{self.queue.pending_dir} ({result.why})[/yellow]")
        return result

    # ----- runs on the rig ------------------------------------------------------------------------------------
    def begin(self, session: Path, spec: Any, identity: dict[str, Any]) -> None:
        """The run on the rig, in the journal and locked until :meth:`close`: if this
        process is killed, the next start finds it.  ``spec``: the rig.qc.spec.Spec."""
        self.queue.running_dir.mkdir(parents=True, exist_ok=True)
        uid = str(uuid.uuid4())            # the ABORTED record's, should there be one: a repeat adds nothing
        doc = {"uid": uid, "session": str(Path(session).resolve()), "pid": os.getpid(),
               "host": socket.gethostname(), "station": self.station,
               "spec": {"name": spec.name, "version": spec.version, "sha256": spec.sha256, "k": spec.k},
               **{k: identity[k] for k in ("serial", "operator", "rig", "started")},
               "identified_by": identity.get("identified_by")}
        path = self.queue.running_dir / f"{uid}.json"
        handle = open(path.with_name(f".{uid}.tmp"), "w")
        fcntl.flock(handle, fcntl.LOCK_EX)    # locked before its name appears: never seen unlocked while alive
        _write_synced(path, doc, handle)
        self._run = Run(path, handle)

    def recover(self) -> list[QcRecord]:
        """Runs whose process is gone (their lock is free): each one's ABORTED record into
        the queue, the operator told, the session marked; before anything moves."""
        found = []
        paths = sorted(self.queue.running_dir.glob("*.json")) if self.queue.running_dir.is_dir() else []
        for path in paths:
            try:
                handle = open(path)
            except FileNotFoundError:
                continue
            with handle:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    continue          # its process is alive: a run at this station right now
                if os.fstat(handle.fileno()).st_nlink == 0:
                    continue          # it ended between the listing and the lock
                entry = json.loads(handle.read())
                record = abandoned_record(entry)
                if record is None:
                    self.say(f"[yellow]unit {entry['serial']}: a run started {entry['started']} ended before its "
                             f"session began (process {entry['pid']} is gone); nothing moved, nothing is "
                             "recorded[/yellow]")
                else:
                    self.queue.put(record, self.records.name)
                    self.say(f"[red]unit {record.serial}: the run started {entry['started']} ({record.session}) was "
                             f"left by a process that is gone ({record.reason}); recorded as ABORTED ({record.uid}). "
                             "Check the rig and the unit before the next test.[/red]")
                    found.append(record)
                path.unlink()
                _sync_dir(path.parent)
        return found

    def close(self) -> None:
        """The run's end: said last, under the verdict's summary, if its record is queued."""
        if self.queued_because is not None:
            self.say(f"[yellow]record queued ({self.queued_because}); python -m rig qc sync --out "
                     f"{self.queue.root.parent} sends it[/yellow]")
        try:
            if self._run is not None:
                self._run.end()
                self._run = None
        finally:
            self.records.close()


def abandoned_record(entry: dict[str, Any]) -> QcRecord | None:
    """The ABORTED record of a run whose process is gone; None if its session never began
    (no session folder: nothing moved).  A session still marked ``running`` is marked
    ended: its process died before the safe stop (the controller's watchdog is what
    stopped the rig); one that had ended died while judging or recording."""
    folder = Path(entry["session"])
    if not (folder / SESSION_FILE).is_file() or not (folder / "dataset.json").is_file():
        return None
    trace = trace_session(folder)         # before the session is marked: its own end time, if it had one
    session = Session.load(folder)
    status, finished = session.meta.get("status"), trace.finished
    where = f"process {entry['pid']} on {entry['host']}"
    if stored_exit_status(session.meta) is ExitStatus.RUNNING:
        # Ended here, as data: stored_exit_status reads ABORTED from now on.
        result = RunResult(session)
        result.end(ExitStatus.ABORTED, KILLED)
        session.finish(result.status, result.to_json())
        reason = f"{KILLED} ({where}; the controller's watchdog stops the rig)"
    else:
        reason = f"process ended while judging ({where}), after the session {status}"
    peers = trace.peers[0] if trace.peers else {}
    spec = entry["spec"]
    return QcRecord(uid=entry["uid"], serial=entry["serial"], operator=entry["operator"], rig=entry["rig"],
                    started=entry["started"], finished=finished, judged=now_utc(),
                    software=software_version(), spec_name=spec["name"], spec_version=spec["version"],
                    spec_sha256=spec["sha256"], calibration_sha256=trace.calibration_sha256,
                    register_map_sha256=trace.register_map_sha256, verdict=None, status=RecordStatus.ABORTED,
                    session=trace.path, data_sha256=trace.data_sha256, files=trace.files, characteristics=(),
                    notes=(reason,), simulated=trace.simulated, controller=peers.get("controller"),
                    daq=peers.get("daq"), reason=reason, k=spec["k"], station=entry.get("station"),
                    identified_by=entry.get("identified_by"), equipment=measuring_equipment(trace),
                    flagged=trace.flagged,
                    details={"found": "on the station's next start", "session_status": status,
                             "session_outcome": session.meta.get("outcome")})


def pending_count(folder: Path) -> int:
    return len(RecordQueue(folder).pending())


def _why(exc: RecordsError) -> str:
    return exc.why if isinstance(exc, Unreachable) else str(exc)
