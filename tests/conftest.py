"""Shared fixtures: a generated dataset with a known truth, reused by the slow tests."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # before any Qt import: CI has no display

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

# Kept in the repository (see its PROVENANCE.md) so that a bare clone runs every test.
SILVERBOX = Path(__file__).resolve().parent / "data" / "silverbox"


def require_program(name: str) -> str:
    """Path of an outside program a test drives.  Where it is missing the test is
    skipped on a developer's machine but fails under CI (``CI`` set), which installs
    it (.ci/run): a test that CI skips silently checks nothing."""
    path = shutil.which(name)
    if path:
        return path
    if os.environ.get("CI", "").lower() not in ("", "0", "false"):
        pytest.fail(f"{name} is not installed; under CI this test must run (.ci/run installs it)")
    pytest.skip(f"{name} is not installed")


@pytest.fixture(scope="session")
def standard_dataset(tmp_path_factory) -> Path:
    """The standard set (14 experiments, 3 periods, 2 kHz) from the simulator, nominal truth."""
    from identify.plans import STANDARD_SET
    from simulator.generate import generate
    from simulator.truth import load_truth

    out = tmp_path_factory.mktemp("standard")
    generate(out, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=7, drop=True, date="261122")
    return out


class ServedRig:
    """``python -m simulator serve`` in a subprocess, on free ports, as a client sees it."""

    def __init__(self, *args: str, daq: str = "tcp://127.0.0.1:0", speed: float = 50.0) -> None:
        import subprocess
        import sys

        cmd = [sys.executable, "-m", "simulator", "serve", "--modbus", "127.0.0.1:0", "--daq", daq,
               "--speed", str(speed), *args]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stderr is not None  # pipes: PIPE above
        endpoints: dict[str, str] = {}
        while len(endpoints) < 2:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"simulator did not start: {self.proc.stderr.read()}")
            kind, url = line.split(maxsplit=1)
            endpoints[kind] = url.strip()
        self.modbus_url, self.daq_url = endpoints["modbus"], endpoints["daq"]
        if self.modbus_url.startswith("tcp://"):
            host, port = self.modbus_url.removeprefix("tcp://").rsplit(":", 1)
            self.host, self.port = host, int(port)
        self.stderr = ""

    def stop(self) -> str:
        """SIGTERM, wait for a clean exit, return what the simulator logged."""
        import signal

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            _, self.stderr = self.proc.communicate(timeout=20)
            assert self.proc.returncode == 0, self.stderr
        return self.stderr

    def rig_time_s(self) -> float:
        """Simulated seconds from the first 'hydraulics on' to the last 'hydraulics off' (after stop)."""
        import re

        marks = re.findall(r"\[sim t=\s*([0-9.]+) s\] hydraulics (on|off)", self.stderr)
        assert marks and marks[0][1] == "on" and marks[-1][1] == "off", self.stderr[-2000:]
        return float(marks[-1][0]) - float(marks[0][0])

    def lost_frames(self) -> int:
        """The simulator's own count of DAQ frames lost to injected faults (after stop)."""
        import re

        m = re.search(r"DAQ frames lost by faults: (\d+)", self.stderr)
        assert m, self.stderr
        return int(m.group(1))


@pytest.fixture
def served_rig() -> Iterator[Callable[..., ServedRig]]:
    """Factory: ``served_rig(*serve_args, daq=..., speed=...)``; all stopped at teardown."""
    rigs: list[ServedRig] = []

    def start(*args: str, **kwargs: Any) -> ServedRig:
        rig = ServedRig(*args, **kwargs)
        rigs.append(rig)
        return rig

    yield start
    for rig in rigs:
        rig.stop()
