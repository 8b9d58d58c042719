"""A session folder: the dataset in the interchange format (dataset.json + one CSV per
experiment), the raw DAQ journal, a session log, a snapshot of the rig's
configuration, and ``session.json`` with what ``--resume`` needs.

Every file that describes captured data is written atomically (write, fsync,
rename): a crash leaves either the previous or the new version, and experiments
already captured are never rewritten.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import os
import platform
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from identify.dataset import FORMAT, Experiment, csv_bytes, write_manifest
from identify.files import atomic_write_bytes
from rig.config import CHANNELS
from rig.errors import BadInput, RigFault
from rig.events import Event, Kind
from rig.session.acquisition import ExperimentRecord

SESSION_FILE = "session.json"
CSV_SLICE_ROWS = 1000                # rows per pandas call when an experiment is written (see _csv_in_slices)


class SessionError(BadInput):
    """A session folder that cannot be created or resumed (says which and why)."""


class SessionWriteError(RigFault):
    """A file of a running session could not be written (a full, removed or read-only
    disk): the session aborts, after the safe stop; what was written before is kept."""


def _software() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("damper-rig", "numpy", "scipy", "pandas", "pymodbus", "pyserial"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return out


@dataclass
class Session:
    path: Path
    meta: dict[str, Any]
    manifest: dict[str, Any]

    @staticmethod
    def check_new(path: Path) -> None:
        """Refuse, without writing anything, a folder where a new session cannot go."""
        path = Path(path)
        if (path / SESSION_FILE).exists() or (path / "dataset.json").exists():
            raise SessionError(f"{path} already holds a session: use --resume to continue it, or another --out")
        if path.exists() and not path.is_dir():
            raise SessionError(f"--out {path}: exists and is not a folder")
        existing = next(p for p in (path, *path.absolute().parents) if p.exists())
        if not os.access(existing, os.W_OK | os.X_OK):
            raise SessionError(f"--out {path}: {existing} is not writable")

    @classmethod
    def create(cls, path: Path, *, plan_source: str, letters: list[str], periods: int | None, date: str | None,
               snapshot: dict[str, str], unit: dict[str, str], endpoints: dict[str, str],
               identify: dict[str, Any] | None = None, peers: dict[str, Any] | None = None,
               purpose: dict[str, Any] | None = None) -> Session:
        """``identify``: the fit asked for after the capture, kept so that a resume after a
        crash still does it.  ``purpose``: what the plan was designed for (its ``[purpose]``),
        kept in dataset.json, where ``identify fit`` takes its parameters by default."""
        path = Path(path)
        cls.check_new(path)
        try:
            path.mkdir(parents=True, exist_ok=True)
            for name, text in snapshot.items():
                atomic_write_bytes(path / "config" / name, text.encode())
            atomic_write_bytes(path / "config" / "software.json",
                               (json.dumps(_software(), indent=2) + "\n").encode())
        except OSError as exc:  # a disk that says no only when asked (read-only, full, /proc)
            raise SessionError(f"--out {path}: cannot create the session folder ({exc.strerror or exc})") from None
        meta: dict[str, Any] = {"plan": plan_source, "experiments": letters, "periods": periods,
                "date": date or _dt.date.today().strftime("%y%m%d"), "status": "running",
                "started": _dt.datetime.now().isoformat(timespec="seconds"), "endpoints": endpoints}
        if identify:
            meta["identify"] = identify
        if peers:   # who answered on the links, one entry per connection (a resume adds one)
            meta["peers"] = [peers]
        manifest = {"format": FORMAT, "name": f"shaker session {meta['date']} ({plan_source} plan)", "unit": unit,
                    "experiments": []}
        if purpose:
            manifest["purpose"] = purpose
        _mark_simulated(manifest, peers)
        session = cls(path, meta, manifest)
        write_manifest(path, manifest)
        session._save_meta()
        return session

    @classmethod
    def load(cls, path: Path) -> Session:
        """A stored session as it is, read only (for checks before :meth:`reopen`)."""
        path = Path(path)
        try:
            meta = json.loads((path / SESSION_FILE).read_text())
            manifest = json.loads((path / "dataset.json").read_text())
        except FileNotFoundError as exc:
            raise SessionError(f"{path}: nothing to resume ({Path(exc.filename).name} missing)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SessionError(f"{path}: unreadable session file ({exc})") from None
        for key in ("plan", "experiments", "periods", "date"):
            if key not in meta:
                raise SessionError(f"{path / SESSION_FILE}: no {key!r}; not a session this program wrote")
        for entry in manifest.get("experiments", []):
            if not (path / entry["file"]).is_file():
                raise SessionError(f"{path}: experiment {entry['label']} is in dataset.json but {entry['file']} "
                                   "is missing")
        return cls(path, meta, manifest)

    def reopen(self, peers: dict[str, Any] | None = None) -> None:
        """Mark a loaded session as running again (the resume is on record, with who
        answered on the links this time)."""
        self.meta["status"] = "running"
        self.meta.pop("outcome", None)     # the last run's; this run writes its own
        if peers:
            self.meta.setdefault("peers", []).append(peers)
            if _mark_simulated(self.manifest, peers):
                write_manifest(self.path, self.manifest)
        self.meta.setdefault("resumed", []).append(_dt.datetime.now().isoformat(timespec="seconds"))
        self._save_meta()

    # ----- contents ----------------------------------------------------------------------
    def label(self, letter: str) -> str:
        return f"{self.meta['date']}{letter}"

    def completed(self) -> set[str]:
        """Letters of the experiments already captured and written."""
        done = {e["label"] for e in self.manifest["experiments"]}
        return {x for x in self.meta["experiments"] if self.label(x) in done}

    @property
    def journal_path(self) -> Path:
        return self.path / "journal" / "daq-raw.bin"

    def write_experiment(self, record: ExperimentRecord) -> Experiment:
        """CSV then manifest, each atomically; returns the experiment as identify reads it."""
        columns = {"time_s": record.time_s, **{c: record.values[:, i] for i, c in enumerate(CHANNELS)}}
        payload = _csv_in_slices(columns)
        file = f"{record.label}.csv"
        entry = {"label": record.label, "file": file, **record.spec.metadata(), "sample_rate_Hz": record.rate_hz,
                 "periods": record.spec.periods, "settle_cycles": record.settle_cycles,
                 "steady_state": record.settled, "lost_samples": record.lost_samples,
                 "stream_lost_samples": record.stream_lost, "over_range_samples": record.over_range,
                 "recaptures": record.recaptures, "captured": _dt.datetime.now().isoformat(timespec="seconds")}
        if record.flags:
            entry["flags"] = record.flags
        try:
            atomic_write_bytes(self.path / file, payload)
            self.manifest["experiments"] = [e for e in self.manifest["experiments"] if e["label"] != record.label]
            self.manifest["experiments"].append(entry)
            write_manifest(self.path, self.manifest)
        except OSError as exc:
            raise SessionWriteError(f"{self.path}: experiment {record.label} was captured but could not be written "
                                    f"({exc.strerror or exc})") from None
        exp = Experiment(record.label, "periodic", file, dict(entry))
        # Identification in memory sees exactly the numbers in the file.
        exp.data = pd.read_csv(io.BytesIO(payload))
        return exp

    def finish(self, status: str, outcome: dict[str, Any] | None = None) -> None:
        """How the session ended: the sentence people read (``status``) and, beside it,
        the outcome as data (``outcome``: :meth:`rig.session.outcome.RunResult.to_json`)."""
        self.meta["status"] = status
        if outcome is not None:
            self.meta["outcome"] = outcome
        self.meta["finished"] = _dt.datetime.now().isoformat(timespec="seconds")
        self._save_meta()

    def _save_meta(self) -> None:
        atomic_write_bytes(self.path / SESSION_FILE, (json.dumps(self.meta, indent=2) + "\n").encode())


class SessionLog:
    """Inline subscriber: every event as one JSON object per line of ``session.log``
    (``time`` ISO 8601 to the millisecond, ``kind``, ``experiment``, then the kind's
    fields, :data:`rig.events.FIELDS`), flushed at once, so that tools can read it
    (:func:`read_log`) and a crash loses no line but the one being written.
