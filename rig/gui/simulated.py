"""The virtual rig as a child process, for ``rig gui --simulate``: ``python -m simulator
serve`` on free loopback ports, exactly as an operator would start it by hand.  The rig
package never imports the simulator; it talks to it over Modbus and the DAQ line only."""

from __future__ import annotations

import atexit
import signal
import subprocess
import sys
import threading
from collections import deque
from dataclasses import dataclass, field


class SimulatorStartError(RuntimeError):
    """The simulator did not come up (its own words are in the message)."""


@dataclass
class SimulatedRig:
    speed: float = 1.0
    params: str | None = None
    faults: list[str] = field(default_factory=list)
    modbus_url: str = ""
    daq_url: str = ""
    log: deque[str] = field(default_factory=lambda: deque(maxlen=200))   # the simulator's stderr, last lines
    _proc: subprocess.Popen | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        cmd = [sys.executable, "-m", "simulator", "serve", "--modbus", "127.0.0.1:0", "--daq", "tcp://127.0.0.1:0",
               "--speed", f"{self.speed:g}"]
        if self.params:
            cmd += ["--params", self.params]
        for fault in self.faults:
            cmd += ["--fault", fault]
        self._proc = proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # Stopped with this program even when its window never closed (a failing test, an
        # exception): an orphaned simulator would hold its ports and a core.
        atexit.register(self.stop)
        assert proc.stdout is not None and proc.stderr is not None  # both are pipes
        # stderr is read all along: a full pipe would block the simulator.
        threading.Thread(target=self._read_stderr, name="simulator-stderr", daemon=True).start()
        endpoints: dict[str, str] = {}
        timer = threading.Timer(timeout_s, proc.kill)
        timer.start()
        try:
            while len(endpoints) < 2:
                line = proc.stdout.readline()
                if not line:
                    proc.wait()
                    raise SimulatorStartError(f"the simulator did not start (exit {proc.returncode}): "
                                              + " ".join(self.log))
                kind, _, url = line.strip().partition(" ")
                endpoints[kind] = url
        finally:
            timer.cancel()
        self.modbus_url, self.daq_url = endpoints["modbus"], endpoints["daq"]

    def _read_stderr(self) -> None:
        assert self._proc is not None and self._proc.stderr is not None
        for line in self._proc.stderr:
            self.log.append(line.rstrip())

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, timeout_s: float = 20.0) -> None:
        """SIGTERM (the simulator's clean stop), SIGKILL if it does not go."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def describe(self) -> str:
        return f"SIMULATED RIG (python -m simulator serve at {self.speed:g}x, not hardware)"
