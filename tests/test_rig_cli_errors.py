"""Bad input to ``rig run``: one line that names the culprit, exit 2 (3 for a dead link),
no traceback, and no session folder left behind."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from rig.config import DEFAULT_RIG_CONFIG
from rig.drivers.daq import probe_daq
from rig.gui.messages import Notice
from rig.gui.station import Station
from tests.conftest import HANG_S

CALIBRATION = Path(__file__).resolve().parents[1] / "rig" / "config" / "daq-calibration-datasheet.toml"


def free_port() -> int:
    """A loopback port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def swapped_calibration(tmp_path: Path) -> Path:
    """The datasheet calibration with the force and pressure tables exchanged."""
    tables = CALIBRATION.read_text().split("[[channel]]")
    tables[2], tables[3] = tables[3], tables[2]
    path = tmp_path / "swapped.toml"
    path.write_text("[[channel]]".join(tables))
    return path


def rig_run(tmp_path: Path, *args: str, shaker: str | None = None, daq: str | None = None):
    out = tmp_path / "session"
    cmd = [sys.executable, "-m", "rig", "run", "--shaker", shaker or f"tcp://127.0.0.1:{free_port()}",
           "--daq", daq or f"socket://127.0.0.1:{free_port()}", "--out", str(out), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=HANG_S), out


CASES = {
    "shaker scheme": (dict(shaker="tpc://127.0.0.1:5020"), [], 2, "shaker address 'tpc://127.0.0.1:5020'"),
    "daq scheme": (dict(daq="sokcet://127.0.0.1:5021"), [], 2, "unknown scheme 'sokcet'"),
    "daq without port": (dict(daq="socket://127.0.0.1"), [], 2, "expected socket://HOST:PORT"),
    "daq slashes": (dict(daq="socket:/127.0.0.1:5021"), [], 2, "'socket:/127.0.0.1:5021': not a device path nor a URL"),
    "missing plan": ({}, ["--plan", "no/such/plan.toml"], 2, "plan 'no/such/plan.toml': no such plan and no such "
                                                              "file; the plans: standard (built in), or the path"),
    "misspelt plan": ({}, ["--plan", "standrad"], 2, "plan 'standrad': no such plan and no such file (did you mean "
                                                     "'standard'?); the plans: standard (built in), or the path of a "
                                                     "plan TOML file"),
    "unknown letter": ({}, ["--experiments", "a,z"], 2, "has no experiment z"),
    "zero periods": ({}, ["--periods", "0"], 2, "--periods: 0: must be at least 1"),
    "negative periods": ({}, ["--periods", "-2"], 2, "--periods: -2: must be at least 1"),
    "unknown estimate": ({}, ["--identify", "--estimate", "theta99"], 2, "no parameter 'theta99'"),
    "dead controller": ({}, [], 3, "no Modbus controller answers at tcp://127.0.0.1:"),
    "port out of range": (dict(shaker="tcp://127.0.0.1:99999"), [], 2,
                          "shaker address 'tcp://127.0.0.1:99999': port '99999' is not a TCP port (1-65535)"),
    "unknown host": (dict(shaker="tcp://no-such-host.invalid:5020"), [], 3,
                     "no Modbus controller answers at tcp://no-such-host.invalid:5020 (the host name "
                     "'no-such-host.invalid' is not known here)"),
}


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_one_line_and_leaves_no_session(tmp_path, case):
    addresses, args, code, message = CASES[case]
    r, out = rig_run(tmp_path, *args, **addresses)
    assert r.returncode == code, r.stderr
    assert "Traceback" not in r.stderr
    assert message in r.stderr, r.stderr
    assert not out.exists(), sorted(p.name for p in out.iterdir())


def test_plan_with_a_toml_error_is_refused_naming_file_and_line(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[experiment]]\nlabel = "x"\nstatic_mm = 133\namplitude_mm = = 5\n')
    r, out = rig_run(tmp_path, "--plan", str(plan))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"plan {plan}: not valid TOML" in r.stderr and "line 4" in r.stderr, r.stderr
    assert not out.exists()


def test_plan_outside_the_limits_lists_every_violation(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[experiment]]\nlabel = "x"\nstatic_mm = 133\namplitude_mm = 200\nfrequency_Hz = 2\n'
                    '[[experiment]]\nlabel = "y"\nstatic_mm = 133\namplitude_mm = 5\nfrequency_Hz = 90\n')
    r, out = rig_run(tmp_path, "--plan", str(plan))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "plan refused, nothing moved (4 violations" in r.stderr, r.stderr
    assert "experiment x: stroke" in r.stderr and "experiment y: frequency 90 Hz outside" in r.stderr
    assert "experiment y: peak velocity 2.827 m/s" in r.stderr
    assert not out.exists()


