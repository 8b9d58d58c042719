"""Plans that do not wait (issue 36): ``capture = "transient"`` records from RUN on, over
the real protocols against the served simulator, and the session's fit takes them as
transients."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import HANG_S

PLAN = """name = "no-wait"
capture = "transient"
periods = 4

[[experiment]]
label = "j"
static_mm = 133
amplitude_mm = 10
frequency_Hz = 2.0

[[experiment]]
label = "n"
static_mm = 14
amplitude_mm = 10
frequency_Hz = 2.0
"""


def test_a_transient_plan_captures_from_run_without_settling_and_is_fitted_as_transient(virtual_rig, tmp_path):
    sim = virtual_rig()
    plan = tmp_path / "no-wait.toml"
    plan.write_text(PLAN)
    out = tmp_path / "session"
    r = subprocess.run([sys.executable, "-m", "rig", "run", "--shaker", sim.modbus_url, "--daq", sim.daq_url,
                        "--out", str(out), "--date", "261126", "--plan", str(plan), "--identify",
                        "--estimate", "theta4,theta6,theta16"], capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-3000:]
    manifest = json.loads((out / "dataset.json").read_text())
    for e in manifest["experiments"]:
        assert e["capture"] == "transient" and e["settle_cycles"] == 0 and e["lost_samples"] == 0
    log = (out / "session.log").read_text()
    assert "transient capture" in log and "steady state after" not in log
    result = json.loads((out / "RESULT.json").read_text())
    assert {e["capture"] for e in result["experiments"].values()} == {"transient"}
    p = result["parameters"]
    assert abs(p["theta4"]["value"] / 5.0e-3 - 1) < 0.01 and abs(p["theta6"]["value"] / -3.0 - 1) < 0.01
    assert p["theta16"]["std"] is not None


def _qc(sim, station, serial: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", "qc", "run", "--spec", "transient", "--serial", serial,
                           "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out", str(station)],
                          capture_output=True, text=True, timeout=HANG_S)


def test_the_transient_qc_spec_passes_a_good_unit_and_fails_a_leaking_one_from_records_taken_at_run(
        virtual_rig, tmp_path):
    good = _qc(virtual_rig(unit="good", unit_seed=4, seed=3), tmp_path / "station", "SN-0042")
    assert good.returncode == 0, good.stderr[-3000:]
    assert good.stdout.startswith("SN-0042: PASS")
    (session,) = [p for p in (tmp_path / "station").iterdir() if p.name.startswith("SN-0042-")]
    (entry,) = json.loads((session / "dataset.json").read_text())["experiments"]
    assert entry["capture"] == "transient" and entry["settle_cycles"] == 0
    leak = _qc(virtual_rig(unit="gas-leak", unit_seed=1, seed=5), tmp_path / "station", "SN-0043")
    assert leak.returncode == 1, leak.stdout + leak.stderr[-3000:]
    assert leak.stdout.startswith("SN-0043: FAIL")
