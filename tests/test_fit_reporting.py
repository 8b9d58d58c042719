"""What a fit reports beyond its estimates: Floquet multipliers per scheme, the last
iterate of an interrupted fit, bounds, progress, warnings and the experiments table.

The data are a linear oscillator's exact multisine response (tests/linear_oscillator.py)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from tests import linear_oscillator as lin


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


def _start(tmp_path: Path, **values: float) -> Path:
    path = tmp_path / "start.json"
    path.write_text(json.dumps({"model": "linear-1dof", "parameters": values}))
    return path


def test_stability_under_the_spectral_scheme_gives_the_damped_oscillators_multiplier(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    result = tmp_path / "R.json"
    proc = identify("fit", str(data), "--model", model, "--scheme", "spectral", "--params",
                    str(_start(tmp_path, c=12.0, k=4.5e4)), "--estimate", "c,k", "--stability",
                    "--output", str(result), "--quiet")
    assert proc.returncode == 0, proc.stderr + proc.stdout
    doc = json.loads(result.read_text())
    p = doc["parameters"]
    period = 1.0 / doc["experiments"]["lin"]["frequency_Hz"]
    # Free motion decays as exp(−c/(2m)·t); both multipliers of the underdamped pair have that size.
    expected = math.exp(-p["c"]["value"] / (2 * p["m"]["value"]) * period)
    assert abs(doc["experiments"]["lin"]["floquet_max_multiplier"] / expected - 1) < 0.01
    assert "Floquet |μ|max" in proc.stdout
