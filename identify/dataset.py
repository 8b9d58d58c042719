"""The dataset interchange format (``docs/dataset-format.md``, version 1).

:func:`read_dataset` validates every rule of the format and raises :class:`DatasetError`
naming the file, the row or column, and what is wrong.  Manifest keys the code does not
know are kept, so a dataset read and written again loses nothing.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from identify.errors import InputError
from identify.files import atomic_write_bytes

FORMAT = "damper-dataset/1"
KINDS = ("periodic", "drop")
DAMPER_COLUMNS = ("stroke_mm", "force_N", "pressure_bar")
OPTIONAL_DAMPER_COLUMNS = ("gas_temperature_C",)
_UNIFORM_TOLERANCE = 1e-3  # relative deviation of a sampling step from the mean step


class DatasetError(InputError):
    """A dataset that breaks the interchange format; the message names file and place."""


@dataclass
class Experiment:
    """One experiment: its manifest entry (all keys kept) and, once loaded, its samples."""

    label: str
    kind: str
    file: str
    meta: dict[str, Any]
    data: pd.DataFrame | None = field(default=None, repr=False)

    @property
    def frequency_hz(self) -> float:
        return float(self.meta["frequency_Hz"])

    @property
    def time_s(self) -> np.ndarray:
        assert self.data is not None
        return self.data["time_s"].to_numpy()

    def column(self, name: str) -> np.ndarray:
        assert self.data is not None
        return self.data[name].to_numpy()

    @property
    def sample_rate_hz(self) -> float:
        """The declared rate where rows are absent (lost samples: read_dataset checked the
        times against it), else the rate of the consecutive rows."""
        if self.meta.get("lost_samples"):
            return float(self.meta["sample_rate_Hz"])
        t = self.time_s
        return (len(t) - 1) / (t[-1] - t[0])


@dataclass
class Dataset:
    """A dataset folder: manifest (every key kept) and experiments in manifest order."""

    path: Path
    manifest: dict[str, Any]
    experiments: list[Experiment]

    @property
    def name(self) -> str:
        return str(self.manifest.get("name", self.path.name))

    def labels(self) -> list[str]:
        return [e.label for e in self.experiments]

    def experiment(self, label: str) -> Experiment:
        for e in self.experiments:
            if e.label == label:
                return e
        raise DatasetError(f"{self.path / 'dataset.json'}: no experiment labelled {label!r} "
                           f"(labels: {', '.join(self.labels())})")

    def select(self, labels: Iterable[str] | None = None, kind: str | None = None) -> list[Experiment]:
        """Experiments by label (in the order given) and/or kind."""
        chosen = [self.experiment(lb) for lb in labels] if labels else list(self.experiments)
        return [e for e in chosen if kind is None or e.kind == kind]


# ------------------------------------------------------------------------------------------
# Reading


def _manifest_error(path: Path, where: str, what: str) -> DatasetError:
    return DatasetError(f"{path}: {where}: {what}")


def read_manifest(directory: str | Path) -> Dataset:
    """Read and check ``dataset.json`` only (no CSV is opened)."""
    directory = Path(directory)
    path = directory / "dataset.json"
    if not directory.is_dir():
        raise DatasetError(f"{directory}: dataset folder not found")
    if not path.is_file():
        raise DatasetError(f"{path}: manifest not found (a dataset folder holds dataset.json)")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise _manifest_error(path, f"line {exc.lineno}, column {exc.colno}", f"not valid JSON ({exc.msg})") from None
    except UnicodeDecodeError:
        raise _manifest_error(path, "encoding", "not UTF-8") from None
    if not isinstance(manifest, dict):
        raise _manifest_error(path, "top level", "expected a JSON object")
    fmt = manifest.get("format")
    if fmt != FORMAT:
        raise _manifest_error(path, "key 'format'", f"expected {FORMAT!r}, got {fmt!r}")
    entries = manifest.get("experiments")
    if entries == []:
        raise _manifest_error(path, "key 'experiments'", "no experiment in it: nothing to fit (a session that "
                                                         "ended before its first capture has none)")
    if not isinstance(entries, list):
        raise _manifest_error(path, "key 'experiments'", "expected a non-empty list")
    experiments: list[Experiment] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        where = f"experiments[{i}]"
        if not isinstance(entry, dict):
            raise _manifest_error(path, where, "expected an object")
        for key in ("label", "kind", "file"):
            if not isinstance(entry.get(key), str) or not entry.get(key):
                raise _manifest_error(path, where, f"required key {key!r} missing or not a string")
        label, kind = entry["label"], entry["kind"]
        where = f"experiment {label!r}"
        if label in seen:
            raise _manifest_error(path, where, "label is not unique")
        seen.add(label)
        if kind not in KINDS:
            raise _manifest_error(path, where, f"unknown kind {kind!r} (expected one of {', '.join(KINDS)})")
        if kind == "periodic":
            fr = entry.get("frequency_Hz")
            if fr is None:
                raise _manifest_error(path, where, "periodic experiment without 'frequency_Hz'")
            if not isinstance(fr, (int, float)) or isinstance(fr, bool) or not math.isfinite(fr) or fr <= 0:
                raise _manifest_error(path, where, f"'frequency_Hz' must be a positive number, got {fr!r}")
        if kind == "drop":
            dm = entry.get("drop_mass_kg")
            if not isinstance(dm, (int, float)) or isinstance(dm, bool) or not dm > 0:
                raise _manifest_error(path, where, f"drop experiment needs a positive 'drop_mass_kg', got {dm!r}")
        experiments.append(Experiment(label, kind, entry["file"], dict(entry)))
    return Dataset(directory, manifest, experiments)


def load_csv(path: Path, required: Iterable[str] = (), frequency_hz: float | None = None, *,
             lost_samples: int = 0, sample_rate_hz: float | None = None) -> pd.DataFrame:
    """Read one experiment CSV and check every rule of the format.

    ``lost_samples`` (from the manifest) allows that many absent rows on the uniform
    grid of ``sample_rate_hz``: samples the rig lost and declared, never guessed.

    Row numbers in messages are line numbers of the file (the header is line 1).
    """
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    # Fast path: a well-formed file parses straight to floats.  Anything else is read
    # again as text, so that the message can name the offending row and column.
    try:
        fast = pd.read_csv(path, dtype=float, skipinitialspace=True)
        if not np.isfinite(fast.to_numpy()).all():
            fast = None
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError):
        fast = None
    df = fast
    if df is None:
        try:
            df = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
        except pd.errors.EmptyDataError:
            raise DatasetError(f"{path}: empty file (a header and samples are required)") from None
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: cannot be parsed as CSV: {str(exc).strip()}") from None
    df.columns = [str(c).strip() for c in df.columns]
    dup = df.columns[df.columns.duplicated()].tolist()
    if dup:
        raise DatasetError(f"{path}: column {dup[0]!r} appears twice in the header")
    for col in ("time_s", *required):
        if col not in df.columns:
            raise DatasetError(f"{path}: column {col!r}: missing (header has {', '.join(df.columns)})")
    if len(df) < 2:
        raise DatasetError(f"{path}: {len(df)} sample rows; at least 2 are needed")
    numeric = {}
    for col in df.columns:
        if fast is not None:
            numeric[col] = df[col].to_numpy(dtype=float)
            continue
        text = df[col]
        values = pd.to_numeric(text, errors="coerce")
        bad = values.isna() | ~np.isfinite(values.to_numpy(dtype=float, na_value=np.nan))
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise DatasetError(f"{path}: line {row + 2}, column {col!r}: "
                               f"{text.iloc[row]!r} is not a finite number")
        numeric[col] = values.to_numpy(dtype=float)
    out = pd.DataFrame(numeric)
    t = out["time_s"].to_numpy()
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        row = int(bad[0]) + 1
        raise DatasetError(f"{path}: line {row + 2}, column 'time_s': time {t[row]!r} does not increase "
                           f"(previous {t[row - 1]!r})")
    if lost_samples:
        # Rows of samples lost on the rig are absent, declared in the manifest: the
        # remaining times must still lie on the uniform grid of the sample rate.
        if not sample_rate_hz:
            raise DatasetError(f"{path}: the manifest declares {lost_samples} lost samples but no sample_rate_Hz")
        mean_dt = 1.0 / sample_rate_hz
        steps = dt / mean_dt
        off = np.flatnonzero((np.abs(steps - np.rint(steps)) > _UNIFORM_TOLERANCE) | (np.rint(steps) < 1))
        if off.size:
            row = int(off[0]) + 1
            raise DatasetError(f"{path}: line {row + 2}, column 'time_s': step {dt[row - 1]:.9g} s is not a "
                               f"multiple of the sampling interval {mean_dt:.9g} s")
        missing = int(np.sum(np.rint(steps) - 1))
        if missing != lost_samples:
            raise DatasetError(f"{path}: column 'time_s' has {missing} missing samples, the manifest declares "
                               f"lost_samples = {lost_samples}")
    else:
        mean_dt = (t[-1] - t[0]) / (len(t) - 1)
        off = np.flatnonzero(np.abs(dt - mean_dt) > _UNIFORM_TOLERANCE * mean_dt)
        if off.size:
            row = int(off[0]) + 1
            raise DatasetError(f"{path}: line {row + 2}, column 'time_s': sampling is not uniform "
                               f"(step {dt[row - 1]:.9g} s against a mean of {mean_dt:.9g} s)")
    if frequency_hz is not None:
        covered = (t[-1] - t[0]) + mean_dt
        if covered * frequency_hz < 1.0 - 1e-9:
            need = int(math.ceil(1.0 / (frequency_hz * mean_dt)))
            raise DatasetError(f"{path}: {len(t)} samples cover {covered:.6g} s, less than one period "
                               f"({1 / frequency_hz:.6g} s at {frequency_hz:g} Hz needs {need} samples)")
    return out


def read_dataset(directory: str | Path, required_columns: Iterable[str] = DAMPER_COLUMNS,
                 labels: Iterable[str] | None = None) -> Dataset:
    """Read and check a dataset folder; load the CSVs of the chosen experiments.

    ``required_columns`` are the columns a model needs (damper columns by default; a
    declared model passes its own).  Experiments not chosen by ``labels`` keep
    ``data = None``.
    """
    ds = read_manifest(directory)
    required = tuple(required_columns)
    chosen = {e.label for e in ds.select(list(labels) if labels else None)}
    for exp in ds.experiments:
        if exp.label not in chosen:
            continue
        path = ds.path / exp.file
        freq = exp.frequency_hz if exp.kind == "periodic" else None
        exp.data = load_csv(path, required, freq, lost_samples=int(exp.meta.get("lost_samples", 0) or 0),
                            sample_rate_hz=exp.meta.get("sample_rate_Hz"))
    return ds


# ------------------------------------------------------------------------------------------
# Writing


def csv_bytes(columns: dict[str, np.ndarray], float_format: str = "%.9g") -> bytes:
    """CSV text of the given columns (header first, ``.`` decimal point)."""
    return pd.DataFrame(columns).to_csv(index=False, float_format=float_format, lineterminator="\n").encode()


def write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    atomic_write_bytes(Path(directory) / "dataset.json",
                       (json.dumps(manifest, indent=2, ensure_ascii=False) + "\n").encode("utf-8"))


def write_dataset(ds: Dataset, directory: str | Path) -> Path:
    """Write a dataset (manifest with every key kept, one CSV per loaded experiment)."""
    directory = Path(directory)
    for exp in ds.experiments:
        if exp.data is not None:
            atomic_write_bytes(directory / exp.file, csv_bytes({c: exp.data[c].to_numpy() for c in exp.data.columns}))
    manifest = dict(ds.manifest)
    manifest["format"] = FORMAT
    manifest["experiments"] = [dict(e.meta) for e in ds.experiments]
    write_manifest(directory, manifest)
    return directory
