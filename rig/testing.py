"""The pytest plugin for simulator-backed tests: the ``virtual_rig`` fixture.

Installing the project registers it (entry point ``pytest11``), so any test suite
gets the fixture with no conftest copying::

    def test_j_settles(virtual_rig, tmp_path):
        sim = virtual_rig(faults=["drop=0.001"])
        with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
            session = r.run_plan("standard", experiments=["j"], out=tmp_path / "s")

Each call starts ``python -m simulator serve`` on free loopback ports, exactly as an
operator would, and returns a :class:`VirtualRig` handle.  Every rig a test started
is stopped at teardown, pass or fail; a failing test gets the simulator's log in its
report.  ``--virtual-rig-speed`` overrides the speed of every rig in a run (e.g. 1 to
watch a test at the rig's own pace); ``@pytest.mark.virtual_rig(speed=…, seed=…)``
sets a test's defaults.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Generator, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

START_TIMEOUT_S = 60.0


class VirtualRig:
    """A running ``simulator serve``: its endpoints, its log, and how to stop it."""

    def __init__(self, *, speed: float = 50.0, params: str | Path | dict[str, float] | None = None, seed: int = 1,
                 faults: Sequence[str] = (), daq: str = "tcp", rig: str = "shaker", modbus: str = "tcp",
                 unit: str | None = None, unit_seed: int | None = None, extra_args: Sequence[str] = ()) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="virtual-rig-")
        if isinstance(params, dict):
            truth = Path(self._tmp.name) / "truth.json"
            truth.write_text(json.dumps({"parameters": params}))
            params = truth
        cmd = [sys.executable, "-m", "simulator", "serve",
               "--modbus", "127.0.0.1:0" if modbus == "tcp" else "rtu:pty",
               "--daq", "tcp://127.0.0.1:0" if daq == "tcp" else "pty",
               "--speed", str(speed), "--seed", str(seed), "--rig", rig]
        cmd += ["--params", str(params)] if params is not None else []
        cmd += ["--unit", unit] if unit is not None else []             # a production unit (QC)
        cmd += ["--unit-seed", str(unit_seed)] if unit_seed is not None else []
        for fault in faults:
            cmd += ["--fault", fault]
        cmd += list(extra_args)
        self.command = cmd
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._lines: list[str] = []
        self._lock = threading.Lock()
        # The log is drained continuously: a simulator blocked on a full pipe would stall the rig.
        self._drain = threading.Thread(target=self._read_log, name="virtual-rig-log", daemon=True)
        self._drain.start()
        self.modbus_url, self.daq_url = self._endpoints()
        self.returncode: int | None = None

    def _endpoints(self) -> tuple[str, str]:
        found: dict[str, str] = {}
        ready = threading.Event()

        def read() -> None:
            assert self._proc.stdout is not None
            for line in self._proc.stdout:
                kind, _, url = line.strip().partition(" ")
                found[kind] = url
                if {"modbus", "daq"} <= found.keys():
                    break
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(START_TIMEOUT_S) or not {"modbus", "daq"} <= found.keys():
            self.stop()
            raise RuntimeError(f"the virtual rig did not start ({' '.join(self.command)}):\n{self.log()}")
        return found["modbus"], found["daq"]

    def _read_log(self) -> None:
        assert self._proc.stderr is not None
        for line in self._proc.stderr:
            with self._lock:
                self._lines.append(line)

    @property
    def host(self) -> str:
        return self.modbus_url.removeprefix("tcp://").rsplit(":", 1)[0]

    @property
    def port(self) -> int:
        return int(self.modbus_url.rsplit(":", 1)[1])

    def log(self) -> str:
        """What the simulator logged so far (faults, trips, commands, each at its simulated time)."""
        with self._lock:
            return "".join(self._lines)

    @property
    def running(self) -> bool:
        return self._proc.poll() is None

    def stop(self, timeout_s: float = 20.0) -> str:
        """SIGTERM, wait for the clean exit, return the whole log (killed if it hangs)."""
        if self._proc.poll() is None:
            self._proc.send_signal(signal.SIGTERM)
            try:
                self._proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._drain.join(timeout=5)
        self.returncode = self._proc.returncode
        self._tmp.cleanup()
        return self.log()

    def rig_time_s(self) -> float:
        """Simulated seconds from the first 'hydraulics on' to the last 'hydraulics off'."""
        marks = re.findall(r"\[sim t=\s*([0-9.]+) s\] hydraulics (on|off)", self.log())
        if not marks or marks[0][1] != "on" or marks[-1][1] != "off":
            raise ValueError("the simulator's log holds no hydraulics on ... off")
        return float(marks[-1][0]) - float(marks[0][0])

    def lost_frames(self) -> int:
        """The simulator's own count of DAQ frames lost to injected faults (once stopped)."""
        m = re.search(r"DAQ frames lost by faults: (\d+)", self.log())
        if m is None:
            raise ValueError("no loss count in the log: stop() the rig first")
        return int(m.group(1))

    def __enter__(self) -> VirtualRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


_RIGS = pytest.StashKey[list[VirtualRig]]()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.getgroup("virtual-rig").addoption(
        "--virtual-rig-speed", type=float, default=None,
        help="simulated seconds per wall second for every virtual_rig of the run (overrides the tests' own)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "virtual_rig(**defaults): defaults for the virtual_rig fixture of a test "
                                       "(speed, params, seed, faults, daq, rig, modbus)")


@pytest.fixture
def virtual_rig(request: pytest.FixtureRequest) -> Iterator[Callable[..., VirtualRig]]:
    """Factory: ``virtual_rig(speed=50, params=None, seed=1, faults=(), daq="tcp", rig="shaker",
    modbus="tcp", unit=None, unit_seed=None)`` starts a simulated rig and returns its :class:`VirtualRig`."""
    marker = request.node.get_closest_marker("virtual_rig")
    defaults: dict[str, Any] = dict(marker.kwargs) if marker else {}
    speed_override = request.config.getoption("--virtual-rig-speed")
    rigs: list[VirtualRig] = []
    request.node.stash[_RIGS] = rigs

    def start(**kwargs: Any) -> VirtualRig:
        options = {**defaults, **kwargs}
        if speed_override is not None:
            options["speed"] = speed_override
        rig = VirtualRig(**options)
        rigs.append(rig)
        return rig

    try:
        yield start
    finally:
        for rig in rigs:
            rig.stop()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item,
                              call: pytest.CallInfo[None]) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    rigs = item.stash.get(_RIGS, [])
    if report.failed and rigs:
        for i, rig in enumerate(rigs, 1):
            report.sections.append((f"virtual rig {i} log ({rig.modbus_url}, {rig.daq_url})", rig.log()))
    return report
