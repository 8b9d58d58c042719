"""The measurand QC specs judged against the truth, in both worlds (issue 40's
acceptance table): production units captured as `rig qc run` captures the spec's plan
(from RUN on, offline with `simulator generate`), judged as `rig qc judge` judges them,
each against the same measurands on the unit's own noise-free response
(`--noise-scale 0`): a unit is truly faulty when one of those lies outside its limits.

Units (seeds used nowhere else): good ones, faulty ones (every fault kind in turn) and
units on a limit (per measurand and side, the unit's knob solved by bisection until its
noise-free measurand sits on the limit, captured with two noise seeds).  The plant's are
judged with spec ``measurands`` (its product), the model world's with
``measurands-model``.  The verdict rests on the measurands alone (the identification
only explains: it is not run here).

Printed per world: the confusion table; false accepts (truly faulty judged PASS, target
0); false rejects (truly good judged FAIL, target ≤ 2 % of the good); INCONCLUSIVE among
the good units whose true values lie inside 80 % of every tolerance (target ≤ 5 %);
units on a limit that PASS (target 0); per fault kind the share that FAILs (target
≥ 98 %); per measurand the error against the truth and how often |error| ≤ k·u.

    python benchmarks/bench_qc_measurands.py [--worlds plant,model] [--good 100] [--faulty 102] [--jobs 2]
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from _setup import ROOT  # first: one BLAS thread, set before numpy loads

# isort: split
import numpy as np
from qc_units import FAULTS, capture, damper

from rig.qc.evaluate import evaluate
from rig.qc.spec import Spec, load_spec
from simulator.physics import Damper
from simulator.truth import load_truth

assert ROOT
SPECS = {"plant": "measurands", "model": "measurands-model"}
GOOD_SEEDS, FAULT_SEEDS, LIMIT_SEEDS = 41000, 42000, 43000   # used nowhere else
# The knob that moves a measurand onto its limit: plant constant (or θ of the model world), and the kinds it moves.
PLANT_KNOBS = {"gas_spring_pressure": "gas_loss", "damping_force": "orifice_diameter",
               "seal_friction": "seal_preload_force", "cycle_energy": "orifice_diameter"}
MODEL_KNOBS = {"gas_spring_pressure": ("theta5", "theta15"), "damping_force": ("theta3",),
               "seal_friction": ("theta8", "theta9"), "cycle_energy": ("theta3",)}


@dataclass(frozen=True)
class Job:
    world: str
    label: str        # good, a fault kind, or characteristic@side
    seed: int         # the noise's (and a production unit's) seed
    unit: object      # None: a production unit of kind label; else PlantConstants or a Damper made on purpose


@dataclass
class Row:
    job: Job
    verdict: str
    failed: list[str]
    measured: dict[str, tuple[float | None, float | None]]   # value, u
    truth: dict[str, float | None]


def _unit(job: Job):
    if job.unit is not None:
        return damper(job.world, None, constants=job.unit)
    return damper(job.world, job.label, job.seed)


def values(spec: Spec, unit, seed: int, noise_scale: float, tmp: Path):
    ev = evaluate(spec, capture(spec, unit, tmp / f"n{noise_scale:g}", seed, noise_scale), diagnose=False)
    return ev


def judged(job: Job) -> Row:
    spec = load_spec(SPECS[job.world])
    unit = _unit(job)
    with tempfile.TemporaryDirectory() as tmp:
        ev = values(spec, unit, job.seed, 1.0, Path(tmp))
        clean = values(spec, unit, job.seed, 0.0, Path(tmp))
    measured = {m.name: (m.value, m.std) for m in ev.measured if not m.predicted}
    truth = {m.name: m.value for m in clean.measured if not m.predicted}
    failed = [j.name for j in ev.judgement.characteristics if j.outcome.value == "FAIL"]
    return Row(job, ev.judgement.verdict.value, failed, measured, truth)


def truly_out(spec: Spec, truth: dict[str, float | None]) -> list[str]:
    out = []
    for c in spec.characteristics:
        v = truth.get(c.name)
        if c.predicted or v is None:
            continue
        if (c.low is not None and v < c.low) or (c.high is not None and v > c.high):
            out.append(c.name)
    return out


def inside(spec: Spec, truth: dict[str, float | None], share: float = 0.8) -> bool:
    """Every true value inside ``share`` of its tolerance (about the tolerance's middle)."""
    for c in spec.characteristics:
        v = truth.get(c.name)
        if c.predicted or v is None or c.low is None or c.high is None:
            continue
        mid, half = (c.low + c.high) / 2, (c.high - c.low) / 2
        if abs(v - mid) > share * half:
            return False
    return True


def limit_units(world: str, spec: Spec) -> dict[str, object]:
    """Per measurand and side, a unit whose noise-free measurand lies on the limit."""
    out: dict[str, object] = {}
    if world == "plant":
        from simulator.plant.constants import load_constants

        base = load_constants()
    else:
        base_theta = dict(load_truth().theta)
    for c in spec.characteristics:
        if not c.measurand:
            continue
        for side, limit in (("low", c.low), ("high", c.high)):
            assert limit is not None

            def make(x: float, kind: str = c.kind):
                if world == "plant":
                    knob = PLANT_KNOBS[kind]
                    return base.changed(**{knob: getattr(base, knob) * x})
                theta = dict(base_theta)
                for name in MODEL_KNOBS[kind]:
                    theta[name] *= x
                return Damper(theta, "2dof")

            def value(x: float, name: str = c.name) -> float:
                with tempfile.TemporaryDirectory() as tmp:
                    unit = damper(world, None, constants=make(x))
                    ev = values(spec, unit, 0, 0.0, Path(tmp))
                v = next(m.value for m in ev.measured if m.name == name)
                assert v is not None
                return v

            lo, hi = 0.5, 2.0
            rising = value(hi) > value(lo)
            for _ in range(22):
                mid = math.sqrt(lo * hi)
                if (value(mid) < limit) == rising:
                    lo = mid
                else:
                    hi = mid
            out[f"{c.name}@{side}"] = make(math.sqrt(lo * hi))
    return out


def jobs_for(world: str, spec: Spec, good: int, faulty: int, limits: bool) -> list[Job]:
    todo = [Job(world, "good", GOOD_SEEDS + i, None) for i in range(good)]
    todo += [Job(world, FAULTS[i % len(FAULTS)], FAULT_SEEDS + i, None) for i in range(faulty)]
    if limits:
        for i, (label, unit) in enumerate(limit_units(world, spec).items()):
            todo += [Job(world, label, LIMIT_SEEDS + 2 * i + s, unit) for s in range(2)]
    return todo


def report(world: str, spec: Spec, rows: list[Row]) -> bool:
    print(f"\n## {world} world: spec {spec.name} {spec.version}, {len(rows)} units\n")
    print("| units | n | PASS | FAIL | INCONCLUSIVE | truly out of tolerance |")
    print("|---|---|---|---|---|---|")
    groups = {"good": [r for r in rows if r.job.label == "good"],
              **{k: [r for r in rows if r.job.label == k] for k in FAULTS},
              "on a limit": [r for r in rows if "@" in r.job.label]}
    for name, sel in groups.items():
        n = Counter(r.verdict for r in sel)
        print(f"| {name} | {len(sel)} | {n['PASS']} | {n['FAIL']} | {n['INCONCLUSIVE']} | "
              f"{sum(1 for r in sel if truly_out(spec, r.truth))} |")
    decided = [r for r in rows if "@" not in r.job.label]
    faulty_truth = [r for r in decided if truly_out(spec, r.truth)]
    good_truth = [r for r in decided if not truly_out(spec, r.truth)]
    fa = [r for r in faulty_truth if r.verdict == "PASS"]
    fr = [r for r in good_truth if r.verdict == "FAIL"]
    well_inside = [r for r in groups["good"] if inside(spec, r.truth)]
    inconclusive = [r for r in well_inside if r.verdict == "INCONCLUSIVE"]
    limit_pass = [r for r in groups["on a limit"] if r.verdict == "PASS"]
    ok = not fa and len(fr) <= 0.02 * len(good_truth) and not limit_pass
    ok = ok and len(inconclusive) <= 0.05 * max(len(well_inside), 1)
    print(f"\nfalse accepts {len(fa)} of {len(faulty_truth)} truly faulty (target 0)")
    print(f"false rejects {len(fr)} of {len(good_truth)} truly good = {100 * len(fr) / max(len(good_truth), 1):.1f} % "
          "(target ≤ 2 %)")
    print(f"INCONCLUSIVE {len(inconclusive)} of {len(well_inside)} good units inside 80 % of every tolerance = "
          f"{100 * len(inconclusive) / max(len(well_inside), 1):.1f} % (target ≤ 5 %)")
    print(f"on a limit: PASS {len(limit_pass)} of {len(groups['on a limit'])} (target 0)")
    for kind in FAULTS:
        sel = groups[kind]
        share = 100 * sum(r.verdict == "FAIL" for r in sel) / max(len(sel), 1)
        ok = ok and share >= 98
        print(f"{kind}: FAIL {sum(r.verdict == 'FAIL' for r in sel)} of {len(sel)} = {share:.1f} % (target ≥ 98 %)")
    for r in fa + fr + limit_pass + inconclusive:
        print(f"  {r.job.label}#{r.job.seed}: {r.verdict} {' '.join(r.failed)}; truly out: "
              f"{' '.join(truly_out(spec, r.truth)) or 'none'}")
    print("\n| measurand | unit | tolerance half-width | error mean (measured − truth) | error sd | mean k·u | "
          "|error| ≤ k·u |")
    print("|---|---|---|---|---|---|---|")
    for c in spec.characteristics:
        if c.predicted or c.low is None or c.high is None:
            continue
        pairs = [(r.measured[c.name], r.truth[c.name]) for r in rows
                 if r.measured.get(c.name, (None, None))[0] is not None and r.truth.get(c.name) is not None]
        err = np.array([m[0] - t for m, t in pairs])  # type: ignore[operator]
        ku = np.array([spec.k * m[1] for m, _ in pairs])  # type: ignore[operator]
        print(f"| {c.name} | {c.unit} | {(c.high - c.low) / 2:.4g} | {err.mean():+.3g} | {err.std():.3g} | "
              f"{ku.mean():.3g} | {100 * np.mean(np.abs(err) <= ku):.1f} % |")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", default="plant,model")
    ap.add_argument("--good", type=int, default=100)
    ap.add_argument("--faulty", type=int, default=102, help="faulty units, the fault kinds in turn")
    ap.add_argument("--no-limits", action="store_true", help="leave out the units on a limit")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    ok = True
    for world in [w for w in args.worlds.split(",") if w]:
        t0 = time.perf_counter()
        spec = load_spec(SPECS[world])
        todo = jobs_for(world, spec, args.good, args.faulty, not args.no_limits)
        print(f"{world}: {len(todo)} units ({time.perf_counter() - t0:.0f} s to solve the limit units)",
              file=sys.stderr, flush=True)
        rows = []
        with multiprocessing.get_context("fork").Pool(args.jobs) as pool:
            for r in pool.imap_unordered(judged, todo):
                rows.append(r)
        ok = report(world, spec, rows) and ok
        print(f"({time.perf_counter() - t0:.0f} s wall)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
