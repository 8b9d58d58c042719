"""The production QC plan of the default spec: rig time, fit time, uncertainty against
tolerance, and the confusion table over seeded production units.

Printed:
  * rig time per unit: the spec's plan with its steady-state criteria on the virtual rig
    in this process, on its simulated clock (seconds at 1x; target <= 6 min);
  * fit time (identification and characteristics, wall clock) on that session;
  * per characteristic: σ (fit, calibration, combined) against the tolerance half-width
    (target: every σ <= 1/4 of it);
  * the confusion table: seeded good units (target 0 false rejects) and seeded faulty
    units of each kind (target 0 false accepts, and the failed characteristic the fault's
    own), judged on generated data.

  * with ``--sessions``: every unit (``--units`` good and faulty ones, and one on each side
    of the pre-charge, damping and friction limits) run through the spec's plan on the
    in-process virtual rig with its own damper, judged on that session: the rig-time
    distribution (target: median <= 45 s, none over 90 s; the transient spec: <= 10 s,
    none over 20 s) and the decision table (target 0 false rejects, 0 false accepts; a
    unit on a limit never PASS).  ``--decide`` stops as ``qc run`` does when every
    characteristic is decided, within a transient capture too.  ``--line-baud 115200`` charges every Modbus
    transaction and DAQ command an RTU line's time at that rate; ``--world plant`` runs
    the plant truth's units (simulator/plant/) instead of the model's, a unit's truth
    then being its characteristics measured directly on its physics
    (benchmarks/bench_qc_plant.py) against the spec re-based on the nominal plant.

  * with ``--served``: every unit (``--units`` good and ``--units`` faulty ones) tested as
    a station does it: ``python -m rig qc run`` with the spec (``--spec``) against its own
    ``python -m simulator serve --unit KIND --speed 10`` over Modbus TCP and the DAQ's
    socket, with the run's early stop when decided: the rig-time distribution (from the
    simulator's log: first hydraulics on to last off) and the decision table (exit status
    and the record's failed characteristics).

    python benchmarks/bench_qc.py [--units 20] [--sessions [--jobs 2] [--line-baud 115200] [--world model|plant]
                                  [--decide]] [--served [--speed 10] [--jobs 2]] [--spec default|transient]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from rig.config import DEFAULT_RIG_CONFIG  # noqa: E402
from rig.qc.evaluate import evaluate  # noqa: E402
from rig.qc.run import decider, partial_judge  # noqa: E402
from rig.qc.spec import load_spec  # noqa: E402
from rig.session.run import Links, RunOptions, SessionRunner, prepare, run_lifecycle  # noqa: E402
from simulator.generate import generate  # noqa: E402
from simulator.physics import Damper  # noqa: E402
from simulator.plant.damper import PlantDamper  # noqa: E402
from simulator.truth import load_truth  # noqa: E402
from tests.virtual_rig_inprocess import DAQ_URL, SHAKER_URL, InProcessRig  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import bench_qc_plant  # noqa: E402

FAULT_OF = {"gas-leak": "gas_precharge_bar", "worn-seal": "friction_10bar_N", "worn-orifice": "damping_force_0.3_N"}
PHYSICAL = set(FAULT_OF.values())
SPEC = "default"  # --spec: the QC spec whose plan runs (forked workers inherit it)
LINE_BAUD: float | None = None  # --line-baud
WORLD = "model"   # --world
DECIDE = False    # --decide
TARGETS = {"default": (45.0, 90.0), "transient": (10.0, 20.0)}  # median, max rig seconds per unit


def rig_session(spec, out: Path, truth: Damper | PlantDamper | None = None,
                seed: int = 0) -> tuple[float, str, bool]:
    """The spec's plan as qc run executes it, on the in-process virtual rig: the rig
    seconds, the session's status for the table, and whether every experiment was captured."""
    rig = InProcessRig(DEFAULT_RIG_CONFIG, seed=seed, truth=truth, line_baud=LINE_BAUD)
    try:
        rig.connect()
        prep = prepare(RunOptions(plan=spec.source, shaker=SHAKER_URL, daq=DAQ_URL, out=out, date="261122",
                                  unit_serial="SN-0001"))
        prep = replace(prep, config=replace(prep.config, steady_state=spec.steady_state))
        def configure(runner: SessionRunner | None) -> None:
            if runner is None or not DECIDE:
                return
            # As qc run: judged between experiments and as a transient record grows (on a
            # thread of its own while the capture goes on).  A judgement's answer counts
            # from when the fit would have ended on the rig: its CPU seconds of the rig's
            # time after it began (the simulated clock runs as fast as it is driven).
            runner.decide = decider(spec, prep, None)
            judge = partial_judge(spec, out)

            def charged(record):
                began, c0 = rig.clock.monotonic(), time.thread_time()
                answer = judge(record)
                due, wall = began + time.thread_time() - c0, time.monotonic()
                while rig.clock.monotonic() < due and time.monotonic() - wall < 60.0:
                    time.sleep(0.002)
                return answer

            runner.acquisition.judge_partial = charged

        t0 = rig.sim.t
        result = run_lifecycle(prep, links=Links(rig.shaker, rig.daq, rig.identity, None), bus=rig.bus,
                               on_runner=configure)
        captured = result.exit_code == 0 and not result.skipped
        status = "complete" if captured else result.status
        if result.decided:
            status += f" early: {result.decided}"
        return rig.sim.t - t0, status, captured
    finally:
        rig.close()


