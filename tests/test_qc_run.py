"""``qc run`` end to end against ``python -m simulator serve``: a good unit passes with the
default spec, on record as simulated (the simulator names itself on both links); an
aborted run is on record without a verdict, with its reason; two runs writing to one
SQLite file both land; a run killed with SIGKILL leaves no verdict behind (and no
database: the file is made with the first record)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from rig.qc.records import Records
from rig.qc.spec import SPECS_DIR

HISTORY_KEYS = {"uid", "serial", "verdict", "status", "reason", "simulated", "judged_at", "rejudges", "superseded_by",
                "station",
                "spec", "k", "characteristics", "started", "finished", "operator", "rig", "measured_on", "details",
                "session", "data_sha256", "archive_id", "identified_by", "rejudge_reason", "equipment", "ambient",
                "flagged", "report_sha256", "previous_sha256", "record_sha256", "released"}


def qc_cmd(sim, out: Path, serial: str, *args: str) -> list[str]:
    return [sys.executable, "-m", "rig", "qc", "run", "--serial", serial, "--shaker", sim.modbus_url, "--daq",
            sim.daq_url, "--out", str(out), *args]


def history(db: Path) -> list[dict]:
    r = subprocess.run([sys.executable, "-m", "rig", "qc", "history", "--db", str(db), "--json"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def short_spec(tmp_path: Path) -> Path:
    """The default spec (one short experiment) with loose settling: a run of a few
    simulated seconds, for tests that are about the records, not the plan."""
    text = (SPECS_DIR / "default.toml").read_text()
    assert text.count("[[experiment]]") == 1
    for old, new in (("pressure_bar = 0.003", "pressure_bar = 0.5"), ("gas_temperature_C = 0.01",
                                                                       "gas_temperature_C = 10.0"),
                     ("force_N = 5.0", "force_N = 200.0"), ('version = "1.3.0"', 'version = "test"')):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "QC-short.toml"
    path.write_text(text)
    return path


def test_a_good_unit_on_the_served_rig_passes_with_the_default_spec(virtual_rig, tmp_path):
    sim = virtual_rig(unit="good", unit_seed=4, seed=3)
    station = tmp_path / "station"
    r = subprocess.run(qc_cmd(sim, station, "SN-0042", "--operator", "alice", "--rig-id", "rig-7"),
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.startswith("SN-0042: PASS") and "SIMULATED" in r.stdout.splitlines()[0]

    (doc,) = history(station / "qc-records.sqlite")
    assert set(doc) == HISTORY_KEYS
    assert (doc["verdict"], doc["status"], doc["operator"], doc["rig"]) == ("PASS", "COMPLETE", "alice", "rig-7")
    assert doc["spec"]["name"] == "default" and \
        doc["spec"]["sha256"] == hashlib.sha256((SPECS_DIR / "default.toml").read_bytes()).hexdigest()
    assert list(doc["characteristics"]) == ["gas_precharge_bar", "damping_force_0.3_N", "friction_10bar_N",
                                            "dissipated_energy_J", "drop_peak_force_kN"]
    assert all(c["outcome"] == "PASS" and c["std"] > 0 for c in doc["characteristics"].values())
    session = Path(doc["session"])
    assert session.parent == station.resolve() and session.name.startswith("SN-0042-")
    meta = json.loads((session / "session.json").read_text())
    assert meta["status"] == "complete"
    # Reached by address, the simulator said what it is on both links: the record says so, for good.
    (peers,) = meta["peers"]
    assert peers["simulated"] and peers["daq"].endswith(",SIMULATOR") and peers["controller"]["firmware"] == "1.23"
    assert doc["simulated"] is True and doc["measured_on"] == {"controller": peers["controller"], "daq": peers["daq"]}
    assert (doc["uid"], doc["rejudges"], doc["superseded_by"]) == (doc["uid"], None, None) and doc["judged_at"]

    (record,) = Records.open(str(station / "qc-records.sqlite")).find()
    for name, digest in record.files.items():
        assert hashlib.sha256((session / name).read_bytes()).hexdigest() == digest, name
    experiments = (SPECS_DIR / "default.toml").read_text().count("[[experiment]]")
    assert {"journal/daq-raw.bin", "dataset.json"} <= set(record.files) and len(record.files) == 2 + experiments
    assert record.calibration_sha256 == hashlib.sha256(
        (session / "config" / "daq-calibration.toml").read_bytes()).hexdigest()
    assert (session / "config" / "plan.toml").read_text().rstrip() == (SPECS_DIR / "default.toml").read_text().rstrip()
    report = (session / "qc-report.html").read_text()
    assert ">PASS</div>" in report and record.uid in report and "work loops" in report.lower()
    assert "class=watermark" in report and "(SIMULATED)</title>" in report


def test_an_aborted_run_is_on_record_without_a_verdict(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["estop@run+3"])
    station = tmp_path / "station"
    r = subprocess.run(qc_cmd(sim, station, "SN-0007", "--spec", str(short_spec(tmp_path))), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 3, r.stderr[-3000:]
    assert "QC run ABORTED" in r.stderr and "no verdict" in r.stderr
    (doc,) = history(station / "qc-records.sqlite")
    assert (doc["verdict"], doc["status"], doc["characteristics"]) == (None, "ABORTED", {})
    assert "emergency stop" in doc["reason"] and doc["simulated"] is True     # the session had started
    outcome = doc["details"]["session_outcome"]                               # how it ended, as data
    assert (outcome["exit_status"], outcome["exit_code"]) == ("aborted", 3) and "emergency stop" in outcome["reason"]
    session = Path(doc["session"])
    assert "safe stop done" in (session / "session.log").read_text()
    report = (session / "qc-report.html").read_text()
    assert "no verdict (ABORTED)" in report and "emergency stop" in report


def test_a_run_stops_as_soon_as_every_characteristic_is_decided(virtual_rig, tmp_path):
    """A second experiment in the plan is not run once the first has decided the unit:
    the session ends there (after the safe stop), and the record says what was used and why."""
    spec = short_spec(tmp_path)
    spec.write_text(spec.read_text() + '\n[[experiment]]\nlabel = "z"\ngroup = "middle"\nstatic_mm = 133\n'
                                       'amplitude_mm = 30\nfrequency_Hz = 2.0\nperiods = 2\n')
    sim = virtual_rig(unit="good", unit_seed=4, seed=3)
    station = tmp_path / "station"
    r = subprocess.run(qc_cmd(sim, station, "SN-0043", "--spec", str(spec)), capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    (doc,) = history(station / "qc-records.sqlite")
    session = Path(doc["session"])
    record = json.loads((session / "qc-record.json").read_text())
    (note,) = [n for n in record["notes"] if n.startswith("experiments used:")]
    assert "(1 of 2)" in note and "every characteristic decided" in note, note
    manifest = json.loads((session / "dataset.json").read_text())
    assert [e["label"][-1] for e in manifest["experiments"]] == ["a"]
    assert json.loads((session / "session.json").read_text())["status"].startswith("ended: 1 of 2 experiments")


def test_two_runs_on_one_sqlite_file_both_land(virtual_rig, tmp_path):
    spec = str(short_spec(tmp_path))
    station = tmp_path / "station"
    sims = [virtual_rig(unit="good", unit_seed=i) for i in (1, 2)]
    procs = [subprocess.Popen(qc_cmd(sim, station, f"SN-100{i}", "--spec", spec), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i, sim in enumerate(sims)]
    outcomes = [p.communicate(timeout=300) for p in procs]
    # the short plan is not the one the spec's limits were made for: any verdict will do
    verdicts = [{0: "PASS", 1: "FAIL", 4: "INCONCLUSIVE"}.get(p.returncode) for p in procs]
    assert None not in verdicts, [err[-2000:] for _, err in outcomes]
    docs = history(station / "qc-records.sqlite")
    assert sorted((d["serial"], d["status"], d["verdict"]) for d in docs) == \
        [("SN-1000", "COMPLETE", verdicts[0]), ("SN-1001", "COMPLETE", verdicts[1])]


def test_a_run_killed_with_sigkill_leaves_no_verdict(virtual_rig, tmp_path):
    sim = virtual_rig(unit="worn-seal")
    station = tmp_path / "station"
    proc = subprocess.Popen(qc_cmd(sim, station, "SN-0666", "--spec", str(short_spec(tmp_path))),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    for line in proc.stderr:            # the run's own progress is the event: capture under way
        if "capturing" in line:
            break
    else:
        raise AssertionError(f"the run ended before capturing (exit {proc.wait()})")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert not (station / "qc-records.sqlite").exists()   # made with the first record: there is none
    (session,) = [p for p in station.iterdir() if p.is_dir() and p.name != "qc-queue"]
    assert json.loads((session / "session.json").read_text())["status"] == "running"
    assert not list(session.glob("qc-*"))
