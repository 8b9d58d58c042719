"""A station's measurement-system studies and its daily master check, stored as the
station's own immutable files (``DIR/qc-studies/*.json``, written once, never replaced)
and, where the records database takes them, as study records (rig.qc.records).

The daily master check tests the master unit against its reference values
(``REF.toml``); it passes when every characteristic lies within ``fraction`` of its
tolerance T = high − low of its reference value, ``fraction`` set in the station's
certificate file::

    [master_check]
    fraction = 0.1          # |value − reference| ≤ fraction·T
    valid = "day"           # until the end of the calendar day (local), or a number of hours (a shift)

Where the station's certificate file has a ``[master_check]`` table, ``qc run`` refuses
production units until a check passed within its validity (:func:`gate`); the console
calls :func:`gate` too, to show why.  A reference file::

    master = "MU-0001"
    [reference]             # each characteristic's reference value, in its spec unit
    gas_precharge_bar = 6.000
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from identify.files import atomic_write_bytes
from rig.errors import BadInput
from rig.qc.spec import Characteristic, Spec
from rig.tomlfile import read_toml

STUDIES_DIR = "qc-studies"


class StudyInputError(BadInput):
    """A reference file, a master-check setting or a study's input that cannot be used."""


@dataclass(frozen=True)
class MasterCheckPolicy:
    fraction: float
    valid: str | float          # "day" or hours

    def valid_until(self, at: _dt.datetime) -> _dt.datetime:
        if self.valid == "day":
            local = at.astimezone()
            return local.replace(hour=0, minute=0, second=0, microsecond=0) + _dt.timedelta(days=1)
        return at + _dt.timedelta(hours=float(self.valid))


def master_check_policy(calibration: str | Path | None) -> MasterCheckPolicy | None:
    """The ``[master_check]`` of a station's certificate file; None where there is none
    (the datasheet's calibration, a file without the table): no daily check enforced."""
    if calibration is None:
        return None
    path = Path(calibration)
    _, doc = read_toml(path, StudyInputError, "calibration ")
    table = doc.get("master_check")
    if table is None:
        return None
    where = f"calibration {path}, [master_check]"
    if not isinstance(table, dict) or set(table) - {"fraction", "valid"}:
        raise StudyInputError(f"{where}: expected fraction and valid")
    fraction = table.get("fraction")
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0 < fraction <= 0.5:
        raise StudyInputError(f"{where}: fraction must be a number in (0, 0.5] (of the tolerance), not {fraction!r}")
    valid = table.get("valid", "day")
    if not (valid == "day" or (isinstance(valid, (int, float)) and not isinstance(valid, bool) and valid > 0)):
        raise StudyInputError(f"{where}: valid must be \"day\" or a positive number of hours, not {valid!r}")
    return MasterCheckPolicy(float(fraction), valid if valid == "day" else float(valid))


@dataclass(frozen=True)
class Reference:
    source: str
    master: str
    values: dict[str, float]


def load_reference(path: str | Path, spec: Spec) -> Reference:
    path = Path(path)
    _, doc = read_toml(path, StudyInputError, "reference ")
    where = f"reference {path}"
    master, values = doc.get("master"), doc.get("reference")
    if not isinstance(master, str) or not master:
        raise StudyInputError(f"{where}: no 'master' (the master unit's serial)")
    if not isinstance(values, dict):
        raise StudyInputError(f"{where}: no [reference] table of the characteristics' reference values")
    names = [c.name for c in spec.characteristics]
    missing = [n for n in names if n not in values]
    if missing:
        raise StudyInputError(f"{where}: no reference value for {', '.join(missing)} (spec {spec.name})")
    bad = [n for n in values if n not in names or isinstance(values[n], bool)
           or not isinstance(values[n], (int, float)) or not math.isfinite(values[n])]
    if bad:
        raise StudyInputError(f"{where}: {bad[0]!r} is not a characteristic of spec {spec.name} with a number")
    return Reference(str(path), master, {n: float(values[n]) for n in names})


def tolerance(c: Characteristic) -> float:
    """T = high − low: a study needs both limits."""
    if c.low is None or c.high is None:
        raise StudyInputError(f"characteristic {c.name}: a one-sided limit has no tolerance width for a study")
    return c.high - c.low


