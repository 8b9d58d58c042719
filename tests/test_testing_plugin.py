"""The test engineer's kit as a test engineer meets it: a test file in a folder of their
own, with only this project installed, run by plain pytest."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

THETA4_TRUTH = 5.0e-3

THEIR_TEST = '''
import json

import rig


def test_one_experiment_with_a_fault_recovers_theta4(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["drop=0.0005"], seed=3)
    with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
        assert r.status().state in ("OFF", "IDLE")
        session = r.run_plan("standard", experiments=["j"], out=tmp_path / "session", date="261123")
    assert session.status == "complete"
    assert [e["label"] for e in session.experiments] == ["261123j"]
    start = tmp_path / "start.json"
    start.write_text(json.dumps({"model": "2dof", "parameters": {"theta4": 6.0e-3, "theta6": -2.5, "theta16": 1.0}}))
    # theta4 alone, with the gas parameters held, came out 3.2 sigma off in 2 of 3 runs: the
    # captured state's residual thermal offset then has nowhere to go (see issue #12's notes).
    result = session.identify(estimate=["theta4", "theta6", "theta16"], params=start)
    theta4 = result.parameters["theta4"]
    assert result.converged and abs(theta4.value - THETA4) < 3 * theta4.std, result.report()
    assert result.to_frame().loc["theta4", "value"] == theta4.value
    assert "drop" in sim.log()
'''.replace("THETA4", repr(THETA4_TRUTH))

THEIR_FAILING_TEST = '''
def test_that_fails_with_a_rig_running(virtual_rig):
    virtual_rig(faults=["estop@5"])
    virtual_rig(speed=20)
    assert False, "this test fails on purpose"
'''


def run_pytest(folder: Path, marker: str, *args: str) -> subprocess.CompletedProcess[str]:
    """Plain pytest in ``folder``; ``marker`` tags the processes it starts (environment)."""
    env = {**os.environ, "VIRTUAL_RIG_TEST_MARKER": marker}
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args], cwd=folder,
                          env=env, capture_output=True, text=True, timeout=600)


def processes_tagged(marker: str) -> list[int]:
    """Live simulator processes started under ``marker``."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            cmdline = (proc / "cmdline").read_bytes()
            environ = (proc / "environ").read_bytes()
        except OSError:
            continue
        if b"simulator\0serve" in cmdline and f"VIRTUAL_RIG_TEST_MARKER={marker}".encode() in environ:
            found.append(int(proc.name))
    return found


@pytest.fixture
def their_folder(tmp_path: Path) -> Path:
    """A folder outside the repository, with no conftest: only the installed plugin."""
    folder = tmp_path / "their-tests"
    folder.mkdir()
    assert not (folder / "conftest.py").exists() and Path(__file__).resolve().parents[1] not in folder.parents
    return folder


def test_their_suite_gets_the_fixture_and_the_api_from_the_installed_project(their_folder):
    (their_folder / "test_rig.py").write_text(THEIR_TEST)
    r = run_pytest(their_folder, uuid.uuid4().hex)
    # The head of the report holds the failed assertion; its tail the captured output and the rig's log.
    assert r.returncode == 0, r.stdout[:5000] + r.stderr[-2000:]
    assert "1 passed" in r.stdout


def test_a_failing_test_leaves_no_simulator_behind_and_reports_its_log(their_folder):
    marker = uuid.uuid4().hex
    (their_folder / "test_fails.py").write_text(THEIR_FAILING_TEST)
    r = run_pytest(their_folder, marker)
    assert r.returncode == 1 and "1 failed" in r.stdout, r.stdout[-4000:]
    assert "virtual rig 1 log" in r.stdout and "virtual rig 2 log" in r.stdout
    assert "fault: emergency stop pressed" in r.stdout   # rig 1 got to its fault while rig 2 started
    assert processes_tagged(marker) == []


def test_the_speed_option_overrides_every_rig_of_the_run(their_folder):
    (their_folder / "test_speed.py").write_text(
        "def test_speed(virtual_rig):\n"
        "    sim = virtual_rig(speed=50)\n"
        "    assert '--speed' in sim.command and sim.command[sim.command.index('--speed') + 1] == '3.0'\n")
    r = run_pytest(their_folder, uuid.uuid4().hex, "--virtual-rig-speed", "3")
    assert r.returncode == 0, r.stdout[-3000:]
