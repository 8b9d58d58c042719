"""Rig time of the standard session: the change criterion with direct moves (before the
rig-time work) against the shipped default, the drift criterion with model-planned
conditioning holds (rig/planning/settling.py) in the order of least predicted rig time
(rig/planning/ordering.py), the same as listed (``--order fixed``), and the shipped default with
lost samples on the line.

Every Modbus transaction and DAQ command takes the time of an RTU line at 115,200 Bd
(``--line-baud``; 11 bits a character, 3.5 characters of silence after each frame, from
each frame's bytes), spent on the simulated clock as the rig's own waits are: the rig
time printed is at 1x with a serial line's latency, not an ideal link's.

Runs on the in-process virtual rig on simulated time (tests/virtual_rig_inprocess.py:
the rig package's drivers against the simulator, nominal truth, its fixed seed), which
gives the same rig time as ``simulator serve`` at any speed and takes a few minutes of
wall time, where a served simulator at 50x takes 50 s per thousand rig seconds and more
on a busy machine.  Each case runs in its own process, so that its peak RSS is its own.

    python benchmarks/bench_session.py                 # the four cases, side by side
    python benchmarks/bench_session.py --hold 60       # and a held 0.04 Hz experiment (memory)
    python benchmarks/bench_session.py --line-baud 0               # links without latency
    python benchmarks/bench_session.py --seeds 6 --cases today,new --jobs 2
                                    # the same over six draws of the simulator's noise

Two fits of independent noise differ by about sqrt(2) sigma rms, so a single draw says
little about whether the new criterion biases a parameter against today's. ``--seeds``
repeats each case over that many noise seeds and prints, per parameter, the mean
difference and its standard error: a bias is a mean that stays off zero.
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

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


def run_case(name: str, hold_cycles: int, out: Path, seed: int = 0, settings: tuple[str, ...] = (),
             plan: str = "standard", line_baud: float = 115200.0) -> dict:
    """One session in this process; returns its figures (JSON-able)."""
    from rig.config import DEFAULT_RIG_CONFIG
    from rig.session.outcome import ExitStatus
    from rig.session.run import Links, RunOptions, SessionContext, fit_session, prepare, run_lifecycle
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
    for setting in settings:   # KEY=VALUE: a top-level key of rig-default.toml's sections
        key, value = setting.split("=", 1)
        text, found = re.subn(rf'(?m)^{re.escape(key)} = [^#\n]*', f"{key} = {value} ", text)
        if not found:
            sys.exit(f"--set {setting}: no key {key!r} in {DEFAULT_RIG_CONFIG.name}")
    config = out / "rig.toml"
    config.write_text(text)
    rig = InProcessRig(config, seed=seed, line_baud=line_baud or None)
    rig.connect()
    try:
        for fault in faults:
            rig.when("settling", 0.0, partial(rig.inject, fault))
        letters = ["a"] if hold_cycles else None
        prep = prepare(RunOptions(plan=plan, shaker=SHAKER_URL, daq=DAQ_URL, out=out / "session",
                                  experiments=letters, rig_config=str(config), date="261122", order=order))
        started: dict[str, Any] = {}

        def predicted(ctx: SessionContext) -> list:
            # once the pace is probed and the durations predicted: the run's rig time starts here
            started.update(eta=sum(ctx.estimates_s.values()), t0=rig.clock.monotonic(), prep=ctx.runner.prep)
            return []

        result = run_lifecycle(prep, links=Links(rig.shaker, rig.daq, rig.identity, None), bus=rig.bus,
                               attach=predicted)
        taken = rig.clock.monotonic() - started["t0"]
        eta, prep, session = started["eta"], started["prep"], result.session
        phases = rig.phases()
        per = {}
        for e in prep.plan.experiments:
            label = session.label(e.letter)
            times = [t for t, x, _ in phases if x == label]
            cycles = next((ev.data.get("cycles") for _, ev in rig.events
                           if ev.kind == "phase" and ev.experiment == label and ev.data.get("phase") == "capturing"), 0)
            per[e.letter] = (max(times) - min(times) if times else 0.0, cycles)
        fit = {}
        if not hold_cycles and result.exit_status is ExitStatus.COMPLETE:
            fitted = fit_session(session, "2dof", START, ESTIMATE, result.captured)
            fit = {k: (fitted.params[k].value, fitted.std[k]) for k in ESTIMATE}
    finally:
        rig.close()
    return {"case": name, "status": result.status, "order": [e.letter for e in prep.plan.experiments],
            "per": per, "taken_s": taken, "eta_s": eta, "fit": fit,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "line": ({"transactions": rig.line_time.transactions, "seconds": rig.line_time.seconds}
                     if rig.line_time else None)}


def _run(name: str, hold: int, seed: int, settings: list[str], plan: str = "standard",
         line_baud: float = 115200.0) -> dict:
    proc = subprocess.run([sys.executable, __file__, "--case", name, "--hold", str(hold), "--seed", str(seed),
                           "--plan", plan, "--line-baud", str(line_baud)] + [f"--set={s}" for s in settings],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode:
        sys.exit(f"{name} (seed {seed}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def print_side_by_side(results: dict, shown: list[str], hold: int) -> None:
    print("rig time per experiment [s] (settle cycles); simulated time, in-process rig")
    print(f"{'':4}" + "".join(f"{n:>22}" for n in shown))
    for letter in sorted(results[shown[0]]["per"]):
        print(f"{letter:4}" + "".join(f"{results[n]['per'][letter][0]:>14.1f} ({results[n]['per'][letter][1]:>4})"
                                      for n in shown))
    print(f"{'total':6}" + "".join(f"{results[n]['taken_s']:>22.1f}" for n in shown))
    print(f"{'ETA':6}" + "".join(f"{results[n]['eta_s']:>22.1f}" for n in shown))
    print(f"{'ETA/taken':10}" + "".join(f"{results[n]['eta_s'] / results[n]['taken_s'] - 1:>+18.1%}" for n in shown))
    print(f"{'order':6}" + "".join(f"{''.join(results[n]['order']):>22}" for n in shown))
    print(f"{'RSS MB':6}" + "".join(f"{results[n]['peak_rss_mb']:>22.0f}" for n in shown))
    if results[shown[0]].get("line"):
        lines = [results[n]["line"] for n in shown]
        print(f"{'line':6}" + "".join(f"{x['transactions']:>9} tx {x['seconds']:>6.1f} s" for x in lines)
              + "  (Modbus transactions + DAQ commands, their line time)")
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
    if hold:
        h = results["hold"]
        print(f"\nheld: a (0.04 Hz) for {hold} cycles, {h['taken_s']:.0f} s of rig time: peak RSS "
              f"{h['peak_rss_mb']:.0f} MB")


def print_over_seeds(runs: dict, shown: list[str], seeds: list[int]) -> None:
    """Per seed, and as mean ± standard error over the seeds: rig time, ETA error and
    each parameter against the first case's fit of the same seed and against the truth."""
    import numpy as np

    from simulator.truth import load_truth

    truth = load_truth().theta
    first = shown[0]
    print(f"over {len(seeds)} noise seeds ({', '.join(map(str, seeds))}); simulated time, in-process rig")
    for n in shown:
        taken = np.array([runs[n, s]["taken_s"] for s in seeds])
        eta = np.array([runs[n, s]["eta_s"] for s in seeds]) / taken - 1
        print(f"{n:>12}: rig time {' '.join(f'{t:6.0f}' for t in taken)} s, mean {taken.mean():.0f} s;"
              f" ETA/taken {' '.join(f'{e:+.1%}' for e in eta)}")
    print("\nΔ in σ per seed, then mean ± standard error (a bias is a mean that stays off zero)")
    for n in shown:
        for k in ESTIMATE:
            vs_truth = np.array([(runs[n, s]["fit"][k][0] - truth[k]) / runs[n, s]["fit"][k][1] for s in seeds])
            line = f"{n:>12} {k:8} vs truth {' '.join(f'{d:+5.2f}' for d in vs_truth)}" \
                   f"  mean {vs_truth.mean():+.2f} ± {vs_truth.std(ddof=1) / np.sqrt(len(seeds)):.2f}"
            if n != first:
                vs_first = np.array([(runs[n, s]["fit"][k][0] - runs[first, s]["fit"][k][0])
                                     / runs[first, s]["fit"][k][1] for s in seeds])
                line += f";  vs {first} {' '.join(f'{d:+5.2f}' for d in vs_first)}" \
                        f"  mean {vs_first.mean():+.2f} ± {vs_first.std(ddof=1) / np.sqrt(len(seeds)):.2f}"
            print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--hold", type=int, default=0, help="also hold experiment a (0.04 Hz) for this many cycles")
    ap.add_argument("--cases", default=",".join(SIDE_BY_SIDE),
                    help=f"comma-separated, of {', '.join(c for c in CASES if c != 'hold')} (today's first)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="run each case over this many noise seeds (0, 1, …) and print the statistics")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once (rig time is simulated: unaffected)")
    ap.add_argument("--plan", default="standard",
                    help="the plan every case runs: standard or PLAN.toml (e.g. one rig design wrote)")
    ap.add_argument("--line-baud", type=float, default=115200.0,
                    help="each Modbus transaction and DAQ command takes an RTU line's time at this rate "
                         "(default 115200; 0: no latency)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a key of rig-default.toml in every case (e.g. drift_sigma_fraction=3.0)")
    args = ap.parse_args()
    if args.case:
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(run_case(args.case, args.hold if args.case == "hold" else 0, Path(tmp), args.seed,
                                      tuple(args.set), str(Path(args.plan).resolve()) if args.plan != "standard"
                                      else "standard", args.line_baud)))
        return
    shown = args.cases.split(",")
    seeds = list(range(args.seeds))
    jobs = [(n, s) for s in seeds for n in shown] + ([("hold", 0)] if args.hold else [])
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        done = dict(zip(jobs, pool.map(lambda job: _run(job[0], args.hold, job[1], args.set, args.plan,
                                                        args.line_baud), jobs), strict=True))
    print(f"plan: {args.plan}; links: " + (f"RTU line time at {args.line_baud:g} Bd per Modbus transaction and DAQ "
                                          "command (11 bits a character, 3.5-character gap per frame)"
                                          if args.line_baud else "no latency"))
    if len(seeds) == 1:
        print_side_by_side({n: r for (n, _), r in done.items()}, shown, args.hold)
    else:
        print_over_seeds(done, shown, seeds)


if __name__ == "__main__":
    main()
