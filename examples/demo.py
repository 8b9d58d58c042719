"""The whole product in one run (``make demo``): start the virtual rig accelerated with
a known truth, run the standard plan against it over Modbus and serial, identify,
print the parameters ± std beside the simulator's truth, stop the simulator.

Only the public command lines are used, exactly as an operator would type them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path


def start_simulator(speed: float, seed: int, truth: str | None) -> tuple[subprocess.Popen, str, str]:
    cmd = [sys.executable, "-m", "simulator", "serve", "--modbus", "127.0.0.1:0", "--daq", "tcp://127.0.0.1:0",
           "--speed", str(speed), "--seed", str(seed)] + (["--params", truth] if truth else [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
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
        shutil.rmtree(out)
    proc, modbus, daq = start_simulator(args.speed, args.seed, args.truth)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