@dataclass(frozen=True)
class Drift:
    """One characteristic of a master check."""

    characteristic: str
    title: str
    unit: str
    value: float | None
    reference: float
    limit: float                     # the allowed |value − reference|
    passed: bool

    @property
    def deviation(self) -> float | None:
        return None if self.value is None else self.value - self.reference


def master_check(spec: Spec, reference: Reference, values: dict[str, float | None],
                 policy: MasterCheckPolicy) -> list[Drift]:
    out = []
    for c in spec.characteristics:
        v, ref = values.get(c.name), reference.values[c.name]
        limit = policy.fraction * tolerance(c)
        out.append(Drift(c.name, c.shown, c.unit, v, ref, limit, v is not None and abs(v - ref) <= limit))
    return out


# ----- stored studies ---------------------------------------------------------------------------
@dataclass(frozen=True)
class StudyRecord:
    """A study or a master check as stored: ``kind`` "type1", "type3" or "check"; ``result``
    its figures (JSON); ``passed`` whether it met its goals."""

    uid: str
    kind: str
    at: str                          # ISO 8601, UTC, to the microsecond: when it ended (the order of two in one second)
    station: str | None
    spec_name: str
    spec_version: str
    spec_sha256: str
    calibration: str | None          # the certificate file's path
    units: tuple[str, ...]           # the master, or the units of a type 3
    passed: bool
    result: dict[str, Any]
    records: tuple[str, ...] = ()    # the uids of the QC records of its runs
    simulated: bool = False
    equipment: tuple[dict[str, str], ...] = ()
    summary: str = ""                # one line: what it found
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> StudyRecord:
        d = dict(doc)
        d["units"], d["records"] = tuple(d["units"]), tuple(d["records"])
        d["equipment"] = tuple(d.get("equipment", ()))
        return cls(**d)


def new_uid() -> str:
    return str(uuid.uuid4())


def store(folder: Path, study: StudyRecord) -> Path:
    """The station's own copy, written once (an existing file is never replaced)."""
    d = Path(folder) / STUDIES_DIR
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"{study.at[:19].replace(':', '')}-{study.kind}-{study.uid[:8]}.json"
    if path.exists():
        raise FileExistsError(path)
    atomic_write_bytes(path, (json.dumps(study.to_json(), indent=2) + "\n").encode())
    os.chmod(path, 0o444)
    return path


def stored(folder: Path) -> list[StudyRecord]:
    d = Path(folder) / STUDIES_DIR
    if not d.is_dir():
        return []
    return sorted((StudyRecord.from_json(json.loads(p.read_text())) for p in d.glob("*.json")), key=lambda s: s.at)


@dataclass(frozen=True)
class GateState:
    """Why production may or may not be tested now (the console shows :attr:`sentence`)."""

    allowed: bool
    sentence: str
    last: StudyRecord | None = None


def gate(folder: Path, calibration: str | Path | None, now: _dt.datetime | None = None) -> GateState:
    """Whether the daily master check allows production units now at the station in
    ``folder``: always where the certificate file sets no ``[master_check]``; else only
    after a check passed, with this certificate file, within its validity."""
    policy = master_check_policy(calibration)
    if policy is None:
        return GateState(True, "no daily master check required by this station's calibration")
    now = now or _dt.datetime.now(_dt.UTC)
    checks = [s for s in stored(folder) if s.kind == "check"]
    if not checks:
        return GateState(False, "no master check on record: run python -m rig qc check --master SERIAL first")
    last = checks[-1]
    at = _dt.datetime.fromisoformat(last.at)
    if not last.passed:
        return GateState(False, f"the last master check ({last.at[:16]} UTC, master {last.units[0]}) FAILED: "
                                f"{last.summary}; find the cause, then check again", last)
    until = policy.valid_until(at)
    if now >= until:
        return GateState(False, f"the last master check passed at {last.at[:16]} UTC and was valid until "
                                f"{until.astimezone(_dt.UTC).isoformat(timespec='minutes')[:16]} UTC: "
                                "check the master again", last)
    if calibration is not None and last.calibration is not None and \
            Path(last.calibration).resolve() != Path(calibration).resolve():
        return GateState(False, f"the last master check used other certificates ({last.calibration}): "
                                "check the master again with these", last)
    return GateState(True, f"master check passed at {last.at[:16]} UTC (master {last.units[0]})", last)
