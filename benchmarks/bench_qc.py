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

    python benchmarks/bench_qc.py [--units 20]
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rich.console import Console  # noqa: E402

from rig.config import DEFAULT_RIG_CONFIG  # noqa: E402
from rig.qc.evaluate import evaluate  # noqa: E402
from rig.qc.spec import load_spec  # noqa: E402
from rig.run import Links, RunOptions, SessionRunner, prepare  # noqa: E402
from simulator.generate import generate  # noqa: E402
from simulator.truth import load_truth  # noqa: E402
from tests.virtual_rig_inprocess import DAQ_URL, SHAKER_URL, InProcessRig  # noqa: E402

FAULT_OF = {"gas-leak": "gas_precharge_bar", "worn-seal": "friction_10bar_N", "worn-orifice": "damping_force_0.3_N"}
PHYSICAL = set(FAULT_OF.values())


def rig_session(spec, out: Path) -> tuple[float, str]:
    """The spec's plan as qc run executes it, on the in-process virtual rig."""
    rig = InProcessRig(DEFAULT_RIG_CONFIG)
    try:
        rig.connect()
        prep = prepare(RunOptions(plan=spec.source, shaker=SHAKER_URL, daq=DAQ_URL, out=out, date="261122",
                                  unit_serial="SN-0001"))
        prep = replace(prep, config=replace(prep.config, steady_state=spec.steady_state))
        runner = SessionRunner(prep, Links(rig.shaker, rig.daq, rig.identity, None), rig.bus,
                               Console(file=io.StringIO()))
        t0 = rig.sim.t
        result = runner.run(runner.open_session())
        return rig.sim.t - t0, result.status
    finally:
        rig.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--units", type=int, default=20, help="good units, and faulty units, each (default 20)")
    args = parser.parse_args()
    spec = load_spec("default")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rig_s, status = rig_session(spec, Path(tmp) / "session")
        wall = time.perf_counter() - t0
        ev = evaluate(spec, Path(tmp) / "session")
        plan = ", ".join(f"{e.letter} {e.static_position_mm:g}±{e.amplitude_mm:g} mm {e.frequency_hz:g} Hz "
                         f"x{e.periods}" for e in spec.plan.experiments)
        print(f"default spec {spec.version}: {len(spec.plan.experiments)} experiments ({plan})")
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
                           load_truth(None, "2dof", kind, seed), periods=None, seed=seed, date="261122")
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
