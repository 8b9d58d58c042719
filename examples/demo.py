"""The whole product in one run (``make demo``): start the virtual rig accelerated with
a known truth, run the standard plan against it over Modbus and serial, identify,
print the parameters ± std beside the simulator's truth, stop the simulator.

Only the public command lines are used, exactly as an operator would type them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from rig.virtual import VirtualRig


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
    try:
        sim = VirtualRig(speed=args.speed, seed=args.seed, params=args.truth)
    except RuntimeError as exc:
        raise SystemExit(str(exc)) from None
    print(f"simulator at {args.speed:g}x: Modbus {sim.modbus_url}, DAQ {sim.daq_url}", flush=True)
    try:
        cmd = [sys.executable, "-m", "rig", "run", "--plan", "standard", "--shaker", sim.modbus_url,
               "--daq", sim.daq_url,
               "--out", str(out), "--identify", "--params", args.start, "--unit", "SIM-0001"]
        if args.experiments:
            cmd += ["--experiments", args.experiments]
        code = subprocess.call(cmd, stdout=subprocess.DEVNULL)
    finally:
        sim.stop()
    if code != 0:
        print(f"rig run failed (exit {code}); see {out}/session.log")
        return code

    from identify.model import DEFAULT_ESTIMATE
    from simulator.truth import load_truth

    truth = load_truth(args.truth, "2dof").theta
    result = json.loads((out / "RESULT.json").read_text())
    print(f"\nidentified from {len(result['experiments'])} experiments captured over Modbus + serial "
          f"({out}):\n")
    print(f"  {'parameter':<22} {'identified':>14} {'± std':>11} {'truth':>12} {'rel. error':>11}")
    residual = False
    for name, p in result["parameters"].items():
        if not p.get("estimated"):
            continue
        # The σ to quote: the residual-based one where the residuals exceed the noise.
        std, mark = (p["std_residual"], "*") if p.get("std_residual") is not None else (p["std"], " ")
        residual |= mark == "*"
        err = (p["value"] - truth[name]) / abs(truth[name])
        print(f"  {name + ' ' + p.get('alias', ''):<22} {p['value']:>14.6g} {std:>10.2g}{mark} {truth[name]:>12.6g} "
              f"{err:>11.1e}")
    if residual:
        print("  * residual-based std: the residuals exceed the measurement noise (the report says by how much)")
    print(f"\nreport: {out}/report.txt   same numbers from the files: python -m identify fit {out} "
          f"--model 2dof --estimate {','.join(DEFAULT_ESTIMATE['2dof'])} --params {args.start} --output RESULT.json")
    took_s = sim.rig_time_s()
    announced_s = json.loads((out / "session.json").read_text())["estimated_rig_time_s"]
    print(f"rig time on the simulator's clock (hydraulics on to off): announced {announced_s / 60:.1f} min, took "
          f"{took_s / 60:.1f} min: the announcement {abs(100 * (announced_s / took_s - 1)):.0f} % "
          f"{'short' if announced_s < took_s else 'long'} (the console's 'about' figure is its wall clock times the "
          f"measured pace)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
