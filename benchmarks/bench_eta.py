"""The announced rig time of a session against the rig time it took, on a served
simulator (the console's case: ``rig gui --simulate``, ``rig qc run`` against
``simulator serve``), with and without cores of the host kept busy.

The rig time taken is the simulator's own (its log: the first "hydraulics on" to the
last "hydraulics off"), so it does not depend on the pace the rig measured.  Printed per
run: the pace the probe measured, the rig time announced before the first experiment,
the rig time taken, the announced against the taken (target: within ±20 %), and what the
session's last line said it took.

    python benchmarks/bench_eta.py                       # QC's default plan at 10x, 0 and 1 busy cores
    python benchmarks/bench_eta.py --busy 0,1,2 --runs 2 --speed 10
    python benchmarks/bench_eta.py --plan standard --experiments e,j --speed 50

One prediction (issue 34): ``--three-figures standard`` or ``--three-figures designed``
prints, side by side, ``rig design``'s prediction (``--target theta4,theta6,theta16
--no-worse-than standard``, its links' pace measured on the served simulator with
``--shaker/--daq``: the standard plan's figure is the reference it prints, the
designed plan's its own), ``rig run``'s announcement of that plan and the rig time the
simulator counted (target: each within ±10 % of the real one).

    python benchmarks/bench_eta.py --three-figures standard     # ~3 min of wall clock at 10x
    python benchmarks/bench_eta.py --three-figures designed
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGET = 0.20
ANNOUNCED = re.compile(r"session: \d+ experiments?, about (\d+):(\d\d) min:s of rig time")
TOOK = re.compile(r"session took .*?(?:about (\d+):(\d\d) min:s of rig time|(\d+):(\d\d) min:s of rig time)")
PACE = re.compile(r"the links run ([0-9.]+) rig seconds per second")
ETA = re.compile(r"About (\d+):(\d\d) left \(m:s of wall clock\)")
STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d+) (session-start|experiment-done|session-end)", re.M)


def corrected_error(said: str, session_log: str) -> float:
    """How far the ETA said after the first experiment (corrected from the progress the
    session made) put the session's end: its elapsed plus that ETA against the whole,
    in wall time (the rig time is the wall time at the session's pace)."""
    import datetime as dt

    stamps = [(dt.datetime.fromisoformat(t).timestamp(), kind) for t, kind in STAMP.findall(session_log)]
    for line in session_log.splitlines():      # session.log as JSON lines
        if line.startswith("{"):
            entry = json.loads(line)
            t = entry.get("time")
            stamps.append((float(t) if isinstance(t, int | float) else dt.datetime.fromisoformat(t).timestamp(),
                           entry.get("kind", "")))
    start = next(t for t, kind in stamps if kind == "session-start")
    first = next(t for t, kind in stamps if kind == "experiment-done")
    end = next(t for t, kind in stamps if kind == "session-end")
    eta = ETA.search(said)
    if eta is None:
        return float("nan")
    return (first - start + int(eta[1]) * 60 + int(eta[2])) / (end - start) - 1


def busy_cores(n: int) -> list[subprocess.Popen]:
    """``n`` processes that each keep one core busy (what another user's job does)."""
    return [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n)]


def run_once(plan: str, experiments: str | None, speed: float, busy: int, seed: int, nice: int,
             unit: str | None = None) -> dict:
    from rig.virtual import VirtualRig

    load = busy_cores(busy)
    try:
        with (tempfile.TemporaryDirectory(prefix="bench-eta-") as tmp,
              VirtualRig(speed=speed, seed=seed, nice=nice, unit=unit, unit_seed=seed if unit else None) as sim):
            links = ["--shaker", sim.modbus_url, "--daq", sim.daq_url]
            if plan == "qc":      # what the console's QC tab runs: qc run, the default spec
                cmd = [sys.executable, "-m", "rig", "qc", "run", "--spec", "default", "--serial", "SN-0001",
                       *links, "--out", tmp]
            else:
                cmd = [sys.executable, "-m", "rig", "run", "--plan", plan, *links, "--out", str(Path(tmp) / "s")]
                cmd += ["--experiments", experiments] if experiments else []
            r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=3600)
            sim.stop()
            said = r.stdout + r.stderr
            if r.returncode not in (0, 1, 4):     # QC: PASS, FAIL, INCONCLUSIVE all ran the plan
                raise SystemExit(f"rig run exit {r.returncode}:\n{said[-3000:]}")
            announced, took = ANNOUNCED.search(said), TOOK.search(said)
            session_log = next(Path(tmp).glob("*/session.log")).read_text()
            probe = PACE.findall(session_log)
            if announced is None or took is None or not probe:
                raise SystemExit(f"no announced or taken rig time, or no pace probe, in:\n{said[-3000:]}")
            said_took = [g for g in took.groups() if g is not None]
            return {"announced_s": int(announced[1]) * 60 + int(announced[2]),
                    "taken_s": sim.rig_time_s(),
                    "said_took_s": int(said_took[0]) * 60 + int(said_took[1]),
                    "pace": float(probe[-1]), "corrected": corrected_error(said, session_log)}
    finally:
        for p in load:
            p.kill()
            p.wait()


