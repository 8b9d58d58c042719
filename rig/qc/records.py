"""The QC records database: one schema through SQLAlchemy, SQLite by default (WAL) or
PostgreSQL by URL (``postgresql://…``, driver psycopg 3).

A record is written once, in one transaction with its characteristics, and never
changed: the tool has no update or delete, and triggers in the database refuse both
(a re-judgement adds a record that refers to the first).  Concurrent writers lose
nothing: SQLite transactions take the write lock when they begin (``BEGIN IMMEDIATE``)
and wait for it; PostgreSQL serialises the schema's creation with an advisory lock.

Credentials never leak: a URL that carries a password is refused (it would show in the
process list and the shell history); the password comes from libpq's own places (a
pgpass file, a service file, PGPASSWORD) or from the station's configuration file
(rig.qc.station), and is handed to the driver as a connection argument, never in a
URL or an argv.  A database is only ever named by :func:`safe_url`, and every message
from the driver is stripped of every password it may have used before anyone sees it.

Readers never create: ``qc history`` and ``qc judge`` open an existing database only.
``qc run`` creates its database, but only when it has a record to write (a run that
never started leaves no empty file behind).

A record is added at most once: its uid is unique, and :meth:`Records.add` of a uid the
database holds already is a no-op that says so (the station's queue may send a record
again after a crash between the database's commit and the queue's note of it).

A record says where it was measured: the controller's device identification and the
DAQ's ``*IDN?``, and ``simulated`` when either named itself a simulator; that flag is part
of the immutable row.  ``details`` holds further facts about the run as a JSON object
(experiments used, rig time, why it stopped …), so that later fields need no new schema.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any
from urllib.parse import quote, quote_plus

from sqlalchemy import (
    Boolean,
    Column,
    Connection,
    Engine,
    Float,
    ForeignKey,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    create_engine,
    event,
    false,
    inspect,
    select,
    text,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, SQLAlchemyError

from rig.errors import BadInput
from rig.qc.integrity import record_sha256
from rig.qc.judge import Outcome

SCHEMA_VERSION = 5            # 2: where measured (simulated, controller, daq), reason, k, details; titles; 3: station;
                              # 4: the hash chain, the report's hash, equipment, ambient, flagged captures, who and
                              # why (identified_by, rejudge_reason), releases
                              # 5: measurement-system studies and master checks (qc_study)
DEFAULT_FILE = "qc-records.sqlite"
SQLITE_WAIT_S = 60.0          # a writer waits this long for another one's transaction
PG_SCHEMA_LOCK = 0x5143_5245  # advisory lock key ("QCRE") held while the schema is created
PG_CHAIN_LOCK = 0x5143_4348   # advisory lock key ("QCCH"), with the station's hash: one writer per station chain
PG_CONNECT_TIMEOUT_S = 10     # a server that does not answer within this is unreachable: the record is queued

metadata = MetaData()
schema_table = Table("qc_schema", metadata, Column("version", Integer, primary_key=True))
record_table = Table(
    "qc_record", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("uid", String(36), nullable=False, unique=True),
    Column("serial", String(64), nullable=False, index=True),
    Column("operator", String(128), nullable=False),
    Column("rig", String(128), nullable=False),
    Column("started", String(40)),
    Column("finished", String(40)),
    Column("judged", String(40), nullable=False),
    Column("software", String(128), nullable=False),
    Column("spec_name", String(128), nullable=False),
    Column("spec_version", String(64), nullable=False),
    Column("spec_sha256", String(64), nullable=False),
    Column("calibration_sha256", String(64)),
    Column("register_map_sha256", String(64)),
    Column("verdict", String(16)),
    Column("status", String(16), nullable=False),
    Column("session", Text, nullable=False),
    Column("data_sha256", String(64), nullable=False, index=True),
    Column("files", Text, nullable=False),        # JSON {relative path: sha256}
    Column("diagnosis", Text, nullable=False),    # JSON list of lines
    Column("remedy", Text),
    Column("notes", Text, nullable=False),        # JSON list of lines
    Column("rejudges", String(36)),               # uid of the first record of the same data
    Column("simulated", Boolean, nullable=False, server_default=false()),
    Column("controller", Text),                   # JSON {object: text}: device identification, firmware
    Column("daq", String(256)),                   # the DAQ's *IDN? answer
    Column("reason", Text),                       # why there is no verdict (ABORTED, ERROR)
    Column("k", Float(precision=53)),             # the guard band's coverage factor of the verdict
    Column("details", Text),                      # JSON object: further facts about the run
    Column("station", String(128), index=True),   # the station that measured (several share a database)
    Column("previous_sha256", String(64)),        # the hash of the station's previous record (the chain)
    Column("record_sha256", String(64)),          # this record's own hash (rig.qc.integrity.record_sha256)
    Column("report_sha256", String(64)),          # the sha256 of the report file written with it
    Column("equipment", Text),                    # JSON list of Equipment: the measuring equipment used
    Column("ambient", Text),                      # JSON object: ambient conditions the rig reported; NULL: none
    Column("flagged", Text),                      # JSON {experiment: [flags]}: captures flagged by the session
    Column("identified_by", String(32)),          # how the station identified the operator: login, pin, typed
    Column("rejudge_reason", Text),               # a re-judgement: why the data were judged again
)
characteristic_table = Table(
    "qc_characteristic", metadata,
    Column("record_id", Integer, ForeignKey("qc_record.id"), primary_key=True),
    Column("position", Integer, primary_key=True),
    Column("name", String(128), nullable=False),
    Column("unit", String(16), nullable=False),
    Column("value", Float(precision=53)),
    Column("std", Float(precision=53)),
    Column("std_fit", Float(precision=53)),
    Column("u_cal", Float(precision=53), nullable=False),
    Column("low", Float(precision=53)),
    Column("high", Float(precision=53)),
    Column("nominal", Float(precision=53), nullable=False),
    Column("outcome", String(16), nullable=False),
    Column("title", String(256)),                 # the spec's readable name of the characteristic
    Column("sigma_basis", String(16)),            # noise, residual or scatter: which σ the verdict used
)
# A measurement-system study (type 1, type 3) or a daily master check (rig.qc.studies):
# immutable like the verdicts; ``document`` holds its figures and the uids of its runs' records.
study_table = Table(
    "qc_study", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("uid", String(36), nullable=False, unique=True),
    Column("kind", String(16), nullable=False),        # type1, type3, check
    Column("at", String(40), nullable=False),          # when it ended (ISO 8601, UTC)
    Column("station", String(128), index=True),
    Column("spec_name", String(128), nullable=False),
    Column("spec_version", String(64), nullable=False),
    Column("spec_sha256", String(64), nullable=False),
    Column("passed", Boolean, nullable=False),
    Column("simulated", Boolean, nullable=False),
    Column("units", Text, nullable=False),             # JSON list: the master, or a type 3's units
    Column("summary", Text, nullable=False),
    Column("document", Text, nullable=False),          # JSON: the whole study (rig.qc.studies.StudyRecord)
)
# Tables a schema version added (created, with their triggers, when an older database is upgraded).
TABLES_ADDED = {5: ("qc_study",)}
# Columns schema version 2 added to version 1's tables (a version 1 database is upgraded on open).
ADDED_IN_2: dict[str, tuple[str, ...]] = {"qc_record": ("simulated", "controller", "daq", "reason", "k", "details"),
              "qc_characteristic": ("title", "sigma_basis")}
ADDED_IN_3: dict[str, tuple[str, ...]] = {"qc_record": ("station",)}
ADDED_IN_4: dict[str, tuple[str, ...]] = {"qc_record": ("previous_sha256", "record_sha256", "report_sha256",
                                                        "equipment", "ambient", "flagged", "identified_by",
                                                        "rejudge_reason")}
ADDED: dict[int, dict[str, tuple[str, ...]]] = {2: ADDED_IN_2, 3: ADDED_IN_3, 4: ADDED_IN_4, 5: {}}
# A second person's approval of a unit's record (``qc release``): a row of its own, never changed.
release_table = Table(
    "qc_release", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("uid", String(36), nullable=False, unique=True),
    Column("record_uid", String(36), nullable=False, index=True),
    Column("serial", String(64), nullable=False, index=True),
    Column("approver", String(128), nullable=False),
    Column("identified_by", String(32), nullable=False),
    Column("released", String(40), nullable=False),
    Column("station", String(128)),
    Column("note", Text),
)
TABLES_IN_4 = ("qc_release",)
IMMUTABLE = ("qc_record", "qc_characteristic", "qc_schema", "qc_release", "qc_study")
INIT_COMMAND = "python -m rig qc db init --db ADMIN_URL --grant STATION_ROLE (docs/qc.md, \"Station set-up\")"
PASSWORD_ADVICE = ("name the database without one (postgresql://USER@HOST:PORT/DB) and keep the password in "
                   "~/.pgpass (mode 0600), a pg_service.conf service (postgresql:///?service=NAME), PGPASSWORD, "
                   "or the station's station.toml readable by its owner only (docs/qc.md, \"Station set-up\")")


class RecordStatus(StrEnum):
    """How the run a record is about ended: judged (COMPLETE, with a verdict), or not."""
    COMPLETE = "COMPLETE"     # judged: the record has a verdict
    ABORTED = "ABORTED"       # the safe stop, an interruption, a lost link, a killed process: no verdict
    ERROR = "ERROR"           # an internal error: no verdict


class RecordsError(BadInput):
    """A records database that cannot be opened or written (named without credentials)."""


class SchemaMismatch(RecordsError):
    """The database answered but holds no QC schema, or another version of it."""


class TooPrivileged(RecordsError):
    """The station's database role could rewrite records (it owns the tables, is a
    superuser, or holds UPDATE, DELETE or TRUNCATE): a station writes with INSERT and SELECT only."""


@dataclass(frozen=True)
class Equipment:
    """One item of measuring equipment a record was measured with.  Today the rig knows its
    DAQ calibration file only (``sha256``); transducer serials, certificates and their due
    dates come from the metrology's calibration records (rig.qc.calibration) when it has them."""
    name: str                         # "DAQ calibration file", "force transducer" …
    serial: str | None = None
    certificate: str | None = None    # the calibration certificate's number
    due: str | None = None            # the next calibration's date (ISO)
    sha256: str | None = None         # the calibration file's hash, where the item is a file


