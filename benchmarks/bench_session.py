"""Rig time of the standard session: the change criterion with direct moves (before the
rig-time work) against the shipped default, the drift criterion with model-planned
conditioning holds (rig/settling.py) in the order of least predicted rig time
(rig/ordering.py), the same as listed (``--order fixed``), and the shipped default with
lost samples on the line.

Runs on the in-process virtual rig on simulated time (tests/virtual_rig_inprocess.py:
the rig package's drivers against the simulator, nominal truth, its fixed seed), which
gives the same rig time as ``simulator serve`` at any speed and takes a few minutes of
wall time, where a served simulator at 50x takes 50 s per thousand rig seconds and more
on a busy machine.  Each case runs in its own process, so that its peak RSS is its own.

    python benchmarks/bench_session.py                 # the four cases, side by side
    python benchmarks/bench_session.py --hold 60       # and a held 0.04 Hz experiment (memory)
"""

from __future__ import annotations

import argparse
import io
import json
import re
import resource
import subprocess
import sys
import tempfile
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CASES = {   # criterion, order, faults, conditioning holds
    "today": ("change", "fixed", [], False),           # the criterion, lead-in and order before rig-time work
    "new": ("drift", "thermal", [], True),             # the shipped default
    "new+listed": ("drift", "fixed", [], True),        # the same as listed (--order fixed)
    "new+faults": ("drift", "thermal", ["corrupt=0.001", "drop=0.0005"], True),
    "change+holds": ("change", "fixed", [], True),
    "drift": ("drift", "fixed", [], False),
    "drift+thermal": ("drift", "thermal", [], False),
    # the drift bound of a fast decay falls without end: the change criterion holds
    "hold": ("change", "fixed", [], False),
}
SIDE_BY_SIDE = ("today", "new", "new+listed", "new+faults")
ESTIMATE = ["theta4", "theta6", "theta16"]
START = ROOT / "examples" / "start-2dof.json"


def run_case(name: str, hold_cycles: int, out: Path) -> dict:
    """One session in this process; returns its figures (JSON-able)."""
    from rich.console import Console

    from rig.config import DEFAULT_RIG_CONFIG
    from rig.run import Links, RunOptions, SessionRunner, fit_session, prepare
    from tests.virtual_rig_inprocess import DAQ_URL, SHAKER_URL, InProcessRig

    criterion, order, faults, holds = CASES[name]
    text = re.sub(r'(?m)^criterion = "\w+"', f'criterion = "{criterion}"', DEFAULT_RIG_CONFIG.read_text())
    if not holds:
        text = re.sub(r'(?m)^max_hold_s = .*$', "max_hold_s = 0.0", text)
    if name == "today":   # and the fade-in and -out it had
        text = re.sub(r'(?m)^ramp_time_s = .*$', "ramp_time_s = 2.0", text)
    if hold_cycles:   # thresholds that are never met: the experiment is held to max_cycles
        text = text.replace("max_cycles = 1500", f"max_cycles = {hold_cycles}").replace(
            "stroke_mm = 0.02", "stroke_mm = 0.0")
    config = out / "rig.toml"
    config.write_text(text)
    rig = InProcessRig(config)
    rig.connect()
    try:
        for fault in faults:
            rig.when("settling", 0.0, partial(rig.inject, fault))
        letters = ["a"] if hold_cycles else None
        prep = prepare(RunOptions(plan="standard", shaker=SHAKER_URL, daq=DAQ_URL, out=out / "session",
                                  experiments=letters, rig_config=str(config), date="261122", order=order))
        runner = SessionRunner(prep, Links(rig.shaker, rig.daq, rig.identity, None), rig.bus,
                               Console(file=io.StringIO()))
        session = runner.open_session()
        eta = sum(runner.estimates_s(session, rig.shaker.status().position_m).values())
        t0 = rig.clock.monotonic()
        result = runner.run(session)
        taken = rig.clock.monotonic() - t0
        phases = rig.phases()
        per = {}
        for e in prep.plan.experiments:
            label = session.label(e.letter)
            times = [t for t, x, _ in phases if x == label]
            cycles = next((ev.data.get("cycles") for _, ev in rig.events
                           if ev.kind == "phase" and ev.experiment == label and ev.data.get("phase") == "capturing"), 0)
            per[e.letter] = (max(times) - min(times) if times else 0.0, cycles)
        fit = {}
        if not hold_cycles and result.status == "complete":
            fitted = fit_session(session, "2dof", START, ESTIMATE, result.captured)
            fit = {k: (fitted.params[k].value, fitted.std[k]) for k in ESTIMATE}
    finally:
        rig.close()
    return {"case": name, "status": result.status, "order": [e.letter for e in prep.plan.experiments],
            "per": per, "taken_s": taken, "eta_s": eta, "fit": fit,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--hold", type=int, default=0, help="also hold experiment a (0.04 Hz) for this many cycles")
    ap.add_argument("--cases", default=",".join(SIDE_BY_SIDE),
                    help=f"comma-separated, of {', '.join(c for c in CASES if c != 'hold')} (today's first)")
    args = ap.parse_args()
    if args.case:
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(run_case(args.case, args.hold if args.case == "hold" else 0, Path(tmp))))
        return
    shown = args.cases.split(",")
    names = shown + (["hold"] if args.hold else [])
    results = {}
    for name in names:
        proc = subprocess.run([sys.executable, __file__, "--case", name, "--hold", str(args.hold)],
                              capture_output=True, text=True, cwd=ROOT)
        if proc.returncode:
            sys.exit(f"{name}: {proc.stderr[-2000:]}")
        results[name] = json.loads(proc.stdout.strip().splitlines()[-1])
    from identify.plans import STANDARD_SET

    print("rig time per experiment [s] (settle cycles); simulated time, in-process rig")
    print(f"{'':4}" + "".join(f"{n:>22}" for n in shown))
    for e in STANDARD_SET:
        print(f"{e.letter:4}" + "".join(f"{results[n]['per'][e.letter][0]:>14.1f} ({results[n]['per'][e.letter][1]:>4})"
                                        for n in shown))
    print(f"{'total':6}" + "".join(f"{results[n]['taken_s']:>22.1f}" for n in shown))
    print(f"{'ETA':6}" + "".join(f"{results[n]['eta_s']:>22.1f}" for n in shown))
    print(f"{'ETA/taken':10}" + "".join(f"{results[n]['eta_s'] / results[n]['taken_s'] - 1:>+18.1%}" for n in shown))
    print(f"{'order':6}" + "".join(f"{''.join(results[n]['order']):>22}" for n in shown))
    print(f"{'RSS MB':6}" + "".join(f"{results[n]['peak_rss_mb']:>22.0f}" for n in shown))
    from simulator.truth import load_truth

    truth = load_truth().theta
    print("\nidentified (start: examples/start-2dof.json); Δ in σ of the first case's fit; truth Δ in each fit's σ")
    for k in ESTIMATE:
        t = truth.get(k)
        row = [f"{k:8}"]
        v0, s0 = results[shown[0]]["fit"][k]
        for n in shown:
            v, s = results[n]["fit"][k]
            row.append(f"{v:.6g} ± {s:.2g} (vs first {(v - v0) / s0:+.2f}σ"
                       + (f", vs truth {(v - t) / s:+.2f}σ)" if t is not None else ")"))
        print("  ".join(row))
    if args.hold:
        h = results["hold"]
        print(f"\nheld: a (0.04 Hz) for {args.hold} cycles, {h['taken_s']:.0f} s of rig time: peak RSS "
              f"{h['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
