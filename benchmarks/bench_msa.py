"""The measurement-system acceptance of the QC station on the served simulator (#43): a
type 1 study of the nominal unit as master (``--runs``, 25 by default) and a type 3 study
of 10 good units × 2 repeats in a randomised order, in the model world or on the plant
(``--physics``), at ``--speed`` (10 by default).  Each run is a ``qc run`` session on
``python -m simulator serve``; for the type 3 study the simulator is served again with
the next unit (``--unit good --unit-seed N`` for unit SN-000N) on the same ports.

    nice -n 10 python benchmarks/bench_msa.py --physics plant --runs 25 --units 10

Prints Cg, Cgk per characteristic, then %GRR of the tolerance and ndc, as the study
commands do, and where their reports and records went.  Slow: about 15 s of wall clock
per run at 10x (45 runs: 12 min), so run it niced.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rig.config import CONFIG_DIR  # noqa: E402
from rig.errors import RigFault  # noqa: E402
from rig.qc.msa_run import run_check, run_type1, run_type3  # noqa: E402
from rig.qc.run import QcOptions  # noqa: E402

CALIBRATION = CONFIG_DIR / "station-calibration-simulated.toml"
REFERENCE = CONFIG_DIR / "master-simulated.toml"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Served:
    """``python -m simulator serve`` on fixed ports, served again with another unit."""

    def __init__(self, physics: str, speed: float) -> None:
        self.physics, self.speed = physics, speed
        self.modbus, self.daq = free_port(), free_port()
        self.proc: subprocess.Popen[str] | None = None

    def serve(self, unit: list[str]) -> None:
        self.stop()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "simulator", "serve", "--physics", self.physics, "--speed", str(self.speed),
             "--modbus", f"tcp://127.0.0.1:{self.modbus}", "--daq", f"socket://127.0.0.1:{self.daq}", *unit],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env={**os.environ})
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("rig options:"):
                return
        raise SystemExit(f"the simulator did not start (exit {self.proc.wait()})")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--physics", choices=("model", "plant"), default="plant")
    ap.add_argument("--speed", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=25, help="type 1 runs (0: no type 1 study)")
    ap.add_argument("--units", type=int, default=10, help="type 3 units (0: no type 3 study)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", help="station folder (default: a temporary one, kept)")
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix=f"bench-msa-{args.physics}-"))
    sim = Served(args.physics, args.speed)

    def options(serial: str) -> QcOptions:
        return QcOptions(spec="default", serial=serial, shaker=f"tcp://127.0.0.1:{sim.modbus}",
                         daq=f"socket://127.0.0.1:{sim.daq}", out=out, operator="bench", rig_id="bench-msa",
                         calibration=str(CALIBRATION))

    def say(text: str) -> None:
        print(text, flush=True)

    print(f"station {out}; {args.physics} world at {args.speed:g}x", flush=True)
    try:
        sim.serve([])                                   # the nominal unit: the master
        code = run_check(options("MU-0001"), "MU-0001", str(REFERENCE), say)
        if args.runs:
            code |= run_type1(options("MU-0001"), "MU-0001", str(REFERENCE), args.runs, say)
        if args.units:
            units = [f"SN-{i:04d}" for i in range(1, args.units + 1)]
            code |= run_type3(options(units[0]), units, args.repeats, say,
                              lambda serial: sim.serve(["--unit", "good", "--unit-seed", str(int(serial[3:]))]),
                              seed=43)
    except RigFault as exc:      # a run without values: the study is not made (said, not a traceback)
        print(f"stopped: {exc}", flush=True)
        return 3
    finally:
        sim.stop()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