@dataclass(frozen=True)
class Release:
    """A second person's approval of a record (``qc release``)."""
    uid: str
    record_uid: str
    serial: str
    approver: str
    identified_by: str
    released: str
    station: str | None = None
    note: str | None = None


class Unreachable(RecordsError):
    """The database server did not answer (down, network lost): the station queues its records."""

    def __init__(self, message: str, why: str) -> None:
        super().__init__(message)
        self.why = why          # the driver's own words, redacted: "connection refused" …


@dataclass(frozen=True)
class CharacteristicRecord:
    name: str
    unit: str
    value: float | None
    std: float | None
    std_fit: float | None
    u_cal: float
    low: float | None
    high: float | None
    nominal: float
    outcome: Outcome
    title: str | None = None          # the spec's readable name; ``name`` is the identifier
    sigma_basis: str | None = None    # noise, residual or scatter (rig.qc.characteristics)


@dataclass(frozen=True)
class QcRecord:
    """One verdict on one unit, as stored.  ``started``/``finished`` are the
    measurement's (ISO 8601, UTC); ``judged`` when this record was made."""

    uid: str
    serial: str
    operator: str
    rig: str
    started: str | None
    finished: str | None
    judged: str
    software: str
    spec_name: str
    spec_version: str
    spec_sha256: str
    calibration_sha256: str | None
    register_map_sha256: str | None
    verdict: Outcome | None
    status: RecordStatus
    session: str
    data_sha256: str                  # fingerprint of the measured data: a re-judgement finds its first record by it
    files: dict[str, str]
    characteristics: tuple[CharacteristicRecord, ...]
    diagnosis: tuple[str, ...] = ()
    remedy: str | None = None
    notes: tuple[str, ...] = ()
    rejudges: str | None = None
    simulated: bool = False           # a peer named itself a simulator: never a production record
    controller: dict[str, str] | None = None   # device identification and firmware; None: not known
    daq: str | None = None            # *IDN?; None: not known (data from elsewhere)
    reason: str | None = None         # why there is no verdict
    k: float | None = None            # the guard band's coverage factor
    details: dict[str, Any] = field(default_factory=dict)   # further facts about the run
    station: str | None = None        # the station that measured; None: written before stations were named
    previous_sha256: str | None = None   # the station's previous record's hash: set by the database's writer
    record_sha256: str | None = None     # this record's hash (None: not yet stored, or stored before version 4)
    report_sha256: str | None = None     # the report written with it
    equipment: tuple[Equipment, ...] = ()
    ambient: dict[str, Any] | None = None        # None: the rig reports no ambient conditions
    flagged: dict[str, list[str]] = field(default_factory=dict)   # experiment → the session's flags on its capture
    identified_by: str | None = None     # login, pin or typed: how the station knew the operator
    rejudge_reason: str | None = None    # a re-judgement: why (its operator and time say who and when)

    @property
    def archive_id(self) -> str:
        """What names the measurement in an archive, in place of a machine path: the
        station (or rig) and the session folder's name."""
        return f"{self.station or self.rig}/{Path(self.session).name}"

    def acceptance(self, c: CharacteristicRecord) -> tuple[float | None, float | None]:
        """The acceptance limits of ISO 14253-1: the spec's limits moved in by k·σ."""
        if c.std is None or self.k is None:
            return None, None
        u = self.k * c.std
        return (None if c.low is None else c.low + u), (None if c.high is None else c.high - u)

    def to_json(self, superseded_by: str | None = None) -> dict[str, Any]:
        """The form ``qc history --json`` prints: ``superseded_by`` is the uid of the next
        judgement of the same data (the database knows it; the record is never changed)."""
        return {
            "uid": self.uid, "serial": self.serial, "verdict": self.verdict, "status": self.status,
            "reason": self.reason, "simulated": self.simulated,
            "judged_at": self.judged, "rejudges": self.rejudges, "superseded_by": superseded_by,
            "spec": {"name": self.spec_name, "version": self.spec_version, "sha256": self.spec_sha256},
            "k": self.k,
            "characteristics": {c.name: {"title": c.title, "value": c.value, "std": c.std,
                                         "sigma_basis": c.sigma_basis, "low": c.low, "high": c.high,
                                         "acceptance": list(self.acceptance(c)), "unit": c.unit,
                                         "outcome": c.outcome} for c in self.characteristics},
            "started": self.started, "finished": self.finished, "operator": self.operator, "rig": self.rig,
            "station": self.station, "measured_on": {"controller": self.controller, "daq": self.daq},
            "details": self.details, "session": self.session, "data_sha256": self.data_sha256,
            "archive_id": self.archive_id, "identified_by": self.identified_by,
            "rejudge_reason": self.rejudge_reason, "equipment": [asdict(q) for q in self.equipment],
            "ambient": self.ambient, "flagged": self.flagged, "report_sha256": self.report_sha256,
            "previous_sha256": self.previous_sha256, "record_sha256": self.record_sha256,
        }

    def to_journal(self) -> dict[str, Any]:
        """Every field, as the station's queue keeps it (JSON); :meth:`from_journal` reads it back."""
        return asdict(self)

    @classmethod
    def from_journal(cls, doc: dict[str, Any]) -> QcRecord:
        fields = dict(doc)
        fields["characteristics"] = tuple(CharacteristicRecord(**{**c, "outcome": Outcome(c["outcome"])})
                                          for c in doc["characteristics"])
        fields["verdict"] = None if doc["verdict"] is None else Outcome(doc["verdict"])
        fields["status"] = RecordStatus(doc["status"])
        fields["diagnosis"], fields["notes"] = tuple(doc["diagnosis"]), tuple(doc["notes"])
        fields["equipment"] = tuple(Equipment(**q) for q in doc.get("equipment", ()))
        return cls(**{k: v for k, v in fields.items() if k in cls.__dataclass_fields__})


