"""The whole product in one run (``make demo``): start the virtual rig accelerated with
a known truth, run the standard plan against it over Modbus and serial, identify,
print the parameters ± std beside the simulator's truth, stop the simulator.

Only the public command lines are used, exactly as an operator would type them.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import IO


def start_simulator(speed: float, seed: int, truth: str | None, log: IO[str]) -> tuple[subprocess.Popen, str, str]:
    cmd = [sys.executable, "-m", "simulator", "serve", "--modbus", "127.0.0.1:0", "--daq", "tcp://127.0.0.1:0",
           "--speed", str(speed), "--seed", str(seed)] + (["--params", truth] if truth else [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)
    assert proc.stdout is not None  # a pipe: stdout=PIPE
    endpoints: dict[str, str] = {}
    while len(endpoints) < 2:
        line = proc.stdout.readline()
        if not line:
            raise SystemExit(f"the simulator did not start (exit {proc.wait()})")
        kind, url = line.split(maxsplit=1)
        endpoints[kind] = url.strip()
    return proc, endpoints["modbus"], endpoints["daq"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="out/demo-session")
    parser.add_argument("--speed", type=float, default=50.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--truth", help="simulator truth (START.json format; default: nominal)")
    parser.add_argument("--start", default="examples/start-2dof.json", help="start values for the fit")
    parser.add_argument("--experiments", help="letters (default: the whole standard plan)")
    args = parser.parse_args()

    out = Path(args.out)
    if out.exists():
        # Only an earlier demo's session is replaced: a folder of anything else is the user's.
        if not (out / "session.json").is_file():
            raise SystemExit(f"--out {out}: exists and is not a session folder; choose another --out")
        shutil.rmtree(out)
    sim_log = tempfile.TemporaryFile("w+")
    proc, modbus, daq = start_simulator(args.speed, args.seed, args.truth, sim_log)
    print(f"simulator at {args.speed:g}x: Modbus {modbus}, DAQ {daq}", flush=True)
    try:
        cmd = [sys.executable, "-m", "rig", "run", "--plan", "standard", "--shaker", modbus, "--daq", daq,
               "--out", str(out), "--identify", "--params", args.start, "--unit", "SIM-0001"]
        if args.experiments:
            cmd += ["--experiments", args.experiments]
        code = subprocess.call(cmd, stdout=subprocess.DEVNULL)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    if code != 0:
        print(f"rig run failed (exit {code}); see {out}/session.log")
        return code

    from simulator.truth import load_truth

    truth = load_truth(args.truth, "2dof").theta
    result = json.loads((out / "RESULT.json").read_text())
    print(f"\nidentified from {len(result['experiments'])} experiments captured over Modbus + serial "
          f"({out}):\n")
    print(f"  {'parameter':<22} {'identified':>14} {'± std':>10} {'truth':>12} {'rel. error':>11}")
    for name, p in result["parameters"].items():
        if not p.get("estimated"):
            continue
        err = (p["value"] - truth[name]) / abs(truth[name])
        print(f"  {name + ' ' + p.get('alias', ''):<22} {p['value']:>14.6g} {p['std']:>10.2g} {truth[name]:>12.6g} "
              f"{err:>11.1e}")
    print(f"\nreport: {out}/report.txt   same numbers from the files: python -m identify fit {out} "
          f"--params {args.start} --estimate theta4,theta6,theta16 --output RESULT.json")
    sim_log.seek(0)
    took_s = rig_time_s(sim_log.read())
    announced_s = json.loads((out / "session.json").read_text())["estimated_rig_time_s"]
    print(f"rig time: announced {announced_s / 60:.1f} min, took {took_s / 60:.1f} min on the simulator's clock "
          f"(hydraulics on to off), {100 * (announced_s / took_s - 1):+.0f} %")
    return 0


def rig_time_s(simulator_log: str) -> float:
    """Simulated seconds from the first 'hydraulics on' to the last 'hydraulics off'."""
    marks = re.findall(r"\[sim t=\s*([0-9.]+) s\] hydraulics (on|off)", simulator_log)
    if not marks or marks[0][1] != "on" or marks[-1][1] != "off":
        raise SystemExit("the simulator's log holds no hydraulics on ... off: no rig time to report")
    return float(marks[-1][0]) - float(marks[0][0])


if __name__ == "__main__":
    sys.exit(main())
