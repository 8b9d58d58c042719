"""Every malformed-dataset case of docs/dataset-format.md: exit 2, one line naming file and place."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

GOOD_ROWS = "\n".join(f"{k * 0.1:.1f},{100 + k},{3000 + k},{10 + k * 0.01}" for k in range(30))


def make(tmp_path: Path, csv: str | None = None, entry: dict | None = None, manifest_text: str | None = None) -> Path:
    d = tmp_path / "ds"
    d.mkdir()
    e = {"label": "x1", "kind": "periodic", "file": "x1.csv", "frequency_Hz": 0.5}
    if entry is not None:
        e = entry
    text = manifest_text if manifest_text is not None else json.dumps(
        {"format": "damper-dataset/1", "experiments": [e]})
    (d / "dataset.json").write_text(text)
    if csv is not None:
        (d / "x1.csv").write_text(csv)
    return d


HEADER = "time_s,stroke_mm,force_N,pressure_bar\n"
CASES = {
    "missing column": (dict(csv="time_s,stroke_mm,force_N\n0,1,2\n0.1,1,2\n"), ["x1.csv", "pressure_bar", "missing"]),
    "non-increasing time": (dict(csv=HEADER + "0,1,2,3\n0.1,1,2,3\n0.1,1,2,3\n"), ["x1.csv", "line 4", "time_s"]),
    "NaN": (dict(csv=HEADER + GOOD_ROWS.replace("3005,", "nan,", 1)), ["x1.csv", "line 7", "force_N"]),
    "text in a cell": (dict(csv=HEADER + GOOD_ROWS.replace("3005,", "abc,", 1)), ["x1.csv", "line 7", "force_N"]),
    "unknown kind": (dict(csv=HEADER + GOOD_ROWS, entry={"label": "x1", "kind": "ramp", "file": "x1.csv"}),
                     ["dataset.json", "x1", "unknown kind"]),
    "missing frequency": (dict(csv=HEADER + GOOD_ROWS, entry={"label": "x1", "kind": "periodic", "file": "x1.csv"}),
                          ["dataset.json", "x1", "frequency_Hz"]),
    "file not found": (dict(csv=None), ["x1.csv", "not found"]),
    "shorter than one period": (dict(csv=HEADER + "0,1,2,3\n0.1,1,2,3\n0.2,1,2,3\n"),
                                ["x1.csv", "less than one period"]),
    "non-uniform sampling": (dict(csv=HEADER + GOOD_ROWS.replace("\n1.0,", "\n1.05,", 1)), ["x1.csv", "not uniform"]),
    "broken JSON": (dict(csv=None, manifest_text="{\"format\": "), ["dataset.json", "not valid JSON"]),
    "wrong format": (dict(csv=None, manifest_text=json.dumps({"format": "other/2", "experiments": []})),
                     ["dataset.json", "format"]),
    "no experiment (a session ended before its first capture)": (
        dict(csv=None, manifest_text=json.dumps({"format": "damper-dataset/1", "experiments": []})),
        ["dataset.json", "no experiment in it", "before its first capture"]),
    "experiments not a list": (dict(csv=None, manifest_text=json.dumps({"format": "damper-dataset/1",
                                                                         "experiments": {"x1": 1}})),
                               ["dataset.json", "'experiments'", "expected a non-empty list"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_malformed_dataset_exits_2_with_a_one_line_message(tmp_path, case):
    kwargs, needles = CASES[case]
    d = make(tmp_path, **kwargs)
    proc = subprocess.run([sys.executable, "-m", "identify", "fit", str(d), "--estimate", "theta4",
                           "--output", str(tmp_path / "r.json")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)


def test_dataset_round_trip_keeps_unknown_keys(tmp_path):
    from identify.dataset import read_dataset, write_dataset

    d = make(tmp_path, csv=HEADER + GOOD_ROWS,
             entry={"label": "x1", "kind": "periodic", "file": "x1.csv", "frequency_Hz": 0.5, "rig": {"id": 7}})
    manifest = json.loads((d / "dataset.json").read_text())
    manifest["operator"] = "J. Doe"
    (d / "dataset.json").write_text(json.dumps(manifest))
    ds = read_dataset(d)
    out = write_dataset(ds, tmp_path / "copy")
    again = read_dataset(out)
    assert again.manifest["operator"] == "J. Doe"
    assert again.experiments[0].meta["rig"] == {"id": 7}
    assert again.experiments[0].data.equals(ds.experiments[0].data)