# ----- URLs and secrets ----------------------------------------------------------------------------------
def default_url(directory: Path) -> str:
    return f"sqlite:///{(Path(directory) / DEFAULT_FILE).resolve()}"


def parse_url(url: str) -> URL:
    """A database URL (a bare path means an SQLite file); refused with one line that
    does not repeat a password, and refused when it carries one."""
    if "://" not in url:
        url = f"sqlite:///{Path(url).resolve()}"
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):   # ValueError: a port that is not a number
        raise RecordsError(f"--db {safe_url(url)}: not a database URL (sqlite:///FILE or "
                           "postgresql://USER@HOST:PORT/DB, the port a number)") from None
    backend = parsed.get_backend_name()
    if backend not in ("sqlite", "postgresql", "postgres"):
        raise RecordsError(f"--db {safe_url(parsed)}: unsupported database {backend!r} (sqlite or postgresql)")
    if parsed.password is not None or "password" in parsed.query:
        raise RecordsError(f"--db {safe_url(url)}: a URL must not carry the password (every user of the "
                           f"machine reads it in the process list); {PASSWORD_ADVICE}")
    if backend == "sqlite":
        if not parsed.database or parsed.database == ":memory:":
            raise RecordsError(f"--db {safe_url(parsed)}: an SQLite URL needs a file (sqlite:///FILE)")
        return parsed.set(drivername="sqlite")
    if not parsed.database and "service" not in parsed.query:
        raise RecordsError(f"--db {safe_url(parsed)}: a PostgreSQL URL needs a database name (…/DB) "
                           "or a service (?service=NAME)")
    return parsed.set(drivername="postgresql+psycopg")


