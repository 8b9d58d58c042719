"""Sessions end to end over the real protocols, against ``python -m simulator serve``:
capture, storage, identification, and what happens when things go wrong."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from rig.drivers.frames import FrameParser
from rig.session.storage import read_log
from tests.conftest import HANG_S

TOLERANCE = {"theta4": 1e-3, "theta6": 1e-3, "theta16": 1e-2}
NOMINAL = {"theta4": 5.0e-3, "theta6": -3.0, "theta16": 0.85}
START = Path(__file__).resolve().parents[1] / "examples" / "start-2dof.json"


def rig_cmd(sim, out: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "rig", "run", "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out", str(out),
            "--date", "261122", *args]


def run_rig(sim, out: Path, *args: str, timeout: float = HANG_S) -> subprocess.CompletedProcess:
    return subprocess.run(rig_cmd(sim, out, *args), capture_output=True, text=True, timeout=timeout)


def manifest(out: Path) -> dict:
    return json.loads((out / "dataset.json").read_text())


def test_session_files_and_identify_from_files_gives_the_same_numbers(virtual_rig, tmp_path):
    sim = virtual_rig()
    out = tmp_path / "session"
    r = run_rig(sim, out, "--experiments", "j,n,l", "--identify", "--params", str(START))
    assert r.returncode == 0, r.stderr[-3000:]
    m = manifest(out)
    assert [e["label"] for e in m["experiments"]] == ["261122j", "261122n", "261122l"]
    for e in m["experiments"]:
        assert e["steady_state"] and e["lost_samples"] == 0 and e["frequency_Hz"] in (2.0, 0.5)
    for name in ("config/rig.toml", "config/daq-calibration.toml", "config/register-map.toml", "config/plan.txt",
                 "config/software.json", "session.log", "session.json", "journal/daq-raw.bin", "RESULT.json",
                 "report.txt"):
        assert (out / name).is_file(), name
    assert json.loads((out / "session.json").read_text())["status"] == "complete"
    in_memory = json.loads((out / "RESULT.json").read_text())
    f = subprocess.run([sys.executable, "-m", "identify", "fit", str(out), "--params", str(START), "--estimate",
                        "theta4,theta6,theta16", "--output", str(tmp_path / "R.json"), "--quiet"],
                       capture_output=True, text=True, timeout=HANG_S)
    assert f.returncode == 0, f.stderr
    from_files = json.loads((tmp_path / "R.json").read_text())
    for k in TOLERANCE:
        assert from_files["parameters"][k]["value"] == in_memory["parameters"][k]["value"]
        assert from_files["parameters"][k]["std"] == in_memory["parameters"][k]["std"]


@pytest.mark.slow
def test_standard_plan_over_modbus_and_serial_recovers_the_truth(virtual_rig, tmp_path):
    sim = virtual_rig(seed=5)
    out = tmp_path / "standard"
    r = run_rig(sim, out, "--identify", "--params", str(START), timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads((out / "RESULT.json").read_text())
    assert result["converged"] and len(result["experiments"]) == 14
    sim.stop()
    announced = json.loads((out / "session.json").read_text())["estimated_rig_time_s"]
    assert announced == pytest.approx(sim.rig_time_s(), rel=0.2)   # the ETA the operator was given
    for k, tol in TOLERANCE.items():
        assert abs(result["parameters"][k]["value"] / NOMINAL[k] - 1) < tol, (k, result["parameters"][k])


def test_line_faults_are_counted_exactly_and_the_capture_recaptured_or_flagged(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["corrupt=1e-4", "drop=1e-3", "overflow@run+5=500"])
    out = tmp_path / "faults"
    r = run_rig(sim, out, "--experiments", "j")
    assert r.returncode == 0, r.stderr[-3000:]
    # a simulator at 50x: the console says so, and what it means for the holds
    assert re.search(r"the links run [\d.]+ rig seconds per second of this computer's clock \(the DAQ's sample count "
                     r"over the pace probe's 5 short streams before the first experiment\): conditioning holds "
                     r"shorter than \d+ s", r.stderr)
    assert re.search(r"session took \d+:\d\d min:s of this computer's clock; at [\d.]+ rig seconds per second of "
                     r"this computer's clock \(the DAQ's sample count over \d+ s of this session's streams that ended "
                     r"as planned\), about \d+:\d\d min:s of rig time; announced \d+:\d\d", r.stderr), r.stderr[-2000:]
    sim.stop()
    (entry,) = manifest(out)["experiments"]
    assert sim.lost_frames() > 500
    # the reader's count equals the simulator's: the experiment's streams and the pace probe's
    probe = re.search(r"pace probe: \d+ samples taken, (\d+) lost", (out / "session.log").read_text())
    assert probe is not None and entry["stream_lost_samples"] + int(probe.group(1)) == sim.lost_frames()
    # a window is captured again for a burst, not for the line's steady loss (its holes declared)
    log = (out / "session.log").read_text()
    assert entry["recaptures"] > 0 or entry["lost_samples"] == 0 or "as the line's steady loss predicts" in log
    if entry["lost_samples"]:
        assert any("lost" in f for f in entry["flags"])
    # identify accepts the declared holes and nothing else
    f = subprocess.run([sys.executable, "-m", "identify", "fit", str(out), "--estimate", "theta4", "--output",
                        str(tmp_path / "R.json"), "--quiet"], capture_output=True, text=True, timeout=HANG_S)
    assert f.returncode == 0, f.stderr


def test_modbus_link_lost_mid_session_reconnects_and_continues(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["modbus-down@run+10=25"])   # 0.5 s of wall time at 50x, below the 2 s watchdog
    out = tmp_path / "link"
    r = run_rig(sim, out, "--experiments", "j")
    assert r.returncode == 0, r.stderr[-3000:]
    log = (out / "session.log").read_text()
    assert f"Modbus link to {sim.modbus_url} lost" in log and f"Modbus link to {sim.modbus_url} back" in log
    assert json.loads((out / "session.json").read_text())["status"] == "complete"
    assert len(manifest(out)["experiments"]) == 1


@pytest.mark.slow
def test_killed_mid_experiment_resume_finishes_and_keeps_earlier_files(virtual_rig, tmp_path):
    sim = virtual_rig()
    out = tmp_path / "killed"
    proc = subprocess.Popen(rig_cmd(sim, out, "--experiments", "j,n", "--identify", "--params", str(START)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = out / "261122j.csv"
    deadline = time.monotonic() + HANG_S
    while not first.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert first.exists()
    journal = out / "journal" / "daq-raw.bin"
    size_after_j = journal.stat().st_size
    while journal.stat().st_size < size_after_j + 200_000 and time.monotonic() < deadline:
        time.sleep(0.05)                                # into experiment n's stream
    digest = hashlib.sha256(first.read_bytes()).hexdigest()
    os.kill(proc.pid, signal.SIGKILL)
    killed_at = time.time()
    proc.wait()
    assert killed_at - journal.stat().st_mtime < 1.0     # flushed at most about a second before the kill
    parser = FrameParser()
    raw = journal.read_bytes()
    assert raw.startswith(b"OK STOP 0\nDAQ4,")                # the handshake is journaled too
    tail = raw.rsplit(b"OK STOP ", 1)[1].split(b"\n", 1)[1]   # experiment n's stream after its START's OK
    assert tail.startswith(b"OK\n")
    block = parser.feed(tail[3:])
    assert len(block) > 1000 and parser.counters.lost_samples == 0

    c = ModbusTcpClient(sim.host, port=sim.port, timeout=2)   # the app is dead: the watchdog stops the shaker
    assert c.connect()
    deadline = time.monotonic() + HANG_S
    while c.read_input_registers(0, count=2, device_id=1).registers != [5, 4] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert c.read_input_registers(0, count=2, device_id=1).registers == [5, 4]
    c.close()
    # Resuming says what is latched and how to clear it, and moves nothing.
    refused = subprocess.run([sys.executable, "-m", "rig", "run", "--resume", "--out", str(out)],
                             capture_output=True, text=True, timeout=HANG_S)
    assert refused.returncode == 3 and "Traceback" not in refused.stderr
    assert "holds a latched alarm: watchdog" in refused.stderr and "--reset-alarm" in refused.stderr, refused.stderr
    assert json.loads((out / "session.json").read_text())["status"] == "running"   # as the kill left it

    r = subprocess.run([sys.executable, "-m", "rig", "run", "--resume", "--out", str(out), "--reset-alarm"],
                       capture_output=True, text=True, timeout=HANG_S)   # the printed advice, followed
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads((out / "session.json").read_text())["status"] == "complete"
    assert "alarm latched before the session: watchdog; cleared by --reset-alarm" in (out / "session.log").read_text()
    # The identification asked for when the session began is done when it completes.
    assert json.loads((out / "RESULT.json").read_text())["converged"]
    assert hashlib.sha256(first.read_bytes()).hexdigest() == digest
    assert [e["label"] for e in manifest(out)["experiments"]] == ["261122j", "261122n"]
    assert "resuming: 1 experiment kept" in (out / "session.log").read_text()
    data = np.loadtxt(out / "261122n.csv", delimiter=",", skiprows=1)
    assert len(data) == 3000


def test_an_alarm_ends_the_command_with_exit_3_after_the_safe_stop(virtual_rig, tmp_path):
    """The command line's view; the policies themselves are tested in-process
    (tests/test_acquisition_machine.py)."""
    sim = virtual_rig(faults=["estop@run+10"])
    out = tmp_path / "abort"
    r = run_rig(sim, out, "--experiments", "j,n")
    assert r.returncode == 3, r.stderr[-3000:]
    events = read_log(out / "session.log")
    assert [(e.experiment, e.data["message"][:28]) for e in events if e.kind == "alarm"] == \
        [("261122j", "shaker alarm: emergency stop")]
    assert any(e.kind == "phase" and e.data.get("reason", "").startswith("shaker alarm: emergency stop")
               for e in events)
    assert "safe stop done" in (out / "session.log").read_text()
    assert json.loads((out / "session.json").read_text())["status"].startswith("aborted: shaker alarm: emergency stop")
    assert manifest(out)["experiments"] == []


def test_ctrl_c_ramps_out_switches_hydraulics_off_and_leaves_consistent_files(virtual_rig, tmp_path):
    sim = virtual_rig()
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(rig_cmd(sim, out, "--experiments", "j"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    c = ModbusTcpClient(sim.host, port=sim.port, timeout=2)
    assert c.connect()
    deadline = time.monotonic() + HANG_S
    while c.read_input_registers(0, count=1, device_id=1).registers[0] != 4 and time.monotonic() < deadline:
        time.sleep(0.05)                                # RUNNING
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=HANG_S)
    assert proc.returncode == 130, err
    assert c.read_input_registers(0, count=2, device_id=1).registers == [0, 0]   # OFF, no alarm
    c.close()
    assert json.loads((out / "session.json").read_text())["status"] == "interrupted (SIGINT)"
    assert manifest(out)["experiments"] == []
    assert "safe stop:" not in err                     # no safe-stop step failed


def test_daq_link_dropped_mid_experiment_is_reopened_and_the_gap_counted(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["disconnect@run+10"])
    out = tmp_path / "daqlink"
    r = run_rig(sim, out, "--experiments", "j")
    assert r.returncode == 0, r.stderr[-3000:]
    log = (out / "session.log").read_text()
    assert "DAQ link lost" in log and "DAQ link back" in log
    (entry,) = manifest(out)["experiments"]
    assert entry["stream_lost_samples"] > 0 and entry["lost_samples"] == 0


def test_manual_commands_and_monitor(virtual_rig):
    sim = virtual_rig()

    def rig(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "rig", *args], capture_output=True, text=True, timeout=HANG_S)

    assert "state OFF" in rig("status", "--shaker", sim.modbus_url).stdout
    refused = rig("move", "9999", "--shaker", sim.modbus_url)
    assert refused.returncode == 2 and "outside the stroke limits" in refused.stderr
    assert "state OFF" in rig("status", "--shaker", sim.modbus_url).stdout   # refused: not even the hydraulics
    moved = rig("move", "120", "--shaker", sim.modbus_url)
    assert moved.returncode == 0 and "at static position 120.00 mm" in moved.stdout, moved.stderr
    refused = rig("move", "400", "--shaker", sim.modbus_url)
    assert refused.returncode == 2 and "outside the stroke limits" in refused.stderr
    stopped = rig("stop", "--hydraulics-off", "--shaker", sim.modbus_url)
    assert "state OFF" in stopped.stdout
    monitor = rig("monitor", "--daq", sim.daq_url, "--duration", "1")
    assert monitor.returncode == 0 and "stroke_mm" in monitor.stdout and "lost 0" in monitor.stdout


def test_the_console_gives_the_rig_time_taken_and_announced_in_minutes_and_seconds():
    """A one-experiment session of 84 s announced at 71 s: whole minutes said 'took 1
    min; announced 1 min' and hid a 18 % error."""
    import io

    from rich.console import Console

    from rig.events import Event
    from rig.session.progress import ConsoleProgress

    now = [100.0]
    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=200), {"261124n": 71.0}, 1.0, lambda: now[0])
    now[0] += 84.0
    progress(Event("session-end"))
    text = out.getvalue()
    assert "session: 1 experiment, about 1:11 min:s of rig time" in text, text
    assert "session took 1:24 min:s of rig time; announced 1:11" in text, text