def test_a_misspelt_key_in_a_plan_is_refused(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[experiment]]\nlabel = "x"\nstatic_mm = 133\namplitude_mm = 5\nfrequency_Hz = 2\nperiod = 5\n')
    r, out = rig_run(tmp_path, "--plan", str(plan))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"plan {plan}, experiment 1: unknown key period (known: " in r.stderr, r.stderr
    assert not out.exists()
    plan.write_text('ordr = "thermal"\n[[experiment]]\nlabel = "x"\nstatic_mm = 133\namplitude_mm = 5\n'
                    'frequency_Hz = 2\n')
    r, out = rig_run(tmp_path, "--plan", str(plan))
    assert r.returncode == 2 and f"plan {plan}: unknown key 'ordr' (did you mean 'order'?)" in r.stderr
    assert not out.exists()


def test_an_out_folder_that_cannot_be_made_is_bad_input(virtual_rig, tmp_path):
    sim = virtual_rig()
    # one experiment: the standard plan's thermal ordering is 8 s of CPU, past the timeout on a loaded host
    r = subprocess.run([sys.executable, "-m", "rig", "run", "--shaker", sim.modbus_url, "--daq", sim.daq_url,
                        "--experiments", "j", "--out", "/proc/no-session-here"], capture_output=True, text=True,
                       timeout=HANG_S)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "--out /proc/no-session-here: cannot create the session folder" in r.stderr


def test_swapped_calibration_is_refused_before_anything_moves(tmp_path):
    r, out = rig_run(tmp_path, "--calibration", str(swapped_calibration(tmp_path)))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "[[channel]] 2 is named 'pressure_bar', but the DAQ's channel 1 is 'force_N'" in r.stderr, r.stderr
    assert not out.exists()


def test_dead_daq_leaves_no_session(virtual_rig, tmp_path):
    sim = virtual_rig()
    r, out = rig_run(tmp_path, shaker=sim.modbus_url, daq=f"socket://127.0.0.1:{free_port()}")
    assert r.returncode == 3 and "Traceback" not in r.stderr
    assert "cannot open the DAQ at socket://127.0.0.1:" in r.stderr, r.stderr
    assert not out.exists()