def safe_url(url: URL | str) -> str:
    """The URL as it may be shown: no password, not even in the query string."""
    if isinstance(url, str):
        if url.partition("://")[2].partition("/")[0].count("@") > 1:
            # An '@' left unescaped in a password: a parser splits at the first one and would
            # show the password's tail as the host; everything before the last '@' goes.
            return _mask_raw(url)
        try:
            parsed = make_url(url)
        except (ArgumentError, ValueError):
            return _mask_raw(url)
    else:
        parsed = url
    return parsed.difference_update_query(["password"]).render_as_string(hide_password=True)


def _mask_raw(text: str) -> str:
    """An unparsable URL: drop whatever sits between '//' … ':' and '@'."""
    head, sep, rest = text.partition("://")
    if sep and "@" in rest:
        userinfo, _, host = rest.rpartition("@")
        return f"{head}://{userinfo.split(':', 1)[0]}:***@{host}" if ":" in userinfo else text
    return text


def secrets_for(url: URL, password: str | None = None) -> list[str]:
    """Every password the driver may use for this URL: the station's (``password``),
    PGPASSWORD, the pgpass file (PGPASSFILE or ~/.pgpass) and, should one ever get
    there, one in the URL or its query."""
    found = [password, url.password, url.query.get("password"), os.environ.get("PGPASSWORD")]
    passfile = Path(os.environ.get("PGPASSFILE") or Path.home() / ".pgpass")
    try:
        for line in passfile.read_text().splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                fields = line.replace("\\\\", "\0").replace("\\:", "\1").split(":", 4)
                if len(fields) == 5:   # host:port:database:user:password (the password may hold ':')
                    found.append(fields[4].replace("\1", ":").replace("\0", "\\"))
    except (OSError, UnicodeDecodeError):
        pass
    out: list[str] = []
    for s in found:
        if isinstance(s, tuple):
            s = s[0] if s else None
        if s:
            out += [str(s), quote(str(s), safe=""), quote_plus(str(s))]
    return sorted(set(out), key=len, reverse=True)


def redact(message: str, secrets: list[str]) -> str:
    for s in secrets:
        message = message.replace(s, "***")
    return message


