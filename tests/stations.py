"""Helpers for tests and benchmarks of QC stations: a station folder with its
``station.toml``, a station's loop of ``qc run`` on its own served simulator, a child's
lines waited for as events (with a hang guard), and the controller read over Modbus."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from pymodbus.client import ModbusTcpClient

from tests.conftest import HANG_S

# The datasheet's addresses (docs/rig-interfaces.md §1), read here independently of rig's driver.
STATE_NAMES = ("OFF", "IDLE", "MOVING", "AT_STATIC", "RUNNING", "ALARM")
ALARM_NAMES = ("none", "stroke limit", "force limit", "low hydraulic pressure", "watchdog", "emergency stop")


def make_station(folder: Path, name: str, db: str, password: str | None = None, *extra: str) -> Path:
    """A station folder whose station.toml names the station and its database (and the
    password, with the file the owner's alone); ``extra``: more lines of it."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "station.toml"
    lines = [f'station = "{name}"', f'db = "{db}"'] + ([f'password = "{password}"'] if password else []) + list(extra)
    path.touch(mode=0o600)
    path.chmod(0o600)
    path.write_text("\n".join(lines) + "\n")
    return folder


def commission(folder: Path, shaker: str, daq: str, spec: str, *args: str) -> subprocess.CompletedProcess:
    """``rig qc station check`` of a station folder with these addresses and spec (what its runs use)."""
    return subprocess.run([sys.executable, "-m", "rig", "qc", "station", "check", "--out", str(folder), "--shaker",
                           shaker, "--daq", daq, "--spec", spec, *args], capture_output=True, text=True,
                          timeout=HANG_S)


class Lines:
    """A child's stderr, line by line on a thread, waited for with a hang guard."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc = proc
        self.seen: list[str] = []
        self._q: queue.Queue[str | None] = queue.Queue()
        assert proc.stderr is not None
        threading.Thread(target=self._read, args=(proc.stderr,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            self._q.put(line)
        self._q.put(None)

    def wait_for(self, marker: str, hang_s: float = HANG_S) -> str:
        deadline = time.monotonic() + hang_s
        while True:
            try:
                line = self._q.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no line with {marker!r} within {hang_s:g} s (hang guard)") from None
            if line is None:
                raise AssertionError(f"the run ended (exit {self.proc.wait()}) before {marker!r}:\n"
                                     + "".join(self.seen[-30:]))
            self.seen.append(line)
            if marker in line:
                return line

    def stdout(self) -> str:
        """The child's whole stdout, once it has ended (stderr stays this reader's)."""
        assert self.proc.stdout is not None
        out = self.proc.stdout.read()
        self.proc.wait(timeout=HANG_S)
        return out

    def rest(self) -> str:
        while (line := self._q.get(timeout=HANG_S)) is not None:
            self.seen.append(line)
        return "".join(self.seen)


@dataclass(frozen=True)
class Controller:
    state: str
    alarm: str
    hydraulics_on: bool
    supply_bar: float
    position_mm: float
    watchdog_s: float          # the stated timeout (holding register 9, 0.1 s)


def read_controller(host: str, port: int) -> Controller:
    client = ModbusTcpClient(host, port=port, timeout=5)
    if not client.connect():
        raise AssertionError(f"the simulator's Modbus server at {host}:{port} does not answer")
    try:
        inputs = client.read_input_registers(0, count=6, device_id=1).registers
        coils = client.read_coils(0, count=1, device_id=1).bits
        (watchdog,) = client.read_holding_registers(9, count=1, device_id=1).registers
    finally:
        client.close()
    position = inputs[2] - 0x10000 if inputs[2] >= 0x8000 else inputs[2]
    return Controller(STATE_NAMES[inputs[0]], ALARM_NAMES[inputs[1]], bool(coils[0]), inputs[5] / 10.0,
                      position / 100.0, watchdog * 0.1)


def wait_controller(host: str, port: int, until, poll_s: float = 0.02, hang_s: float = HANG_S) -> Controller:
    """Poll the controller until ``until(status)`` holds (a hang guard, not a budget)."""
    deadline = time.monotonic() + hang_s
    while True:
        c = read_controller(host, port)
        if until(c):
            return c
        if time.monotonic() > deadline:
            raise AssertionError(f"the controller did not get there within {hang_s:g} s: {c}")
        time.sleep(poll_s)


@dataclass
class StationLoop:
    """One station: its folder and simulator, testing ``units`` serials one after another."""
    folder: Path
    prefix: str                      # serials PREFIX-0001, PREFIX-0002, …
    shaker: str
    daq: str
    units: int
    spec: str
    extra: tuple[str, ...] = ()
    progress: bool = False           # a line per unit on stderr (benchmarks)
    exits: list[int] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def serial(self, i: int) -> str:
        return f"{self.prefix}-{i + 1:04d}"

    def run(self) -> None:
        for i in range(self.units):
            t0 = time.monotonic()
            r = subprocess.run([sys.executable, "-m", "rig", "qc", "run", "--serial", self.serial(i), "--shaker",
                                self.shaker, "--daq", self.daq, "--out", str(self.folder), "--spec", self.spec,
                                "--reset-alarm", *self.extra], capture_output=True, text=True, timeout=HANG_S,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
            self.wall_s.append(time.monotonic() - t0)
            self.exits.append(r.returncode)
            if r.returncode not in (0, 1, 4):
                self.errors.append(f"{self.serial(i)}: exit {r.returncode}: {r.stderr[-1500:]}")
            if self.progress:
                print(f"  {self.serial(i)}: exit {r.returncode}, {self.wall_s[-1]:.0f} s wall", file=sys.stderr,
                      flush=True)


def run_stations(loops: list[StationLoop]) -> None:
    threads = [threading.Thread(target=loop.run, name=loop.prefix) for loop in loops]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