def test_resume_of_a_folder_without_a_session_names_it(tmp_path):
    r = subprocess.run([sys.executable, "-m", "rig", "run", "--resume", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"{tmp_path}: nothing to resume (session.json missing)" in r.stderr, r.stderr


def test_swapped_addresses_are_named_in_one_line_and_the_simulator_goes_on(virtual_rig, tmp_path):
    sim = virtual_rig()
    # A lost link would be waited for an hour: the swap must be seen from the first
    # answers, never from a reconnect timing out (the 25 s wait).
    config = tmp_path / "rig.toml"
    config.write_text(DEFAULT_RIG_CONFIG.read_text().replace("reconnect_s = 20.0", "reconnect_s = 3600.0"))
    shaker, daq = sim.daq_url.replace("socket://", "tcp://"), sim.modbus_url.replace("tcp://", "socket://")
    r, out = rig_run(tmp_path, "--rig-config", str(config), shaker=shaker, daq=daq)
    assert r.returncode == 3 and "Traceback" not in r.stderr, r.stderr
    first, line = r.stderr.strip().splitlines()     # the first line, said at once (#34), then the error's one
    assert first.startswith("plan standard: 14 experiments") and first.endswith(f"the DAQ at {daq}")
    assert line == (f"error: the two addresses look swapped: at the controller's address {shaker} a DAQ answered "
                    f"(DAQ4,SIM0001,1.00,SIMULATOR), at the DAQ's address {daq} a Modbus controller in state OFF "
                    "answered; nothing was moved")
    assert not out.exists()
    assert probe_daq(sim.daq_url) == "DAQ4,SIM0001,1.00,SIMULATOR"       # the DAQ took the Modbus bytes and goes on

    # The console's Connect says the same in its one line.
    posted: list[object] = []
    station = Station(shaker, daq, posted.append, rig_config=str(config))
    try:
        station.connect().result(timeout=HANG_S)
    finally:
        station.close()
    assert [p.text for p in posted if isinstance(p, Notice) and p.level == "error"] == \
        [f"connect failed: {line.removeprefix('error: ')}"]
    assert probe_daq(sim.daq_url) == "DAQ4,SIM0001,1.00,SIMULATOR"
    log = sim.stop()
    assert "hydraulics on" not in log and "Traceback" not in log, log


class DaqCutAtStart:
    """A DAQ on TCP that answers the handshake, then drops the line at the first START and
    answers no more (a cable pulled as the session begins)."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        self.server.close()                            # no second client: the line stays cut
        with conn, conn.makefile("rwb", buffering=0) as line:
            for raw in line:
                command = raw.strip().decode()
                if command == "START":
                    return
                answer = {"*IDN?": "DAQ4,virtual,cut-at-start,1.0", "STOP": "OK STOP 0"}.get(command, "OK")
                line.write(answer.encode() + b"\n")


def test_a_daq_cut_at_the_first_start_is_one_line_and_on_record(virtual_rig, tmp_path):
    """Before any motion (the pace probe's START): exit 3, one line, session.json not running."""
    sim, daq = virtual_rig(), DaqCutAtStart()
    config = tmp_path / "rig.toml"
    config.write_text(DEFAULT_RIG_CONFIG.read_text().replace("reconnect_s = 20.0", "reconnect_s = 1.0"))
    # one experiment: no thermal ordering to compute (seconds of CPU that a loaded host stretches)
    r, out = rig_run(tmp_path, "--rig-config", str(config), "--experiments", "j", shaker=sim.modbus_url, daq=daq.url)
    assert r.returncode == 3 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()   # the first line, said at once (#34), then the error's one
    assert len(lines) == 2 and lines[0].startswith("plan standard: 1 experiment as listed; connecting"), r.stderr
    assert "link lost during 'START'" in lines[1], r.stderr
    status = json.loads((out / "session.json").read_text())["status"]
    assert status.startswith("aborted: DAQ at ") and status.endswith("(before anything moved)"), status


def test_a_plan_past_full_extension_is_refused_in_one_line_and_nothing_moves(virtual_rig, tmp_path):
    """Experiment m as Table 1 reads (17 ± 22 mm) commands the stroke to −5 mm, inside the
    controller's trip limits (−10 mm) but past the damper's top-out stop: refused against
    the rig's [damper] envelope before the hydraulics come on."""
    sim = virtual_rig()
    plan = tmp_path / "plan.toml"
    plan.write_text('[[experiment]]\nlabel = "m"\nstatic_mm = 17\namplitude_mm = 22\nfrequency_Hz = 1\n')
    r, out = rig_run(tmp_path, "--plan", str(plan), shaker=sim.modbus_url, daq=sim.daq_url)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    refusal = [line for line in r.stderr.splitlines() if "refused" in line]
    assert refusal == [line for line in r.stderr.splitlines() if line.strip()], r.stderr   # one line
    assert ("plan refused, nothing moved" in refusal[0]
            and "experiment m: commands the stroke to -5.0 mm, past the damper's full extension at 0.0 mm"
            in refusal[0]), r.stderr
    status = subprocess.run([sys.executable, "-m", "rig", "status", "--shaker", sim.modbus_url],
                            capture_output=True, text=True, timeout=HANG_S).stdout
    assert "state OFF" in status and "position 0.00 mm" in status, status   # no hydraulics, no move
    assert not out.exists()


def test_the_envelope_refuses_onto_a_stop_and_an_older_rig_file_checks_none(tmp_path):
    """Commanding onto the top-out stop is commanding into it; a rig file without
    [damper] (from before the envelope) keeps its behaviour; the standard set and the QC
    specs' plans stay inside."""
    from dataclasses import replace

    from identify.plans import ExperimentSpec
    from rig.config import load_rig_config
    from rig.planning.plans import Plan, check_plan, load_plan
    from rig.qc.spec import load_spec

    config = load_rig_config(None)
    assert config.stroke_envelope_m == (0.0, 0.3)
    onto = Plan("p", (ExperimentSpec("x", "", 20, 20, 1.0),))
    assert check_plan(onto, config) == ["experiment x: commands the stroke to 0.0 mm, past the damper's full "
                                        "extension at 0.0 mm"]
    assert check_plan(onto, replace(config, stroke_envelope_m=None)) == []
    old = tmp_path / "rig.toml"
    old.write_text("\n".join(line for line in DEFAULT_RIG_CONFIG.read_text().splitlines()
                             if not line.startswith(("[damper]", "full_extension_mm", "bottom_out_mm"))))
    assert load_rig_config(old).stroke_envelope_m is None
    assert check_plan(load_plan("standard"), config) == []
    for name in ("default", "transient"):
        assert check_plan(load_spec(name).plan, config) == [], name