# ----- the database -----------------------------------------------------------------------------------------
class Records:
    """An open records database.  :meth:`add` is the only way in; nothing changes or deletes."""

    def __init__(self, engine: Engine, url: URL, password: str | None = None) -> None:
        self.engine, self.url = engine, url
        self.name = safe_url(url)
        self._secrets = secrets_for(url, password)
        self._pending = False    # the schema to be checked (made) with the first record
        self.unreachable: str | None = None   # why the server did not answer when opened (``reach_later``)
        self.writer = False      # a station's writer: refused where its role could rewrite records
        self._rights_checked = False

    @classmethod
    def open(cls, url: str, create: bool = False, defer: bool = False, *, password: str | None = None,
             reach_later: bool = False, writer: bool = False) -> Records:
        """The records database at ``url``.  Without ``create`` only an existing one is
        opened (readers, ``identify batch --db``: a mistyped path must not start an empty
        one); with it a new one is made, and with ``defer`` too a new SQLite file is made
        only when the first record is added (a run that never started leaves nothing).
        ``password``: the station's, given to the driver as a connection argument.
        ``reach_later``: a server that does not answer is no error (``unreachable`` says
        why; the schema is checked with the first record), a refused login still is.
        ``writer``: a station's (``qc run``, ``qc judge``, ``qc sync``): on PostgreSQL it never
        makes or upgrades the schema (an administrator does: :func:`init_schema`) and is
        refused (:class:`TooPrivileged`) where its role could rewrite records."""
        parsed = parse_url(url)
        pending = False
        if parsed.get_backend_name() == "sqlite":
            path = Path(str(parsed.database))
            if path.is_dir():
                raise RecordsError(f"--db {safe_url(parsed)}: a folder, not a database file (the station's "
                                   f"database is {path / DEFAULT_FILE})")
            if not path.is_file():
                if not create:
                    raise RecordsError(f"records database {safe_url(parsed)} does not exist (qc run creates it; "
                                       "give the URL or file of an existing one)")
                existing = next(p for p in path.absolute().parents if p.exists())
                if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
                    raise RecordsError(f"--db {safe_url(parsed)}: {existing} is not a writable folder")
                pending = defer
                if not defer:
                    path.parent.mkdir(parents=True, exist_ok=True)
            engine = create_engine(parsed, connect_args={"timeout": SQLITE_WAIT_S})
            event.listen(engine, "connect", _sqlite_connect)
            event.listen(engine, "begin", lambda conn: conn.exec_driver_sql("BEGIN IMMEDIATE"))
        else:
            # The password is a connection argument: it is in no URL, no argv, no message.
            connect_args: dict[str, Any] = {"connect_timeout": PG_CONNECT_TIMEOUT_S}
            if password:
                connect_args["password"] = password
            engine = create_engine(parsed, pool_pre_ping=True, connect_args=connect_args)
        records = cls(engine, parsed, password)
        records._pending, records.writer = pending, writer
        if not pending:
            try:
                with records._errors("cannot be opened"):
                    records._ensure_schema(create)
                    records._check_writer()
            except Unreachable as exc:
                if not reach_later:
                    records.close()
                    raise
                records._pending, records.unreachable = True, exc.why
            except RecordsError:
                records.close()
                raise
        return records

    def close(self) -> None:
        self.engine.dispose()

    @contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except SQLAlchemyError as exc:
            reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()
            first = redact(reason[0] if reason else type(exc).__name__, self._secrets)
            message = redact(f"records database {self.name} {what}: {first}", self._secrets)
            if _unreachable(exc):
                raise Unreachable(message, first) from None
            raise RecordsError(message) from None

    def _ensure_schema(self, create: bool) -> None:
        with self.engine.begin() as conn:
            if conn.dialect.name == "postgresql":
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_SCHEMA_LOCK})
            admin_only = self.writer and conn.dialect.name == "postgresql"
            if not inspect(conn).has_table("qc_schema"):
                if not create or admin_only:
                    raise SchemaMismatch(f"{self.name} is not a QC records database (no qc_schema table)"
                                         + (f"; an administrator makes it: {INIT_COMMAND}" if admin_only else ""))
                metadata.create_all(conn)
                _create_triggers(conn)
                conn.execute(schema_table.insert().values(version=SCHEMA_VERSION))
                return
            versions = conn.execute(select(schema_table.c.version)).scalars().all()
            if versions and max(versions) < SCHEMA_VERSION and set(versions) <= set(range(1, SCHEMA_VERSION)):
                # PostgreSQL: the administrator's command (create, not a station's writer) upgrades;
                # a reader or a station is told who does.
                if conn.dialect.name == "postgresql" and (admin_only or not create):
                    raise SchemaMismatch(f"records database {self.name} has schema version {max(versions)}; this "
                                         f"program reads and writes version {SCHEMA_VERSION}: an administrator "
                                         f"upgrades it ({INIT_COMMAND})")
                _upgrade(conn, max(versions))
                return
        if not versions or max(versions) != SCHEMA_VERSION:   # {1, 2, 3}: upgraded from 1 to 2 and 3
            raise SchemaMismatch(f"records database {self.name} has schema version "
                                 f"{', '.join(map(str, versions)) or 'none'}; this program reads and writes "
                                 f"version {SCHEMA_VERSION}")

    def _create_pending(self) -> None:
        """The database made with its first write, where opening it found none."""
        if self._pending:
            with self._errors("cannot be created"):
                if self.url.get_backend_name() == "sqlite":
                    Path(str(self.url.database)).parent.mkdir(parents=True, exist_ok=True)
                self._ensure_schema(create=True)
            self._pending = False

    def add(self, record: QcRecord) -> bool:
        """The record and its characteristics, in one transaction; False (and nothing
        written) when the database holds a record of this uid already."""
        self._create_pending()
        with self._errors("cannot be opened"):
            self._check_writer()
        with self._errors("refused the record"), self.engine.begin() as conn:
            record = self._chained(conn, record)
            row = {k: v for k, v in record.__dict__.items() if k != "characteristics"}
            row["files"] = json.dumps(record.files, sort_keys=True)
            row["equipment"] = json.dumps([asdict(q) for q in record.equipment])
            row["ambient"] = None if record.ambient is None else json.dumps(record.ambient, sort_keys=True)
            row["flagged"] = json.dumps(record.flagged, sort_keys=True)
            row["controller"] = None if record.controller is None else json.dumps(record.controller, sort_keys=True)
            row["details"] = json.dumps(record.details, sort_keys=True)
            row["diagnosis"] = json.dumps(list(record.diagnosis))
            row["notes"] = json.dumps(list(record.notes))
            # ON CONFLICT DO NOTHING: a second sender of the same record (a queue sent again,
            # two stations' syncs of one shared queue) waits for the first one's commit and adds nothing.
            insert = (postgresql.insert if conn.dialect.name == "postgresql" else sqlite.insert)(record_table)
            key = conn.execute(insert.values(**row).on_conflict_do_nothing(index_elements=["uid"])
                               .returning(record_table.c.id)).scalar()
            if key is None:
                return False
            if record.characteristics:
                conn.execute(characteristic_table.insert(), [
                    {"record_id": key, "position": i, **c.__dict__}
                    for i, c in enumerate(record.characteristics)])
        return True

    def _chained(self, conn: Connection, record: QcRecord) -> QcRecord:
        """The record with the hash of its station's last record and its own hash, within
        the transaction that writes it (one writer per station: SQLite's write lock, taken
        at BEGIN, or PostgreSQL's advisory lock on the station)."""
        station = record_table.c.station
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key, hashtext(:station))"),
                         {"key": PG_CHAIN_LOCK, "station": record.station or ""})
        mine = station.is_(None) if record.station is None else station == record.station
        previous = conn.execute(select(record_table.c.record_sha256).where(mine)
                                .order_by(record_table.c.id.desc()).limit(1)).scalar()
        chained = replace(record, previous_sha256=previous, record_sha256=None)
        return replace(chained, record_sha256=record_sha256(chained))

    def rights(self) -> Rights:
        """What this connection's role may do to the records' tables (PostgreSQL)."""
        with self._errors("cannot be read"), self.engine.connect() as conn:
            return _rights(conn)

    def _check_writer(self) -> None:
        """A station's writer on PostgreSQL: refused where its role could rewrite records
        (checked once, when the server first answers)."""
        if not self.writer or self._rights_checked or self.url.get_backend_name() != "postgresql" or self._pending:
            return
        with self.engine.connect() as conn:
            rights = _rights(conn)
        self._rights_checked = True
        if rights.could_rewrite:
            raise TooPrivileged(f"records database {self.name}: role {rights.role} {rights.why()}; a station "
                                f"writes with INSERT and SELECT only, as a role that owns nothing "
                                f"({INIT_COMMAND})")
        if not rights.may_write:
            raise RecordsError(f"records database {self.name}: role {rights.role} may not "
                               f"{' and '.join(rights.missing)}; an administrator grants it ({INIT_COMMAND})")

    def add_release(self, release: Release) -> None:
        with self._errors("cannot be opened"):
            self._check_writer()
        with self._errors("refused the release"), self.engine.begin() as conn:
            conn.execute(release_table.insert().values(**asdict(release)))

    def releases(self, serial: str | None = None) -> list[Release]:
        query = select(release_table).order_by(release_table.c.id)
        if serial is not None:
            query = query.where(release_table.c.serial == serial)
        with self._errors("cannot be read"), self.engine.connect() as conn:
            return [Release(**{k: r[k] for k in Release.__dataclass_fields__}) for r in conn.execute(query).mappings()]

    def find(self, serial: str | None = None, since: str | None = None, station: str | None = None) -> list[QcRecord]:
        """Records in the order they were written, optionally of one serial number, of
        one station and measured on or after ``since`` (an ISO date or time, UTC)."""
        if self._pending:
            return []     # no file yet: no records
        query = select(record_table).order_by(record_table.c.id)
        if serial is not None:
            query = query.where(record_table.c.serial == serial)
        if station is not None:
            query = query.where(record_table.c.station == station)
        if since is not None:
            query = query.where(record_table.c.started >= since)
        with self._errors("cannot be read"), self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            chars: dict[int, list[CharacteristicRecord]] = {}
            ids = [r["id"] for r in rows]
            if ids:
                for c in conn.execute(select(characteristic_table)
                                      .where(characteristic_table.c.record_id.in_(ids))
                                      .order_by(characteristic_table.c.record_id,
                                                characteristic_table.c.position)).mappings():
                    chars.setdefault(c["record_id"], []).append(CharacteristicRecord(
                        **{k: c[k] for k in CharacteristicRecord.__dataclass_fields__ if k != "outcome"},
                        outcome=Outcome(c["outcome"])))
        return [_record(r, tuple(chars.get(r["id"], []))) for r in rows]

    def add_study(self, uid: str, kind: str, at: str, station: str | None, spec: tuple[str, str, str], passed: bool,
                  simulated: bool, units: list[str], summary: str, document: dict[str, Any]) -> bool:
        """A study or master check, once (False: the database holds its uid already)."""
        self._create_pending()
        row = dict(uid=uid, kind=kind, at=at, station=station, spec_name=spec[0], spec_version=spec[1],
                   spec_sha256=spec[2], passed=passed, simulated=simulated, units=json.dumps(units),
                   summary=summary, document=json.dumps(document, sort_keys=True))
        with self._errors("refused the study"), self.engine.begin() as conn:
            insert = (postgresql.insert if conn.dialect.name == "postgresql" else sqlite.insert)(study_table)
            key = conn.execute(insert.values(**row).on_conflict_do_nothing(index_elements=["uid"])
                               .returning(study_table.c.id)).scalar()
        return key is not None

    def studies(self) -> list[dict[str, Any]]:
        """Every study and master check, oldest first, as the documents stored."""
        if self._pending:
            return []
        with self._errors("cannot be read"), self.engine.connect() as conn:
            return [json.loads(r) for r in conn.execute(select(study_table.c.document).order_by(study_table.c.id))
                    .scalars()]

    def first_for_data(self, data_sha256: str) -> QcRecord | None:
        if self._pending:
            return None
        query = select(record_table).where(record_table.c.data_sha256 == data_sha256).order_by(record_table.c.id)
        with self._errors("cannot be read"), self.engine.connect() as conn:
            row = conn.execute(query.limit(1)).mappings().first()
        return _record(row, ()) if row else None

    def for_data(self, data_sha256: str) -> list[QcRecord]:
        """Every record of the same measured data, first written first, without their
        characteristics: the first (which re-judgements refer to) and the latest."""
        if self._pending:
            return []
        query = select(record_table).where(record_table.c.data_sha256 == data_sha256).order_by(record_table.c.id)
        with self._errors("cannot be read"), self.engine.connect() as conn:
            return [_record(row, ()) for row in conn.execute(query).mappings()]


