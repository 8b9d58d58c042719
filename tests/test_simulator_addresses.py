"""``simulator serve`` takes the addresses in the forms ``rig`` takes them
(``tcp://`` for the controller, ``socket://`` or a device path for the DAQ; the
earlier ``HOST:PORT``, ``tcp://`` DAQ and ``rtu:pty`` still work) and prints what
``rig`` is to be given, verbatim: a test copies the printed options into ``rig``."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from simulator.cli import main, parse_daq, parse_modbus

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("text", "tcp"), [("tcp://127.0.0.1:5020", ("127.0.0.1", 5020)),
                                           ("127.0.0.1:5020", ("127.0.0.1", 5020)),
                                           ("tcp://:0", ("127.0.0.1", 0)),
                                           ("tcp://localhost:502", ("localhost", 502)),
                                           ("rtu:pty", None)])
def test_modbus_forms(text, tcp):
    endpoint = parse_modbus(text)
    assert endpoint.tcp == tcp and endpoint.link is None


@pytest.mark.parametrize(("text", "tcp"), [("socket://127.0.0.1:5021", ("127.0.0.1", 5021)),
                                           ("tcp://127.0.0.1:5021", ("127.0.0.1", 5021)),
                                           ("pty", None)])
def test_daq_forms(text, tcp):
    endpoint = parse_daq(text)
    assert endpoint.tcp == tcp and endpoint.link is None


def test_a_path_links_a_pseudo_terminal_there_as_rig_takes_a_device_path(tmp_path):
    assert parse_daq(str(tmp_path / "daq")).link == tmp_path / "daq"
    assert parse_modbus(f"rtu://{tmp_path}/controller").link == tmp_path / "controller"


@pytest.mark.parametrize(("option", "text", "said"), [
    ("--modbus", "tcp://127.0.0.1", "expected tcp://HOST:PORT"),
    ("--modbus", "tcp://127.0.0.1:70000", "a port 0…65535"),
    ("--modbus", "socket://127.0.0.1:5020", "expected tcp://HOST:PORT"),
    ("--modbus", "rtu:relative/path", "expected tcp://HOST:PORT"),
    ("--daq", "socket://127.0.0.1", "expected socket://HOST:PORT"),
    ("--daq", "rfc2217://127.0.0.1:5021", "expected socket://HOST:PORT"),
    ("--daq", "/no/such/folder/daq", "no folder /no/such/folder"),
])
def test_a_malformed_address_is_one_line_and_exit_2(capsys, option, text, said):
    assert main(["serve", option, text]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and said in err and text in err, err


def test_an_existing_path_is_never_replaced(tmp_path, capsys):
    taken = tmp_path / "daq"
    taken.write_text("someone's file")
    assert main(["serve", "--daq", str(taken)]) == 2
    assert "the path exists" in capsys.readouterr().err
    assert taken.read_text() == "someone's file"


@pytest.mark.parametrize("forms", ["tcp", "paths"])
def test_rig_takes_what_the_simulator_prints(tmp_path, forms):
    """The printed 'rig options' line, pasted into rig status and rig monitor, reaches
    the controller and the DAQ; linked paths are gone once the simulator stops."""
    modbus, daq = (("tcp://127.0.0.1:0", "socket://127.0.0.1:0") if forms == "tcp"
                   else (f"rtu://{tmp_path}/controller", str(tmp_path / "daq")))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    sim = subprocess.Popen([sys.executable, "-m", "simulator", "serve", "--modbus", modbus, "--daq", daq,
                            "--speed", "5"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert sim.stdout is not None
        lines = [sim.stdout.readline().strip() for _ in range(3)]
        options = shlex.split(lines[2].removeprefix("rig options: "))
        assert lines[0] == f"modbus {options[1]}" and lines[1] == f"daq {options[3]}", lines
        if forms == "paths":
            assert options == ["--shaker", f"rtu://{tmp_path}/controller", "--daq", str(tmp_path / "daq")]
            assert (tmp_path / "daq").is_symlink()
        else:
            assert options[1].startswith("tcp://127.0.0.1:") and options[3].startswith("socket://127.0.0.1:")
        rig = [sys.executable, "-m", "rig"]
        status = subprocess.run([*rig, "status", *options[:2]], capture_output=True, text=True, env=env, timeout=60)
        assert status.returncode == 0 and "state OFF" in status.stdout, status.stdout + status.stderr
        monitor = subprocess.run([*rig, "monitor", *options[2:], "--duration", "0.5"], capture_output=True,
                                 text=True, env=env, timeout=60)
        assert monitor.returncode == 0 and "DAQ4," in monitor.stderr, monitor.stdout + monitor.stderr
    finally:
        sim.send_signal(signal.SIGTERM)
        sim.communicate(timeout=30)
    assert sim.returncode == 0
    assert not (tmp_path / "daq").exists() and not (tmp_path / "controller").exists()
