"""Sensitivity of the paper's findings, and of the figures QC and the drop test rest on,
to the plant's unsourced constants: the fidelity benchmark's checks run on every named
variant of the plant (simulator.plant.family: constants moved within their brackets,
docs/plant.md), beside the model world.

Per variant it prints which findings hold under the paper's procedure and today's
(bench_plant_fidelity.py says what each is and how it is checked), θ16 of the paper's
small-amplitude experiments j, m, n, and the headline figures:
  * the orifice damping force at 0.1 and 0.3 m/s (20 °C) and the seal's Coulomb friction
    at 10 bar: what a QC spec's limits are set on;
  * the energy per cycle: ∮p dV of experiment a (0.04 Hz, the heat-loss loop) and ∮F dq
    of experiment b (0.1 Hz, 127 mm);
  * the drop test (350 kg touching at 0.5 m/s, simulator.plant.drop.simulate_drop): peak
    ground load, peak stroke, and the stroke's reversals within 2.5 s (oscillation or
    friction lock).

    python benchmarks/bench_plant_family.py [--variants low-cd,averaged-seal] [--procedure paper|today|both]
        [--keep DIR [--reuse]]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import _setup  # noqa: F401  (first: one BLAS thread, the repository importable)

# isort: split
import numpy as np
from bench_plant_fidelity import Finding, findings, loop_area, run_world
from bench_plant_fidelity import World as FidelityWorld

from identify.dataset import read_dataset
from simulator.plant.constants import PlantConstants
from simulator.plant.damper import PlantDamper
from simulator.plant.drop import simulate_drop
from simulator.plant.family import load_variant, variant_constants, variant_names
from simulator.plant.oil import kinematic_viscosity
from simulator.plant.orifice import pressure_drop
from simulator.truth import load_truth

DROP_MASS_KG = 350.0
DROP_VELOCITY_M_S = 0.5   # the paper's peak velocity
SMALL = ("j", "m", "n")   # where the paper found θ16 negative


@dataclass(frozen=True)
class Headline:
    damping_n: tuple[float, float]    # orifice force at 0.1, 0.3 m/s
    friction_10bar_n: float
    loop_a_j: float
    work_b_j: float
    drop_peak_force_n: float
    drop_peak_stroke_mm: float
    drop_reversals: int


def force_loop(folder: Path, letter: str) -> float:
    """∮ F dq per period of experiment ``letter`` [J]: the energy the damper takes per cycle."""
    ds = read_dataset(folder, ["stroke_mm", "force_N"])
    e = next(x for x in ds.experiments if x.label.endswith(letter))
    q, f = e.column("stroke_mm") * 1e-3, e.column("force_N")
    periods = (e.time_s[-1] - e.time_s[0]) * e.frequency_hz
    return float(abs(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(q))) / periods)


def headline(k: PlantConstants, folder: Path | None) -> Headline:
    nu = kinematic_viscosity(k, k.charge_temperature)
    area = k.geometry_piston_area
    damping = tuple(float(area * pressure_drop(k, area * v, nu)) for v in (0.1, 0.3))
    drop = simulate_drop(mass_kg=DROP_MASS_KG, velocity_m_s=DROP_VELOCITY_M_S, duration_s=2.5, rate_hz=1000.0,
                         constants=k)
    v = drop.velocity_m_s
    reversals = int(np.count_nonzero(np.diff(np.sign(v[np.abs(v) > 1e-3]))))
    loop_a = loop_area(folder, "a")[0] if folder else float("nan")
    work_b = force_loop(folder, "b") if folder else float("nan")
    return Headline((damping[0], damping[1]), k.seal_preload_force + k.seal_pressure_area * 10e5, loop_a, work_b,
                    float(np.max(drop.force_N)), float(np.max(drop.stroke_m) * 1e3), reversals)


def theta16_small(w: FidelityWorld, procedure: str) -> str:
    s = w.fits[procedure].singles2
    return " ".join(f"{s[k].values['theta16']:+.3g}" if s[k].converged else "--" for k in SMALL)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variants", help="comma-separated variant names (default: all, nominal first)")
    parser.add_argument("--procedure", choices=("paper", "today", "both"), default="both")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--keep", help="keep the generated datasets in this folder")
    parser.add_argument("--reuse", action="store_true", help="with --keep: fit the datasets already there")
    args = parser.parse_args()
    names = args.variants.split(",") if args.variants else variant_names()
    unknown = sorted(set(names) - set(variant_names()))
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(variant_names())})")
    procedures = ["paper", "today"] if args.procedure == "both" else [args.procedure]
    print(f"plant family benchmark: {len(names)} plants and the model world, the standard set each "
          f"({', '.join(procedures)} procedure)", flush=True)
    for n in names:
        print(f"  {n}: {load_variant(n).basis}")
    worlds: dict[str, FidelityWorld] = {}
    heads: dict[str, Headline] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        worlds["model world"] = run_world("model world", load_truth(), root / "model", args.seed, args.reuse,
                                            procedures)
        for n in names:
            k = variant_constants(n)
            worlds[n] = run_world(n, PlantDamper(k), root / n, args.seed, args.reuse, procedures)
            heads[n] = headline(k, root / n)
    table: dict[tuple[str, str], list[Finding]] = {(w, p): findings(worlds[w], p) for w in worlds for p in procedures}
    keys = [f.key for f in table[("model world", procedures[0])]]
    print(f"\nfindings that hold (+) or not (-), per procedure; columns {' '.join(keys)}; "
          f"θ16 [W/K] of {', '.join(SMALL)} (2-dof singles)")
    print(f"  {'world':24}" + "".join(f"{'the paper' if p == 'paper' else 'today':>20}{'θ16 j m n':>24}"
                                     for p in procedures))
    for w in worlds:
        cells = "".join(f"{' '.join('+' if f.holds else '-' for f in table[(w, p)]):>20}"
                        f"{theta16_small(worlds[w], p):>24}" for p in procedures)
        print(f"  {w:24}{cells}")
    for p in procedures:
        moves = [keys[i] for i in range(len(keys))
                 if len({table[(n, p)][i].holds for n in names}) > 1]
        always = [keys[i] for i in range(len(keys)) if all(table[(n, p)][i].holds for n in names)]
        never = [keys[i] for i in range(len(keys)) if not any(table[(n, p)][i].holds for n in names)]
        print(f"  {p}: across the family, hold on every plant: {' '.join(always) or 'none'}; on none: "
              f"{' '.join(never) or 'none'}; move with the constants: {' '.join(moves) or 'none'}")
    print("\nwhat decides findings 7 and 8 (friction from the force jumps: its line, and how far off the averaged "
          "line; single-experiment spreads of θ4, θ6, 2-dof/1-dof)")
    for w in worlds:
        f7 = table[(w, procedures[0])][6].shown.split("; ", 1)[1]
        f8 = "; ".join(f"{p}: {table[(w, p)][7].shown.split(' (')[0].removeprefix('spread 2-dof/1-dof: ')}"
                       for p in procedures)
        print(f"  {w:24}{f7}\n  {'':24}{f8}")
    print("\nheadline figures (QC and drop); the drop: 350 kg touching at 0.5 m/s, 2.5 s")
    print(f"  {'plant':24}{'damping 0.1 / 0.3 m/s':>24}{'friction @10 bar':>18}{'∮p dV a':>10}{'∮F dq b':>10}"
          f"{'drop peak F':>13}{'peak stroke':>13}{'reversals':>11}")
    for n in names:
        h = heads[n]
        print(f"  {n:24}{f'{h.damping_n[0]:.0f} / {h.damping_n[1]:.0f} N':>24}{f'{h.friction_10bar_n:.0f} N':>18}"
              f"{f'{h.loop_a_j:.0f} J':>10}{f'{h.work_b_j:.0f} J':>10}{f'{h.drop_peak_force_n / 1e3:.2f} kN':>13}"
              f"{f'{h.drop_peak_stroke_mm:.1f} mm':>13}{h.drop_reversals:>11}")
    print(f"\n{len(names)} plants and the model world in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