WRITTEN = ("qc_record", "qc_characteristic", "qc_release", "qc_study")   # a station inserts into these, reads all
SEQUENCES = ("qc_record", "qc_release", "qc_study")           # their ids: INSERT needs USAGE on the sequence


@dataclass(frozen=True)
class Rights:
    """What a PostgreSQL role may do to the records' tables."""
    role: str
    superuser: bool
    owns: tuple[str, ...]            # tables it owns (or a role it is a member of owns): it may disable triggers
    changes: tuple[str, ...]         # "UPDATE on qc_record" …: privileges a station must not hold
    missing: tuple[str, ...]         # "INSERT on qc_record" …: privileges a station needs and lacks

    @property
    def could_rewrite(self) -> bool:
        return self.superuser or bool(self.owns) or bool(self.changes)

    @property
    def may_write(self) -> bool:
        return not self.missing

    def why(self) -> str:
        parts = (["is a superuser (it may disable the triggers)"] if self.superuser else []) + (
            [f"owns {', '.join(self.owns)} (an owner may disable their triggers and rewrite records)"]
            if self.owns else []) + ([f"holds {', '.join(self.changes)}"] if self.changes else [])
        return " and ".join(parts)


def _rights(conn: Connection) -> Rights:
    role, superuser = conn.execute(text("SELECT current_user, rolsuper FROM pg_roles WHERE rolname = current_user")
                                   ).one()
    owns, changes, missing = [], [], []
    for table in IMMUTABLE:
        row = conn.execute(text(
            "SELECT pg_has_role(current_user, c.relowner, 'MEMBER'), has_table_privilege(c.oid, 'UPDATE'), "
            "has_table_privilege(c.oid, 'DELETE'), has_table_privilege(c.oid, 'TRUNCATE'), "
            "has_table_privilege(c.oid, 'INSERT'), has_table_privilege(c.oid, 'SELECT') "
            "FROM pg_class c WHERE c.oid = to_regclass(:t)"), {"t": table}).first()
        if row is None:
            missing.append(f"the table {table} (not there)")
            continue
        owner, update, delete, truncate, insert, select_ = row
        if owner:
            owns.append(table)
        changes += [f"{what} on {table}" for what, held in (("UPDATE", update), ("DELETE", delete),
                                                              ("TRUNCATE", truncate)) if held]
        if not select_:
            missing.append(f"SELECT on {table}")
        if table in WRITTEN and not insert:
            missing.append(f"INSERT on {table}")
    for table in SEQUENCES:
        usage = conn.execute(text("SELECT has_sequence_privilege(pg_get_serial_sequence(:t, 'id'), 'USAGE')"),
                             {"t": table}).scalar()
        if not usage:
            missing.append(f"USAGE on the id sequence of {table}")
    return Rights(role, bool(superuser), tuple(owns), tuple(changes), tuple(missing))


