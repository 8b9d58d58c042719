"""The type test behind a measurand QC spec: the product's nominal unit measured by the
spec's own procedure, so that the spec's nominal values are the product's.

For each measurand characteristic: its value on the nominal unit's noise-free response
(the value the spec's ``nominal`` states), and over ``--repeats`` captures with the
transducers' noise its mean, scatter and the expanded uncertainty the judge would
quote (each against the spec's tolerance half-width).  For a predicted characteristic
(the drop test's peak force): the unit's own drop (the spec's nominal) and, over
``--references`` reference units (the nominal and good units), the model's prediction
from the spec's identification against each unit's own drop: the relative errors' root
mean square is the model discrepancy σ_δ (identify/discrepancy.py) the spec states.

    python benchmarks/qc_type_test.py --spec measurands --world plant [--repeats 5] [--references 3]
    python benchmarks/qc_type_test.py --spec measurands-model --world model

Prints the TOML values to state; changing them is a new revision of the spec.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from _setup import ROOT  # first: one BLAS thread, set before numpy loads

# isort: split
import numpy as np
from qc_units import capture, damper

from identify.discrepancy import from_errors
from identify.parameters import Parameters
from rig.qc.characteristics import check_model, drop_peak_force
from rig.qc.evaluate import evaluate
from rig.qc.spec import Characteristic, Spec, load_spec

assert ROOT
TYPE_TEST_SEEDS = 9000   # seeds of the type test's captures and reference units, used nowhere else


def own_drop_kn(world: str, unit, c: Characteristic, spec: Spec) -> float:
    """The unit's own drop test's peak force [kN]."""
    if world == "model":
        model = check_model(spec)
        return drop_peak_force(model, Parameters(model, dict(unit.theta)).vector(), c.args["mass_kg"],
                               c.args["velocity_m_s"]) / 1e3
    from simulator.plant.drop import simulate_drop

    record = simulate_drop(mass_kg=c.args["mass_kg"], velocity_m_s=c.args["velocity_m_s"], duration_s=1.0,
                           constants=unit.k)
    return float(np.max(record.force_N)) / 1e3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spec", default="measurands")
    ap.add_argument("--world", default="plant", choices=("model", "plant"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--references", type=int, default=3, help="reference units for the drop's discrepancy (0: none)")
    args = ap.parse_args()
    spec = load_spec(args.spec)
    nominal = damper(args.world, None)
    measurands = [c for c in spec.characteristics if c.measurand]
    with tempfile.TemporaryDirectory() as tmp:
        clean = evaluate(spec, capture(spec, nominal, Path(tmp) / "clean", TYPE_TEST_SEEDS, 0.0), diagnose=False)
        noisy = [evaluate(spec, capture(spec, nominal, Path(tmp) / f"r{i}", TYPE_TEST_SEEDS + 1 + i), diagnose=False)
                 for i in range(args.repeats)]
    print(f"type test of spec {spec.name} {spec.version} on the {args.world} world's nominal unit "
          f"({args.repeats} captures with noise)\n")
    print(f"{'characteristic':<28} {'noise-free':>11} {'mean':>11} {'scatter':>9} {'k·u':>9} {'spec nominal':>12} "
          f"{'tol. half':>9}  unit")
    for c in measurands:
        v0 = next(m for m in clean.measured if m.name == c.name).value
        vals = [next(m for m in e.measured if m.name == c.name) for e in noisy]
        x = np.array([m.value for m in vals])
        ku = spec.k * float(np.mean([m.std for m in vals]))
        half = (c.high - c.low) / 2 if c.low is not None and c.high is not None else float("nan")
        print(f"{c.name:<28} {v0:11.5g} {x.mean():11.5g} {x.std(ddof=1):9.3g} {ku:9.3g} {c.nominal:12.5g} "
              f"{half:9.4g}  {c.unit}")
    for c in spec.characteristics:
        if c.kind != "drop_peak_force":
            continue
        own = own_drop_kn(args.world, nominal, c, spec)
        print(f"\n{c.name}: the nominal unit's own drop {own:.4g} kN (spec nominal {c.nominal:g})")
        errors = []
        for i in range(args.references):
            unit = nominal if i == 0 else damper(args.world, "good", TYPE_TEST_SEEDS + i)
            with tempfile.TemporaryDirectory() as tmp:
                ev = evaluate(spec, capture(spec, unit, Path(tmp) / "ref", TYPE_TEST_SEEDS + 50 + i))
            m = next(m for m in ev.measured if m.name == c.name)
            truth = own_drop_kn(args.world, unit, c, spec)
            if m.value is None:
                print(f"  reference {i}: no prediction ({m.note})")
                continue
            errors.append((m.value - truth) / truth)
            print(f"  reference {i}: predicted {m.value:.4g} kN, own drop {truth:.4g} kN, "
                  f"error {100 * errors[-1]:+.2f} %")
        if errors:
            d = from_errors(errors, f"{len(errors)} reference units' drops")
            print(f"  model discrepancy σ_δ = {100 * d.relative:.2f} % (discrepancy_percent)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
