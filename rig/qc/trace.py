"""Traceability: what a record says about where its verdict came from — the software,
the measured files with their sha256, the rig's calibration and register map as used,
and when the measurement was made."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import subprocess
from dataclasses import dataclass, field
from functools import cache
from importlib import metadata
from pathlib import Path

from rig.qc.records import Equipment

JOURNAL = "journal/daq-raw.bin"
CALIBRATION = "config/daq-calibration.toml"
REGISTER_MAP = "config/register-map.toml"


def now_utc() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def as_utc(stamp: str | None) -> str | None:
    """A session.json time (local, naive) as ISO 8601 UTC."""
    if not stamp:
        return None
    t = _dt.datetime.fromisoformat(stamp)
    return (t if t.tzinfo else t.astimezone()).astimezone(_dt.UTC).isoformat(timespec="seconds")


@cache
def software_version() -> str:
    """The software release as an auditor reads it: ``release TAG`` where the checkout is
    a tagged commit without changes, else ``VERSION development build, commit C`` (and
    ``with uncommitted changes``); an installed package without git: ``release VERSION``."""
    try:
        version = metadata.version("damper-rig")
    except metadata.PackageNotFoundError:
        version = "unknown"
    here = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True, timeout=5).stdout.strip()

    try:
        commit = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
        tag = git("describe", "--tags", "--exact-match", "HEAD")
    except (OSError, subprocess.SubprocessError):
        return f"release {version}"
    if not commit:
        return f"release {version}"
    if tag and not dirty:
        return f"release {tag}"
    return f"{version} development build, commit {commit}" + (" with uncommitted changes" if dirty else "")


def sha256(path: Path) -> str | None:
    if not path.is_file():
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class SessionTrace:
    path: str
    files: dict[str, str]                 # relative path → sha256: dataset.json, every CSV, the raw journal
    data_sha256: str                      # the measured data's fingerprint (dataset.json and the CSVs)
    calibration_sha256: str | None
    register_map_sha256: str | None
    started: str | None
    finished: str | None
    peers: tuple[dict, ...] = ()          # session.json's: who answered on the links, per connection
    generated: bool = False               # dataset.json says the simulator generated the data
    flagged: dict[str, list[str]] = field(default_factory=dict)   # experiment → its capture's flags (dataset.json)
    certificates: tuple[dict[str, str], ...] = ()   # the transducers' certificates the calibration file held

    @property
    def simulated(self) -> bool:
        return self.generated or any(p.get("simulated") for p in self.peers)


def trace_session(session: Path) -> SessionTrace:
    session = Path(session).resolve()
    manifest = json.loads((session / "dataset.json").read_text())
    data = ["dataset.json"] + [e["file"] for e in manifest["experiments"]]
    files = {name: digest for name in data if (digest := sha256(session / name))}
    journal = sha256(session / JOURNAL)
    fingerprint = hashlib.sha256("".join(f"{n}:{files.get(n)}\n" for n in data).encode()).hexdigest()
    if journal:
        files[JOURNAL] = journal
    meta_path = session / "session.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    peers = tuple(p for p in meta.get("peers", []) if isinstance(p, dict))
    generator = str(manifest.get("source", {}).get("generator", ""))
    flagged = {str(e["label"]): [str(f) for f in e["flags"]] for e in manifest["experiments"] if e.get("flags")}
    return SessionTrace(str(session), files, fingerprint, sha256(session / CALIBRATION), sha256(session / REGISTER_MAP),
                        as_utc(meta.get("started")), as_utc(meta.get("finished")), peers,
                        generated=generator.startswith("simulator"), flagged=flagged,
                        certificates=_certificates(session / CALIBRATION))


def _certificates(calibration: Path) -> tuple[dict[str, str], ...]:
    """The certificates of the calibration file the session copied (none for a datasheet's
    file, or a session that kept no copy)."""
    from rig.qc.calibration import CertificateError, equipment

    if not calibration.is_file():
        return ()
    try:
        return tuple(equipment(calibration))
    except CertificateError:   # a copy that no longer reads as certificates names the file by its hash alone
        return ()


def measuring_equipment(trace: SessionTrace) -> tuple[Equipment, ...]:
    """The measuring equipment a record names: the calibration file the session used, by its
    hash, and each transducer whose certificate it holds (rig.qc.calibration's
    ``equipment()``: channel, serial, certificate, due)."""
    files = () if trace.calibration_sha256 is None else (
        Equipment("DAQ calibration file (gain and offset of the four channels)", sha256=trace.calibration_sha256),)
    return files + tuple(Equipment(f"{c['channel']} transducer", serial=c.get("serial"),
                                   certificate=c.get("certificate"), due=c.get("due")) for c in trace.certificates)