def init_schema(url: str, grant: tuple[str, ...] = (), password: str | None = None) -> tuple[str, int, Rights | None]:
    """An administrator's work (``qc db init``): the schema made (or upgraded) by the role
    ``url`` connects as, which then owns it, and each station role in ``grant`` given
    INSERT and SELECT only.  Returns the database's name, its schema version and, on
    PostgreSQL, the administrator's own rights (to say that it owns the tables)."""
    records = Records.open(url, create=True, password=password)
    try:
        with records._errors("refused the grant"), records.engine.begin() as conn:
            if conn.dialect.name != "postgresql":
                if grant:
                    raise RecordsError(f"--grant: {records.name} is an SQLite file; its rights are the file's "
                                       "(a station's own folder)")
                return records.name, SCHEMA_VERSION, None
            for role in grant:
                quoted = conn.dialect.identifier_preparer.quote(role)
                conn.exec_driver_sql(f"GRANT SELECT ON {', '.join(IMMUTABLE)} TO {quoted}")
                conn.exec_driver_sql(f"GRANT INSERT ON {', '.join(WRITTEN)} TO {quoted}")
                for table in SEQUENCES:
                    sequence = conn.execute(text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": table}).scalar()
                    conn.exec_driver_sql(f"GRANT USAGE ON SEQUENCE {sequence} TO {quoted}")
            return records.name, SCHEMA_VERSION, _rights(conn)
    finally:
        records.close()


def _record(row: Any, characteristics: tuple[CharacteristicRecord, ...]) -> QcRecord:
    fields = {k: row[k] for k in QcRecord.__dataclass_fields__ if k in row}
    fields["files"] = json.loads(row["files"])
    fields["diagnosis"] = tuple(json.loads(row["diagnosis"]))
    fields["notes"] = tuple(json.loads(row["notes"]))
    fields["controller"] = json.loads(row["controller"]) if row["controller"] else None
    fields["details"] = json.loads(row["details"]) if row["details"] else {}
    fields["simulated"] = bool(row["simulated"])
    fields["equipment"] = tuple(Equipment(**q) for q in json.loads(row["equipment"])) if row.get("equipment") else ()
    fields["ambient"] = json.loads(row["ambient"]) if row.get("ambient") else None
    fields["flagged"] = json.loads(row["flagged"]) if row.get("flagged") else {}
    fields["verdict"] = None if row["verdict"] is None else Outcome(row["verdict"])
    fields["status"] = RecordStatus(row["status"])
    return QcRecord(characteristics=characteristics, **{k: v for k, v in fields.items() if k != "characteristics"})


def superseded(records: list[QcRecord]) -> dict[str, str]:
    """uid → the uid of the next judgement of the same measured data (records in the
    order written): what made a record's verdict no longer the latest."""
    out: dict[str, str] = {}
    last: dict[str, str] = {}
    for r in records:
        if r.data_sha256 in last:
            out[last[r.data_sha256]] = r.uid
        last[r.data_sha256] = r.uid
    return out


def _upgrade(conn: Connection, version: int) -> None:
    """From ``version`` to this one: new nullable columns (records judged before say nothing
    of where they were measured, or which station), no row changed; each version goes in as
    a row of its own (rows are immutable)."""
    for added in range(version + 1, SCHEMA_VERSION + 1):
        for name in TABLES_ADDED.get(added, ()):
            metadata.tables[name].create(conn)
            _create_triggers(conn, (name,))
        for table, columns in ADDED[added].items():
            for name in columns:
                column = metadata.tables[table].c[name]
                default = " DEFAULT FALSE NOT NULL" if name == "simulated" else ""
                conn.exec_driver_sql(f"ALTER TABLE {table} ADD COLUMN {name} "
                                     f"{column.type.compile(dialect=conn.dialect)}{default}")
                for index in metadata.tables[table].indexes:
                    if name in index.columns:
                        index.create(conn)
        if added == 4:
            metadata.create_all(conn, tables=[release_table])
            _create_triggers(conn, TABLES_IN_4)
        conn.execute(schema_table.insert().values(version=added))


def _unreachable(exc: SQLAlchemyError) -> bool:
    """The PostgreSQL server did not answer (refused, timed out, gone mid-transaction), as
    against a login or a statement it refused: psycopg's OperationalError without an
    SQLSTATE (the connection failed before the server said anything), class 08 (connection
    exception) or 57P01-57P03 (shut down, cannot connect now)."""
    if isinstance(exc, DBAPIError) and exc.connection_invalidated:
        return True
    orig = getattr(exc, "orig", None)
    if orig is None or not type(orig).__module__.startswith("psycopg"):
        return False
    state = getattr(orig, "sqlstate", None)
    if state is None:
        # psycopg gives no SQLSTATE for an error while connecting; the server's own FATAL
        # (a refused login, no such database) says it answered, so it was reached, unless
        # it is starting up or shutting down (not reachable, as yet).
        words = str(orig)
        if "FATAL:" in words and not any(w in words for w in ("starting up", "shutting down", "not yet accepting")):
            return False
        return any(t.__name__ == "OperationalError" for t in type(orig).__mro__)
    return str(state).startswith("08") or state in ("57P01", "57P02", "57P03")


def _sqlite_connect(dbapi_connection: Any, _record: Any) -> None:
    # The driver's own transaction handling off: the "begin" listener says BEGIN IMMEDIATE.
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute(f"PRAGMA busy_timeout = {int(SQLITE_WAIT_S * 1000)}")
    cursor.execute("PRAGMA journal_mode = WAL")
    cursor.execute("PRAGMA foreign_keys = ON")
    cursor.close()


def _create_triggers(conn: Connection, tables: tuple[str, ...] = IMMUTABLE) -> None:
    """Records are never changed or deleted by a role that does not own the tables (an
    owner or a superuser may disable triggers: a station's role is neither)."""
    if conn.dialect.name == "sqlite":
        for table in tables:
            for action in ("UPDATE", "DELETE"):
                conn.exec_driver_sql(
                    f"CREATE TRIGGER {table}_no_{action.lower()} BEFORE {action} ON {table} "
                    f"BEGIN SELECT RAISE(ABORT, 'QC records are never changed or deleted'); END")
    else:
        conn.exec_driver_sql(
            "CREATE OR REPLACE FUNCTION qc_refuse_change() RETURNS trigger LANGUAGE plpgsql AS "
            "$$ BEGIN RAISE EXCEPTION 'QC records are never changed or deleted'; END $$")
        for table in tables:
            conn.exec_driver_sql(f"CREATE TRIGGER {table}_immutable BEFORE UPDATE OR DELETE OR TRUNCATE ON {table} "
                                 "FOR EACH STATEMENT EXECUTE FUNCTION qc_refuse_change()")


def station_copies(folder: Path, database: str) -> list[QcRecord]:
    """The records a station folder says it sent (``qc-queue/sent/``) to ``database`` (its name
    as rig.qc.records.safe_url gives it; each copy says which database it was queued for)."""
    sent = Path(folder) / "qc-queue" / "sent"
    docs = [json.loads(p.read_text()) for p in sorted(sent.glob("*.json"))] if sent.is_dir() else []
    return [QcRecord.from_journal(d) for d in docs if d.get("queued_for") == database]