def test_the_console_says_the_rig_time_taken_at_the_pace_the_session_measured_last():
    """The probe said 6.95 rig s/s on a busy host; the session's streams said 10: the
    rig time taken is the wall time at the session's pace, read when it ends."""
    import io

    from rich.console import Console

    from rig.events import Event
    from rig.session.progress import ConsoleProgress

    now, pace = [100.0], [6.95]
    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=200), {"261126l": 110.0}, lambda: pace[0], lambda: now[0])
    now[0] += 11.0
    pace[0] = 10.0
    progress(Event("session-end"))
    assert "session took 0:11 min:s of this computer's clock; at 10 rig seconds per second of this computer's " \
           "clock (the DAQ's sample count over the pace given), about 1:50 min:s of rig time; announced 1:50" \
           in out.getvalue(), out.getvalue()


def test_the_eta_trusts_the_experiments_done_as_far_as_they_are_the_session():
    """Two experiments of 100 s announced; the first took 120 s of rig time (12 s of wall
    clock at 10x): the second is expected to take 110 s, not 120 s (one experiment's
    settling is tens of per cent off either way), 11 s of wall clock at the pace."""
    import io

    from rich.console import Console

    from rig.events import Event
    from rig.session.progress import ConsoleProgress

    now = [0.0]
    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=200), {"261126a": 100.0, "261126b": 100.0}, 10.0,
                               lambda: now[0])
    now[0] = 12.0
    progress(Event("experiment-done", "261126a", {"file": "261126a.csv", "samples": 6000, "lost": 0, "flags": []}))
    assert "About 0:11 left (m:s of wall clock)." in out.getvalue(), out.getvalue()