Row = tuple[str, int, float, str, str, list[str], list[str]]


def judged_session(job: tuple[str, int, object]) -> Row:
    """One unit through the spec's plan on the in-process rig, judged on its session:
    (kind, seed, rig seconds, session status, verdict, failed characteristics, the
    characteristics truly out of tolerance).  The model world's truth is the unit's kind
    (good, a fault, or on a limit); the plant's its characteristics measured directly."""
    kind, seed, truth = job
    spec = _world_spec()
    with tempfile.TemporaryDirectory() as tmp:
        damper = PlantDamper(truth) if WORLD == "plant" else truth  # type: ignore[arg-type]
        rig_s, status, captured = rig_session(spec, Path(tmp) / "session", damper, seed)  # type: ignore[arg-type]
        if WORLD == "plant":
            direct = bench_qc_plant.direct_values(spec, bench_qc_plant.Job("plant", kind, seed, truth), Path(tmp))
            out_of_tolerance = bench_qc_plant.truly_faulty(spec, direct)
        else:
            out_of_tolerance = [FAULT_OF[kind]] if kind in FAULT_OF else []  # on a limit: neither
        if not captured:
            return kind, seed, rig_s, status, "-", [], out_of_tolerance
        ev = evaluate(spec, Path(tmp) / "session")
    failed = [j.name for j in ev.judgement.characteristics if j.outcome.value == "FAIL"]
    return kind, seed, rig_s, status, ev.judgement.verdict.value, failed, out_of_tolerance


_SPEC_CACHE: dict[tuple[str, str], object] = {}


def _world_spec():
    """The spec the units are judged against: as written in the model world; on the plant
    re-based on the nominal plant's directly measured characteristics (the spec a type
    whose nominal differs from the model's prior would be written with)."""
    key = (SPEC, WORLD)
    if key not in _SPEC_CACHE:
        spec = load_spec(SPEC)
        if WORLD == "plant":
            from simulator.plant.constants import load_constants

            with tempfile.TemporaryDirectory() as tmp:
                nominal = bench_qc_plant.direct_values(spec, bench_qc_plant.Job("plant", "nominal", 0,
                                                                                 load_constants()), Path(tmp))
            spec = bench_qc_plant.rebased(spec, nominal)
        _SPEC_CACHE[key] = spec
    return _SPEC_CACHE[key]


