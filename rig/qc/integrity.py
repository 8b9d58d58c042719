"""Records nobody can rewrite unseen: each station's records form a hash chain.

A record's hash is the sha256 of its canonical JSON (every field but the hash itself,
keys sorted, no spaces, numbers of the numeric columns as floats so that SQLite and
PostgreSQL read back what was hashed).  When the database takes a record it sets the
record's ``previous_sha256`` to the hash of the same station's last record, then hashes
the record with it (rig.qc.records.Records.add, one writer per station at a time).

:func:`verify` walks each station's records in the order written: a record whose
content no longer matches its hash was **changed**; one whose ``previous_sha256`` is not
its predecessor's hash follows a **deleted** or an **inserted** record; a record
without a hash after a station's chain began was **inserted** by hand.  A station's
own copies (``OUT/qc-queue/sent/``) that the database lacks were **deleted** (the end of
a chain has no successor to notice).  A database administrator who rewrites a record
and every later hash of its station escapes the chain, but not the station's copies.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol


class Chained(Protocol):
    """What the chain reads of a record (rig.qc.records.QcRecord; a protocol here, so that
    the records' module can take its hash from this one without a loop)."""

    @property
    def uid(self) -> str: ...
    @property
    def serial(self) -> str: ...
    @property
    def station(self) -> str | None: ...
    @property
    def record_sha256(self) -> str | None: ...
    @property
    def previous_sha256(self) -> str | None: ...

    def to_journal(self) -> dict[str, Any]: ...

NUMERIC = ("value", "std", "std_fit", "u_cal", "low", "high", "nominal")


def canonical(record: Chained) -> bytes:
    """The bytes a record's hash is taken of."""
    doc: dict[str, Any] = record.to_journal()
    doc.pop("record_sha256", None)
    doc["k"] = None if doc["k"] is None else float(doc["k"])
    for c in doc["characteristics"]:
        for key in NUMERIC:
            if c.get(key) is not None:
                c[key] = float(c[key])
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def record_sha256(record: Chained) -> str:
    return hashlib.sha256(canonical(record)).hexdigest()


class Finding(StrEnum):
    CHANGED = "changed"          # its content does not match its hash
    BROKEN = "broken link"       # its previous_sha256 is not its predecessor's: one deleted or inserted before it
    INSERTED = "inserted"        # no hash, after the station's chain began
    MISSING = "missing"          # the station's own copy is not in the database


@dataclass(frozen=True)
class Problem:
    finding: Finding
    station: str | None
    uid: str
    serial: str


@dataclass(frozen=True)
class Verification:
    checked: int                     # records whose hash and link were checked
    unchained: int                   # records written before the chain (schema version < 4)
    problems: tuple[Problem, ...]

    @property
    def ok(self) -> bool:
        return not self.problems


def verify(records: list[Chained], copies: Sequence[Chained] = ()) -> Verification:
    """``records`` in the order written (the whole database, or one station's records);
    ``copies``: a station's own copies of what it sent, each of which must be there."""
    last: dict[str | None, str | None] = {}
    problems: list[Problem] = []
    checked = unchained = 0
    for r in records:
        if r.record_sha256 is None:
            if last.get(r.station) is not None:
                problems.append(Problem(Finding.INSERTED, r.station, r.uid, r.serial))
            else:
                unchained += 1
            continue
        checked += 1
        if record_sha256(r) != r.record_sha256:
            problems.append(Problem(Finding.CHANGED, r.station, r.uid, r.serial))
        if r.previous_sha256 != last.get(r.station):
            problems.append(Problem(Finding.BROKEN, r.station, r.uid, r.serial))
        last[r.station] = r.record_sha256
    held = {r.uid for r in records}
    problems += [Problem(Finding.MISSING, c.station, c.uid, c.serial) for c in copies if c.uid not in held]
    return Verification(checked, unchained, tuple(problems))


def sentence(problem: Problem) -> str:
    """One problem as the terminal says it."""
    what = {Finding.CHANGED: "changed after it was written (its content no longer matches its hash)",
            Finding.BROKEN: "does not follow its predecessor (a record before it was deleted or inserted)",
            Finding.INSERTED: "has no hash although its station's chain had begun (inserted by hand)",
            Finding.MISSING: "is in the station's own copies but not in the database (deleted)"}[problem.finding]
    return f"record {problem.uid} (unit {problem.serial}, station {problem.station or '—'}) {what}"
