"""The virtual rig as a child process: ``python -m simulator serve`` on free loopback
ports, exactly as an operator would start it by hand, with its endpoints, its log and
its clean stop.  The rig package never imports the simulator; it talks to it over
Modbus and the DAQ line only, and learns its endpoints and state from the JSON file
``serve --state`` keeps (the log is for people: it is shown, never parsed).  Used by
the pytest plugin (``rig.testing``), the demo (``examples/demo.py``) and
``rig gui --simulate``."""

from __future__ import annotations

import atexit
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rig.errors import BadInput, RigFault

START_TIMEOUT_S = 60.0


class VirtualRig:
    """A running ``simulator serve``: its endpoints, its log, and how to stop it."""

    def __init__(self, *, speed: float = 50.0, params: str | Path | dict[str, float] | None = None, seed: int = 1,
                 faults: Sequence[str] = (), daq: str = "tcp", rig: str = "shaker", modbus: str = "tcp",
                 unit: str | None = None, unit_seed: int | None = None, extra_args: Sequence[str] = (),
                 nice: int = 0) -> None:
        """``nice``: the simulator's lower scheduling priority, for a console that must stay
        responsive on the machine that also plays the rig's hardware."""
        self._tmp = tempfile.TemporaryDirectory(prefix="virtual-rig-")
        if isinstance(params, dict):
            truth = Path(self._tmp.name) / "truth.json"
            truth.write_text(json.dumps({"parameters": params}))
            params = truth
        cmd = [sys.executable, "-m", "simulator", "serve",
               "--modbus", "tcp://127.0.0.1:0" if modbus == "tcp" else "rtu:pty",
               "--daq", "socket://127.0.0.1:0" if daq == "tcp" else "pty",
               "--speed", str(speed), "--seed", str(seed), "--rig", rig]
        cmd += ["--params", str(params)] if params is not None else []
        cmd += ["--unit", unit] if unit is not None else []             # a production unit (QC)
        cmd += ["--unit-seed", str(unit_seed)] if unit_seed is not None else []
        for fault in faults:
            cmd += ["--fault", fault]
        self._state_path = Path(self._tmp.name) / "state.json"
        cmd += ["--state", str(self._state_path)]
        cmd += list(extra_args)
        self.command = cmd
        self._state: dict[str, Any] = {}   # the state file as last read (kept once the folder is gone)
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      preexec_fn=(lambda: os.nice(nice)) if nice else None)
        # Stopped with this program even when nobody called stop() (a failing test, an
        # exception in a window): an orphaned simulator would hold its ports and a core.
        atexit.register(self.stop)
        self._lines: list[str] = []
        self._lock = threading.Lock()
        # The log is drained continuously: a simulator blocked on a full pipe would stall the rig.
        self._drain = threading.Thread(target=self._read_log, name="virtual-rig-log", daemon=True)
        self._drain.start()
        self.modbus_url, self.daq_url = self._endpoints()
        self.returncode: int | None = None

    def _endpoints(self) -> tuple[str, str]:
        ready = threading.Event()

        def read() -> None:
            # The first line on stdout (or its end, when the simulator gave up) says the
            # state file is written: the simulator writes it before it prints its addresses.
            assert self._proc.stdout is not None
            self._proc.stdout.readline()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        found = self.state() if ready.wait(START_TIMEOUT_S) else {}
        if found.get("state") != "serving":
            self.stop()
            said = [line.strip().removeprefix("error: ") for line in self.log().splitlines() if line.strip()]
            why = f"the virtual rig did not start (simulator exit {self.returncode}): {(said or ['no output'])[-1]}"
            # The simulator's exit 2 is input it refused (a truth file, a fault): the caller's mistake.
            raise BadInput(why) if self.returncode == 2 else RigFault(why)
        return str(found["modbus"]), str(found["daq"])

    def state(self) -> dict[str, Any]:
        """The simulator's state file (``simulator serve --state``): ``state`` (serving,
        stopped), ``modbus``, ``daq``, ``hydraulics`` ([simulated s, on] pairs), and once
        stopped ``t_s``, ``lost_frames``, ``lost``.  Empty before the simulator wrote it."""
        try:
            self._state = json.loads(self._state_path.read_text())
        except FileNotFoundError:
            pass   # not written yet, or stopped and cleaned up: what was read last stands
        return self._state

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
        self.state()   # its last word, before the folder goes
        self._tmp.cleanup()
        return self.log()

    def rig_time_s(self) -> float:
        """Simulated seconds from the first hydraulics on to the last hydraulics off."""
        marks = self.state().get("hydraulics", [])
        if not marks or not marks[0][1] or marks[-1][1]:
            raise ValueError("the simulator's state holds no hydraulics on ... off")
        return float(marks[-1][0]) - float(marks[0][0])

    def lost_frames(self) -> int:
        """The simulator's own count of DAQ frames lost to injected faults (once stopped)."""
        lost = self.state().get("lost_frames")
        if lost is None:
            raise ValueError("no loss count in the simulator's state: stop() the rig first")
        return int(lost)

    def __enter__(self) -> VirtualRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