def sessions(units: int, jobs: int) -> int:
    """Rig-time distribution and decision table over units run through the plan."""
    import multiprocessing

    import numpy as np

    # The units on the limits first, then good and faulty ones in turn: a run cut short
    # still covers every kind.
    todo: list[tuple[str, int, object]]
    if WORLD == "plant":
        from simulator.plant.units import unit_constants

        todo = [(name, 3000 + i, k) for i, (name, k) in enumerate(bench_qc_plant.plant_limit_units(
            _world_spec()).items())]
        for i in range(units):
            fault = list(FAULT_OF)[i % 3]
            todo += [("good", 1000 + i, unit_constants("good", 1000 + i)),
                     (fault, 2000 + i, unit_constants(fault, 2000 + i))]
    else:
        todo = [(name, 3000 + i, d) for i, (name, d) in enumerate(bench_qc_plant.limit_units(load_spec(SPEC)).items())]
        for i in range(units):
            fault = list(FAULT_OF)[i % 3]
            todo += [("good", 1000 + i, load_truth(None, "2dof", "good", 1000 + i)),
                     (fault, 2000 + i, load_truth(None, "2dof", fault, 2000 + i))]
    median_target, max_target = TARGETS.get(SPEC, TARGETS["default"])
    rows = []
    t0 = time.perf_counter()
    with multiprocessing.get_context("fork").Pool(jobs) as pool:
        for row in pool.imap_unordered(judged_session, todo):
            rows.append(row)
            kind, seed, rig_s, status, verdict, failed, out = row
            print(f"  {kind:<28} seed {seed}: {rig_s:6.1f} s rig time, {status}, {verdict} {' '.join(failed)}"
                  f"{'; truly out: ' + ' '.join(out) if out else ''}", flush=True)
    taken = np.array([r[2] for r in rows])
    line = f"an RTU line at {LINE_BAUD:g} Bd" if LINE_BAUD else "no link latency"
    line += ", stopped when decided (the fits' CPU time charged)" if DECIDE else ""
    print(f"\n{len(rows)} units of the {WORLD} world through the {SPEC} spec's plan on the in-process rig at 1x "
          f"({line}), {time.perf_counter() - t0:.0f} s wall")
    within = np.median(taken) <= median_target and taken.max() <= max_target
    print(f"  rig time per unit: median {np.median(taken):.1f} s (target <= {median_target:g} s), 90th percentile "
          f"{np.percentile(taken, 90):.1f} s, max {taken.max():.1f} s (target none over {max_target:g} s); "
          f"{'met' if within else 'NOT met'}")
    for group in ("good", "faulty", "on a limit"):
        sel = [r for r in rows if (r[0] == "good") == (group == "good") and ("@" in r[0]) == (group == "on a limit")]
        if sel:
            t = np.array([r[2] for r in sel])
            counts = Counter(r[4] for r in sel)
            print(f"  {group:<11} {len(sel):>3} units: rig time median {np.median(t):5.1f} s, max {t.max():5.1f} s; "
                  f"PASS {counts['PASS']}, FAIL {counts['FAIL']}, INCONCLUSIVE {counts['INCONCLUSIVE']}, "
                  f"no verdict {counts['-']}")
    # Truth: the unit's kind in the model world, its directly measured characteristics on
    # the plant (a "good" plant unit may be truly out, a faulty one truly in).
    decided = [r for r in rows if "@" not in r[0]]
    false_rejects = sum(1 for r in decided if not r[6] and r[4] == "FAIL")
    false_accepts = sum(1 for r in decided if r[6] and r[4] == "PASS")
    limit_pass = sum(1 for r in rows if "@" in r[0] and r[4] == "PASS")
    truly = sum(1 for r in decided if r[6])
    print(f"  false rejects {false_rejects} of {len(decided) - truly} truly good (target 0), false accepts "
          f"{false_accepts} of {truly} truly faulty (target 0); units on a limit PASS {limit_pass} (target 0)")
    return int(bool(false_rejects or false_accepts or limit_pass or not within))


EXIT_VERDICT = {0: "PASS", 1: "FAIL", 4: "INCONCLUSIVE"}


def served_unit(job: tuple[str, int, float]) -> tuple[str, int, float, float, str, list[str], str]:
    """One unit as a station tests it: qc run against a served simulator of that unit.
    (kind, seed, rig seconds, wall seconds, verdict, failed characteristics, why no verdict)."""
    from rig.virtual import VirtualRig

    kind, seed, speed = job
    with tempfile.TemporaryDirectory() as tmp, VirtualRig(speed=speed, unit=kind, unit_seed=seed, seed=seed) as sim:
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "rig", "qc", "run", "--spec", SPEC, "--serial", f"SN-{seed:04d}",
                            "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out", tmp], capture_output=True,
                           text=True, cwd=ROOT)
        wall = time.perf_counter() - t0
        sim.stop()
        verdict = EXIT_VERDICT.get(r.returncode, f"exit {r.returncode}")
        failed: list[str] = []
        records = list(Path(tmp).glob("*/qc-record.json"))
        if records:
            doc = json.loads(records[0].read_text())
            failed = [k for k, c in doc["characteristics"].items() if c["outcome"] == "FAIL"]
        why = "" if r.returncode in EXIT_VERDICT else (r.stderr.strip().splitlines() or ["?"])[-1]
        return kind, seed, sim.rig_time_s(), wall, verdict, failed, why