"""

    def __init__(self, path: Path) -> None:
        try:
            self._file = open(path, "a", encoding="utf-8")
        except OSError as exc:
            raise SessionWriteError(f"{path}: the session log cannot be written ({exc.strerror or exc})") from None

    def __call__(self, event: Event) -> None:
        # Milliseconds: what a session spends between two phases is what a rig's time is made of.
        stamp = _dt.datetime.fromtimestamp(event.time).astimezone().isoformat(timespec="milliseconds")
        record = {"time": stamp, "kind": str(event.kind), "experiment": event.experiment,
                  **{k: _plain(v) for k, v in event.data.items()}}
        self._file.write(json.dumps(record, ensure_ascii=False, default=str) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _plain(value: Any) -> Any:
    """A field as JSON holds it: floats to six significant digits (no channel is measured
    finer; seventeen digits of float noise helped no reader), NaN and infinity as null."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(f"{value:.6g}") if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def read_log(path: Path) -> list[Event]:
    """The events of a ``session.log`` (a line that is not a JSON object, as sessions
    before this format wrote, comes back as a log event holding the line)."""
    events = []
    for line in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            record = json.loads(line)
            stamp = _dt.datetime.fromisoformat(record.pop("time")).timestamp()
            kind, experiment = Kind(record.pop("kind")), record.pop("experiment")
        except (ValueError, KeyError, TypeError, AttributeError):
            if line.strip():
                events.append(Event(Kind.LOG, None, {"message": line}, 0.0))
            continue
        events.append(Event(kind, experiment, record, stamp))
    return events


def _mark_simulated(manifest: dict[str, Any], peers: dict[str, Any] | None) -> bool:
    """The dataset's own file says SIMULATED where a peer named itself a simulator, so
    that the data keep the mark wherever they are copied (its CSVs are described by it);
    True when the mark was added now."""
    if not (peers and peers.get("simulated")) or manifest.get("simulated"):
        return False
    manifest["simulated"] = True
    manifest["name"] = f"{manifest.get('name', 'session')} (SIMULATED: measured on a simulator, not on hardware)"
    return True


def _csv_in_slices(columns: dict[str, np.ndarray]) -> bytes:
    """:func:`identify.dataset.csv_bytes`, byte for byte, :data:`CSV_SLICE_ROWS` rows at a time.

    pandas writes a whole CSV in one C call that holds the interpreter lock: 60 ms for a
    24,000-row experiment on an idle machine, several times that under load, during which
    every other thread of the process waits (the console's window, the DAQ reader).  A
    slice at a time lets them in between."""
    n = len(next(iter(columns.values())))
    parts = []
    for start in range(0, max(n, 1), CSV_SLICE_ROWS):
        text = csv_bytes({name: values[start:start + CSV_SLICE_ROWS] for name, values in columns.items()})
        parts.append(text if start == 0 else text.split(b"\n", 1)[1])
    return b"".join(parts)