DESIGNED = re.compile(r": \d+ experiments?, (\d+) s of rig time predicted \(standard: (\d+) s\)")
THREE_TARGET = 0.10


def three_figures(which: str, speed: float, seed: int, nice: int) -> dict:
    """``rig design``'s prediction, ``rig run``'s announcement and the simulator's count
    of the rig time, for the standard or the designed lab plan, on one served simulator."""
    from rig.virtual import VirtualRig

    with (tempfile.TemporaryDirectory(prefix="bench-eta-") as tmp,
          VirtualRig(speed=speed, seed=seed, nice=nice) as sim):
        links = ["--shaker", sim.modbus_url, "--daq", sim.daq_url]
        lab = Path(tmp) / "lab.toml"
        design = subprocess.run([sys.executable, "-m", "rig", "design", "--target", "theta4,theta6,theta16",
                                 "--no-worse-than", "standard", *links, "--out", str(lab)],
                                capture_output=True, text=True, cwd=ROOT, timeout=3600)
        found = DESIGNED.search(design.stdout)
        if design.returncode != 0 or found is None:
            raise SystemExit(f"rig design exit {design.returncode}:\n{(design.stdout + design.stderr)[-3000:]}")
        predicted = float(found[2] if which == "standard" else found[1])
        plan = "standard" if which == "standard" else str(lab)
        r = subprocess.run([sys.executable, "-m", "rig", "run", "--plan", plan, *links, "--out",
                            str(Path(tmp) / "s")], capture_output=True, text=True, cwd=ROOT, timeout=3600)
        sim.stop()
        said = r.stdout + r.stderr
        announced = ANNOUNCED.search(said)
        if r.returncode != 0 or announced is None:
            raise SystemExit(f"rig run exit {r.returncode}:\n{said[-3000:]}")
        basis = design.stdout.splitlines()[0]
        return {"design_s": predicted, "announced_s": int(announced[1]) * 60 + int(announced[2]),
                "real_s": sim.rig_time_s(), "basis": basis}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plan", default="qc",
                    help="qc (default: rig qc run --spec default, as the console's QC tab), standard or a plan TOML")
    ap.add_argument("--experiments", help="letters of the plan (default: all)")
    ap.add_argument("--speed", type=float, default=10.0, help="the simulator's speed (default 10, the console's)")
    ap.add_argument("--busy", default="0,1", help="busy cores per case, comma-separated (default 0,1)")
    ap.add_argument("--nice", type=int, default=5,
                    help="the simulator's niceness (default 5, as rig gui --simulate starts it)")
    ap.add_argument("--runs", type=int, default=1, help="runs per case")
    ap.add_argument("--unit", help="--plan qc: a production unit of the simulator (good, gas-leak, worn-seal, "
                                   "worn-orifice)")
    ap.add_argument("--three-figures", choices=("standard", "designed"),
                    help="rig design's prediction, rig run's announcement and the real rig time of this plan")
    args = ap.parse_args(argv)
    if args.three_figures:
        f = three_figures(args.three_figures, args.speed, seed=1, nice=args.nice)
        print(f"{args.three_figures} plan on simulator serve at {args.speed:g}x (nice {args.nice}); "
              f"target: each within ±{THREE_TARGET:.0%} of the real rig time")
        print(f"  {f['basis']}")
        print(f"{'rig design':>12} {'rig run':>12} {'real':>8}   {'design/real':>11} {'run/real':>9}")
        print(f"{f['design_s']:>11.0f}s {f['announced_s']:>11.0f}s {f['real_s']:>7.1f}s   "
              f"{f['design_s'] / f['real_s'] - 1:>+11.1%} {f['announced_s'] / f['real_s'] - 1:>+9.1%}")
        return 0
    print(f"plan {args.plan}{' ' + args.experiments if args.experiments else ''}"
          f"{' unit ' + args.unit if args.unit else ''} on "
          f"simulator serve at {args.speed:g}x (nice {args.nice}); target: announced within ±{TARGET:.0%} of taken")
    print(f"{'busy':>4} {'run':>3} {'pace':>6} {'announced':>9} {'taken':>7} {'error':>7} {'rig said':>8} "
          f"{'after 1st':>9}")
    worst = 0.0
    for busy in (int(b) for b in args.busy.split(",")):
        for run in range(args.runs):
            f = run_once(args.plan, args.experiments, args.speed, busy, seed=run + 1, nice=args.nice, unit=args.unit)
            error = f["announced_s"] / f["taken_s"] - 1
            worst = max(worst, abs(error))
            print(f"{busy:>4} {run + 1:>3} {f['pace']:>6.3g} {f['announced_s']:>8.0f}s {f['taken_s']:>6.0f}s "
                  f"{error:>+7.1%} {f['said_took_s']:>7.0f}s {f['corrected']:>+9.1%}", flush=True)
    print(f"worst |announced/taken − 1| = {worst:.1%} (target ≤ {TARGET:.0%})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