def served(units: int, jobs: int, speed: float) -> int:
    """Rig-time distribution and decision table over units tested by qc run on served simulators."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    todo = []
    for i in range(units):
        todo += [("good", 1000 + i, speed), (list(FAULT_OF)[i % 3], 2000 + i, speed)]
    rows = []
    t0 = time.perf_counter()
    with ThreadPoolExecutor(jobs) as pool:
        for row in pool.map(served_unit, todo):
            rows.append(row)
            kind, seed, rig_s, wall, verdict, failed, why = row
            print(f"  {kind:<13} seed {seed}: {rig_s:6.1f} s rig time, {wall:5.1f} s wall, {verdict} "
                  f"{' '.join(failed)}{why}", flush=True)
    taken = np.array([r[2] for r in rows])
    walls = np.array([r[3] for r in rows])
    print(f"\n{len(rows)} units, each qc run against its own served simulator at {speed:g}x (Modbus TCP, DAQ "
          f"socket), {jobs} at a time, {time.perf_counter() - t0:.0f} s wall")
    print(f"  rig time per unit: median {np.median(taken):.1f} s (target <= 45 s), 90th percentile "
          f"{np.percentile(taken, 90):.1f} s, max {taken.max():.1f} s (target none over 90 s); "
          f"{'met' if np.median(taken) <= 45 and taken.max() <= 90 else 'NOT met'}")
    print(f"  wall per unit (process start, links, run, fit, record): median {np.median(walls):.1f} s, "
          f"max {walls.max():.1f} s")
    print(f"  {'unit':<8} {'n':>4} {'PASS':>6} {'FAIL':>6} {'INCONCLUSIVE':>13} {'no verdict':>11} "
          f"{'rig time median':>16}")
    for group in ("good", "faulty"):
        sel = [r for r in rows if (r[0] == "good") == (group == "good")]
        counts = Counter(r[4] for r in sel)
        print(f"  {group:<8} {len(sel):>4} {counts['PASS']:>6} {counts['FAIL']:>6} {counts['INCONCLUSIVE']:>13} "
              f"{len(sel) - sum(counts[v] for v in EXIT_VERDICT.values()):>11} "
              f"{np.median([r[2] for r in sel]):>14.1f} s")
    false_rejects = sum(1 for r in rows if r[0] == "good" and r[4] == "FAIL")
    false_accepts = sum(1 for r in rows if r[0] != "good" and r[4] == "PASS")
    wrong = [f"{r[0]} seed {r[1]}: failed {sorted(set(r[5]) & PHYSICAL)}" for r in rows
             if r[0] != "good" and r[4] == "FAIL" and set(r[5]) & PHYSICAL != {FAULT_OF[r[0]]}]
    print(f"  false rejects {false_rejects} (target 0), false accepts {false_accepts} (target 0), faulty units "
          f"failed on another characteristic than their fault's: {len(wrong)}")
    for line in wrong:
        print(f"    {line}")
    return int(bool(false_rejects or false_accepts))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--units", type=int, default=20, help="good units, and faulty units, each (default 20)")
    parser.add_argument("--sessions", action="store_true",
                        help="run every unit through the plan on the in-process rig (rig-time distribution)")
    parser.add_argument("--served", action="store_true",
                        help="test every unit with qc run against its own served simulator (rig time, decisions)")
    parser.add_argument("--speed", type=float, default=10.0, help="--served: the simulators' speed (default 10x)")
    parser.add_argument("--jobs", type=int, default=1, help="--sessions, --served: units run at once")
    parser.add_argument("--line-baud", type=float, help="--sessions: an RTU line's latency at this rate (115200)")
    parser.add_argument("--decide", action="store_true",
                        help="--sessions: stop when decided, between experiments and within a transient "
                             "capture (each fit's CPU time counted as rig time)")
    parser.add_argument("--world", choices=("model", "plant"), default="model",
                        help="--sessions: the units' physics (default model)")
    parser.add_argument("--spec", default="default", help="QC spec (default, transient: captured from RUN on, or a "
                                                          "file)")
    args = parser.parse_args()
    global SPEC, LINE_BAUD, WORLD, DECIDE
    SPEC, LINE_BAUD, WORLD, DECIDE = args.spec, args.line_baud, args.world, args.decide
    if args.served:
        return served(args.units, args.jobs, args.speed)
    if args.sessions:
        return sessions(args.units, args.jobs)
    spec = load_spec(SPEC)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rig_s, status, _ = rig_session(spec, Path(tmp) / "session")
        wall = time.perf_counter() - t0
        ev = evaluate(spec, Path(tmp) / "session")
        plan = ", ".join(f"{e.letter} {e.static_position_mm:g}±{e.amplitude_mm:g} mm {e.frequency_hz:g} Hz "
                         f"x{e.periods}" for e in spec.plan.experiments)
        print(f"{spec.name} spec {spec.version}: {len(spec.plan.experiments)} experiments ({plan})")
        print(f"  rig time per unit: {rig_s:6.1f} s = {rig_s / 60:.1f} min at 1x (session {status}; simulated in "
              f"{wall:.0f} s; target <= 6 min: {'met' if rig_s <= 360 else 'NOT met'})")
        print(f"  fit time (identification + characteristics): {ev.fit_s:.1f} s; verdict on the nominal damper: "
              f"{ev.judgement.verdict.value}")
        print(f"  {'characteristic':<22} {'value':>10} {'σ fit':>9} {'u_cal':>7} {'σ':>8} {'half-width':>10} "
              f"{'σ/half-width':>12}  (target <= 0.25)")
        worst = 0.0
        for c, m in zip(spec.characteristics, ev.measured, strict=True):
            assert c.low is not None and c.high is not None and m.value is not None and m.std is not None
            half = (c.high - c.low) / 2
            ratio = m.std / half
            worst = max(worst, ratio)
            print(f"  {c.name:<22} {m.value:10.5g} {m.std_fit:9.2g} {m.u_cal:7.2g} {m.std:8.2g} {half:10.4g} "
                  f"{ratio:12.3f}  {c.unit}")
        print(f"  every σ <= 1/4 of the tolerance half-width: {'met' if worst <= 0.25 else 'NOT met'} "
              f"(worst {worst:.3f})")

        kinds = ["good"] * args.units + [list(FAULT_OF)[i % 3] for i in range(args.units)]
        table: Counter[tuple[str, str]] = Counter()
        wrong_cause, fit_times = [], []
        for i, kind in enumerate(kinds):
            seed = 1000 + i
            out = generate(Path(tmp) / f"{kind}-{seed}", list(spec.plan.experiments),
                           load_truth(None, "2dof", kind, seed), periods=None, seed=seed, date="261122",
                           ramp_s=spec.steady_state.ramp_time_s)
            ev = evaluate(spec, out)
            fit_times.append(ev.fit_s)
            table[("good" if kind == "good" else "faulty", ev.judgement.verdict.value)] += 1
            failed = {j.name for j in ev.judgement.characteristics if j.outcome.value == "FAIL"} & PHYSICAL
            if kind != "good" and failed != {FAULT_OF[kind]}:
                wrong_cause.append(f"{kind} seed {seed}: failed {sorted(failed)}")
    print(f"confusion table, {args.units} good and {args.units} faulty seeded units (generated data, "
          f"fit {min(fit_times):.1f}…{max(fit_times):.1f} s per unit):")
    print(f"  {'unit':<8} {'PASS':>6} {'FAIL':>6} {'INCONCLUSIVE':>13}")
    for row in ("good", "faulty"):
        print(f"  {row:<8} " + " ".join(f"{table[(row, v)]:>{w}}" for v, w in
                                         (("PASS", 6), ("FAIL", 6), ("INCONCLUSIVE", 13))))
    false_rejects, false_accepts = table[("good", "FAIL")], table[("faulty", "PASS")]
    print(f"  false rejects {false_rejects} (target 0), false accepts {false_accepts} (target 0), "
          f"faulty units failed on another characteristic than their fault's: {len(wrong_cause)}")
    for line in wrong_cause:
        print(f"    {line}")
    return 0 if not (false_rejects or false_accepts or wrong_cause) and worst <= 0.25 and rig_s <= 360 else 1


if __name__ == "__main__":
    sys.exit(main())
