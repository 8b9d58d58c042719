"""Fidelity of the plant truth to the paper: the standard set generated on the plant
(``simulator generate --physics plant``, offline), the 1-dof and 2-dof models fitted
with identify, and each of the paper's findings printed beside its statement, in both
worlds: the model world (data the 2-dof model itself made, the nominal θ) and the plant;
and under two procedures, side by side:

  * the paper's (Verbeek, de Kraker & van Campen 1995): friction θ8-θ10 of each
    experiment estimated from its force jumps at the velocity reversals (the paper's
    Fig. 7; identify.friction), then fixed; both models fitted on the stroke alone (the
    paper's criterion, eq. 24);
  * today's: friction fixed at the nominal averages θ8 = 80 N, θ9 = 4e-5 m² (the paper's
    averaged friction), each model on its declared outputs (1-dof: stroke; 2-dof: stroke
    and pressure), and for finding 4 the 1-dof also on stroke and pressure.

In both: θ3 fixed at its nominal value (the paper did not estimate it); 1-dof θ4, θ6, θ7;
2-dof θ4, θ6, θ16 from examples/start-2dof.json with θ16's lower bound 0 lifted (the paper
reports negative values); one experiment at a time, and jointly.

The findings (docs/plant.md prints the table this writes):
  1. single-experiment θ4 and θ6 spread far beyond their σ (1-dof);
  2. θ7 outside [1, 1.4] for some 1-dof single fits;
  3. joint 1-dof residual means depend on the group (high, middle, low);
  4. 2-dof residuals about half the 1-dof's on large amplitudes;
  5. θ16 varies, and is negative for some small-amplitude experiments (j, m, n);
  6. a heat-loss loop in the 0.04 Hz experiment (a);
  7. friction θ8-θ10 from each experiment's force jumps differs per experiment, roughly
     linearly with pressure, off the averaged line;
  8. the 2-dof single-experiment θ4 and θ6 spread much less than the 1-dof's;
  and the acceptance check: the 2-dof fit's residuals on the plant clearly exceed the
  transducer noise.

A finding the plant shows is *discriminating* when the model world (data of the
identification model itself) does not show it under the same procedure: only then does
reproducing it say something about the plant's physics.  Whatever the plant does not
show is printed as NOT reproduced.

    python benchmarks/bench_plant_fidelity.py [--seed 1] [--procedure paper|today|both] [--keep DIR [--reuse]]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from _setup import START  # first: one BLAS thread, set before numpy loads

# isort: split
import numpy as np

from identify.dataset import read_dataset
from identify.errors import IdentifyError
from identify.fit import fit_experiments
from identify.folding import fold
from identify.friction import FrictionResult, extract
from identify.model import load_model
from identify.notation import plus_minus, significant
from identify.parameters import Parameters
from identify.plans import STANDARD_SET
from identify.preparation import model_columns
from identify.result import FitResult
from simulator.generate import generate
from simulator.plant import load_plant
from simulator.sensors import DATASHEET_CHANNELS
from simulator.truth import load_truth

LARGE = ("a", "b", "g", "f", "k")          # amplitudes of 75 mm and more
SMALL = ("j", "c", "n", "m")               # 10-22 mm at 1-2 Hz
GROUPS = ("high", "middle", "low")
NOISE = {ch.name: ch.noise_std for ch in DATASHEET_CHANNELS}
ESTIMATE_1DOF = ["theta4", "theta6", "theta7"]
ESTIMATE_2DOF = ["theta4", "theta6", "theta16"]
# The 1-dof fit's trial steps probe exponents where (1 + θ6·q)^(−θ7) is undefined; the fit rejects those steps.
warnings.filterwarnings("ignore", "invalid value encountered in power", RuntimeWarning)
NOMINAL_FRICTION = (80.0, 4e-5)            # θ8 [N], θ9 [m²]: the averages of identify/models/damper.py


@dataclass(frozen=True)
class Procedure:
    name: str
    title: str
    per_experiment_friction: bool
    outputs_2dof: tuple[str, ...] | None   # None: the model's declared outputs


PROCEDURES = {
    "paper": Procedure("paper", "the paper's procedure: friction per experiment from the force jumps, then fixed; "
                       "stroke-only outputs (eq. 24)", True, ("stroke_mm",)),
    "today": Procedure("today", "today's procedure: friction fixed at the averages; 2-dof on stroke and pressure",
                       False, None),
}


@dataclass
class Single:
    letter: str
    values: dict[str, float]
    std: dict[str, float]
    rms: dict[str, float]      # residual rms per output
    converged: bool


@dataclass
class Fits:
    """One procedure's fits of one world."""

    procedure: Procedure
    singles1: dict[str, Single]
    singles2: dict[str, Single]
    singles1_same: dict[str, Single]   # the 1-dof on the 2-dof's outputs (large amplitudes), for finding 4
    joint1: FitResult
    joint2: FitResult


@dataclass
class World:
    name: str
    folder: Path
    generate_s: float
    generate_cpu_s: float
    fits: dict[str, Fits]
    loop_area: float
    loop_noise: float
    friction: FrictionResult


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def fit(model_name: str, experiments, estimate, params, outputs=None, fixed=None) -> FitResult:
    return fit_experiments(load_model(model_name), experiments, params, estimate, max_iterations=60,
                           outputs=outputs, fixed=fixed)


def single(model_name: str, exp, estimate, params, outputs=None, fixed=None) -> Single:
    try:
        r = fit(model_name, [exp], estimate, params, outputs, fixed)
    except (IdentifyError, ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        print(f"    {model_name} {exp.label}: no fit ({exc})")
        return Single(exp.label[-1], {}, {}, {}, False)
    e = r.experiments[0]
    rms = {o: float(np.sqrt(np.mean(e.residual(o) ** 2))) for o in e.measured}
    return Single(exp.label[-1], {k: r.value(k) for k in estimate}, {k: r.honest_std(k) for k in estimate}, rms,
                  bool(r.converged))


def loop_area(folder: Path, letter: str) -> tuple[float, float]:
    """∮ p dV over the captured periods of experiment ``letter`` per period [J], and its
    standard error from the transducer noise (V = A·stroke, A = 5e-3 m²)."""
    ds = read_dataset(folder, ["stroke_mm", "pressure_bar"])
    e = next(x for x in ds.experiments if x.label.endswith(letter))
    q = e.column("stroke_mm") * 1e-3
    p = e.column("pressure_bar") * 1e5
    periods = (e.time_s[-1] - e.time_s[0]) * e.frequency_hz
    work = float(np.sum(0.5 * (p[1:] + p[:-1]) * np.diff(q)) * 5e-3 / periods)  # compression positive in q
    # Noise: each sample's pressure noise times its stroke step, summed in quadrature.
    noise = float(np.sqrt(np.sum((NOISE["pressure_bar"] * 1e5 * np.diff(q)) ** 2)) * 5e-3 / periods)
    return work, noise


def generate_world(name: str, truth, out: Path, seed: int, reuse: bool) -> tuple[float, float]:
    """The standard set (3 periods, 2 kHz) of ``truth`` into ``out``: (wall s, CPU s)."""
    t0, c0 = time.perf_counter(), cpu_s()
    if not (reuse and (out / "dataset.json").exists()):
        generate(out, list(STANDARD_SET), truth, periods=3, rate_hz=2000.0, seed=seed, date="261126")
    gen_s, gen_cpu = time.perf_counter() - t0, cpu_s() - c0
    print(f"  {name}: standard set generated in {gen_s:.1f} s ({gen_cpu:.1f} s CPU)", flush=True)
    return gen_s, gen_cpu


def fit_procedure(out: Path, friction: FrictionResult, procedure: Procedure) -> Fits:
    m1, m2 = load_model("1dof"), load_model("2dof")
    p1 = Parameters(m1)
    p2 = Parameters.from_file(m2, str(START))
    p2["theta16"].minimum = None
    fixed = None
    if procedure.per_experiment_friction:
        names = p2.names()
        fixed = {e.label: {names.index(k): getattr(e, k) for k in ("theta8", "theta9", "theta10")}
                 for e in friction.experiments}
    outputs2 = list(procedure.outputs_2dof or m2.declaration.default_outputs)
    e1 = [e for e in read_dataset(out, model_columns(m1, list(m1.declaration.default_outputs))).experiments
          if e.kind == "periodic"]
    e2 = [e for e in read_dataset(out, model_columns(m2, outputs2)).experiments if e.kind == "periodic"]
    s1 = {e.label[-1]: single("1dof", e, ESTIMATE_1DOF, p1, fixed=fixed) for e in e1}
    s2 = {e.label[-1]: single("2dof", e, ESTIMATE_2DOF, p2, outputs2, fixed) for e in e2}
    if outputs2 == list(m1.declaration.default_outputs):
        same = {k: s1[k] for k in LARGE}
    else:
        same = {e.label[-1]: single("1dof", e, ESTIMATE_1DOF, p1, outputs2, fixed) for e in e2
                if e.label[-1] in LARGE}
    j1 = fit("1dof", e1, ESTIMATE_1DOF, p1, fixed=fixed)
    j2 = fit("2dof", e2, ESTIMATE_2DOF, p2, outputs2, fixed)
    return Fits(procedure, s1, s2, same, j1, j2)


def run_world(name: str, truth, out: Path, seed: int, reuse: bool, procedures: list[str]) -> World:
    t0 = time.perf_counter()
    gen_s, gen_cpu = generate_world(name, truth, out, seed, reuse)
    friction = friction_jumps(out)
    fits = {p: fit_procedure(out, friction, PROCEDURES[p]) for p in procedures}
    area, noise = loop_area(out, "a")
    print(f"  {name}: fits done ({time.perf_counter() - t0:.0f} s in all)", flush=True)
    return World(name, out, gen_s, gen_cpu, fits, area, noise, friction)


def friction_jumps(folder: Path) -> FrictionResult:
    """θ8-θ10 of each experiment from its force jumps at the reversals."""
    columns = ("stroke_mm", "force_N", "pressure_bar")
    ds = read_dataset(folder, list(columns))
    return extract([fold(e.label, e.time_s, {c: e.column(c) for c in columns}, e.frequency_hz, 800,
                         e.sample_rate_hz) for e in ds.experiments if e.kind == "periodic"])


def spread(singles: dict[str, Single], name: str) -> tuple[float, float, float, float]:
    """Min, max, relative spread (max−min)/|median| and median σ/|value| over converged fits."""
    vals = np.array([s.values[name] for s in singles.values() if s.converged])
    stds = np.array([s.std[name] for s in singles.values() if s.converged])
    med = float(np.median(vals))
    return float(vals.min()), float(vals.max()), float(np.ptp(vals) / abs(med)), float(np.median(stds / np.abs(vals)))


def group_means(joint: FitResult, output: str) -> dict[str, tuple[float, float]]:
    """Residual mean per group and the mean's noise-only standard error."""
    out = {}
    groups = {s.letter: s.group for s in STANDARD_SET}
    for g in GROUPS:
        r = np.concatenate([e.residual(output) for e in joint.experiments if groups[e.label[-1]] == g])
        out[g] = (float(np.mean(r)), float(NOISE[output] / np.sqrt(len(r))))
    return out


@dataclass(frozen=True)
class Finding:
    key: str              # "1" … "8", "*"
    title: str
    paper: str
    shown: str            # what this world shows
    holds: bool
    by_procedure: bool    # False: the same data under either procedure (6, 7)


def findings(w: World, procedure: str) -> list[Finding]:
    """Each finding in world ``w`` under ``procedure``."""
    f = w.fits[procedure]
    rows = []
    lo4, hi4, sp4, sd4 = spread(f.singles1, "theta4")
    lo6, hi6, sp6, sd6 = spread(f.singles1, "theta6")
    n_conv1 = sum(s.converged for s in f.singles1.values())
    rows.append(Finding("1", "spread of single-experiment θ4, θ6 (1-dof)",
                        "θ4 and θ6 'by far not constant over the experiments'; not all fits converged",
                        f"θ4 {significant(lo4)}…{significant(hi4)} m² (spread {sp4:.0%}, σ {sd4:.1%}); "
                        f"θ6 {significant(lo6)}…{significant(hi6)} 1/m (spread {sp6:.0%}, σ {sd6:.1%}); "
                        f"{n_conv1}/14 converged",
                        sp4 > 5 * sd4 and sp6 > 5 * sd6 and sp4 > 0.05, True))
    th7 = {k: s.values["theta7"] for k, s in f.singles1.items() if s.converged}
    outside = sorted(k for k, v in th7.items() if not 1.0 <= v <= 1.4)
    rows.append(Finding("2", "θ7 outside [1, 1.4] (1-dof singles)",
                        "the gas exponent θ7 fell outside the isothermal-adiabatic range 1-1.4",
                        "θ7 " + " ".join(f"{k}:{v:.2f}" for k, v in sorted(th7.items()))
                        + f"; outside: {','.join(outside) or 'none'}",
                        bool(outside), True))
    gm = group_means(f.joint1, "stroke_mm")
    spread_g = max(m for m, _ in gm.values()) - min(m for m, _ in gm.values())
    se = max(s for _, s in gm.values())
    rows.append(Finding("3", "group-dependent residual means (1-dof joint)",
                        "joint-fit residual means depend on the group: the polytropic spring is not right over "
                        "the stroke",
                        "stroke residual mean " + ", ".join(f"{g} {m:+.3f} mm" for g, (m, _) in gm.items())
                        + f" (noise-only s.e. {se:.1e} mm)",
                        spread_g > 10 * se and spread_g > 0.02, True))
    both = [k for k in LARGE if f.singles1_same[k].converged and f.singles2[k].converged]

    def rms(s: Single) -> float:  # over the outputs, each in units of its transducer noise
        return float(np.sqrt(np.mean([(s.rms[o] / NOISE[o]) ** 2 for o in s.rms])))
    ratios = [rms(f.singles2[k]) / rms(f.singles1_same[k]) for k in both]
    ratio = float(np.median(ratios)) if both else float("nan")
    outputs = " and ".join(o.split("_")[0] for o in (f.procedure.outputs_2dof or ("stroke_mm", "pressure_bar")))
    rows.append(Finding("4", "2-dof residuals vs 1-dof on large amplitudes",
                        "on large amplitudes the 2-dof residuals are about half the 1-dof model's",
                        f"rms ({outputs}, in noise units) 2-dof/1-dof on " + ",".join(both) + ": "
                        + " ".join(f"{r:.2f}" for r in ratios) + f" (median {ratio:.2f})",
                        0.25 <= ratio <= 0.75, True))
    th16 = {k: (s.values["theta16"], s.std["theta16"]) for k, s in f.singles2.items() if s.converged}
    negative = sorted(k for k, (v, _) in th16.items() if v < 0)
    vals = np.array([v for v, _ in th16.values()])
    rows.append(Finding("5", "θ16 varies, negative for small amplitudes (2-dof singles)",
                        "θ16 'far from constant', negative for some small-amplitude experiments (j, m, n)",
                        "θ16 [W/K] " + " ".join(f"{k}:{v:.2g}" for k, (v, _) in sorted(th16.items()))
                        + f"; negative: {','.join(negative) or 'none'}",
                        bool(set(negative) & {"j", "m", "n"}) and float(np.ptp(vals)) > 1.0, True))
    rows.append(Finding("6", "heat-loss loop at 0.04 Hz (experiment a)",
                        "heat loss shows even in the almost static 0.04 Hz experiment: the p-stroke loop encloses "
                        "an area",
                        f"∮p dV = {plus_minus(w.loop_area, w.loop_noise, 'J')} per period",
                        w.loop_area > 5 * w.loop_noise, False))
    fr = w.friction
    amps = {e.label[-1]: (np.mean([r.pressure_bar for r in e.reversals]), np.mean([r.amplitude_n for r in e.reversals]))
            for e in fr.experiments}
    th8, th9 = NOMINAL_FRICTION
    off = max(abs(a / (th8 + th9 * p * 1e5) - 1) for p, a in amps.values())
    rows.append(Finding("7", "friction per experiment from the force jumps",
                        "θ8-θ10 differ per experiment, roughly linearly with pressure; the averages were used",
                        "F_a [N] at p [bar] " + " ".join(f"{k}:{a:.0f}@{p:.0f}" for k, (p, a) in sorted(amps.items()))
                        + f"; line θ8 = {plus_minus(fr.theta8, fr.theta8_std, 'N')}, θ9 = "
                        + f"{plus_minus(fr.theta9, fr.theta9_std, 'm²')}; up to {off:.0%} off the nominal θ8 + θ9·p",
                        bool(float(np.ptp([a for _, a in amps.values()])) > 20 and fr.theta9 > 0 and off > 0.1),
                        False))
    _, _, sp4b, _ = spread(f.singles2, "theta4")
    _, _, sp6b, _ = spread(f.singles2, "theta6")
    rows.append(Finding("8", "2-dof single-experiment spreads vs the 1-dof's",
                        "the 2-dof single-experiment θ4 and θ6 spread much less than the 1-dof's",
                        f"spread 2-dof/1-dof: θ4 {sp4b:.0%}/{sp4:.0%}, θ6 {sp6b:.0%}/{sp6:.0%} "
                        "(much less: below half)",
                        sp4b < 0.5 * sp4 and sp6b < 0.5 * sp6, True))
    ratio_noise = {o: float(np.sqrt(f.joint2.channel_variances[o])) / NOISE[o] for o in f.joint2.outputs}
    rows.append(Finding("*", "2-dof residuals vs transducer noise (joint)",
                        "(acceptance) a plant the model fits to the noise has failed",
                        ", ".join(f"{o} residual std {ratio_noise[o]:.0f}x noise" for o in ratio_noise),
                        min(ratio_noise.values()) > 3, True))
    return rows


def verdict(plant: Finding, model: Finding | None) -> str:
    """REPRODUCED/NOT reproduced, and whether the model world shows it too."""
    if not plant.holds:
        return "NOT reproduced"
    if model is None:
        return "REPRODUCED"
    return "REPRODUCED, not discriminating" if model.holds else "REPRODUCED, discriminating"


def serving_cost(damper, seconds: float = 20.0) -> float:
    """CPU seconds per rig second of the in-process engine running experiment j (2 Hz,
    the densest) at the served rate, blocks of 0.1 s (what 10x serving steps)."""
    from simulator.daq import TcpPort
    from simulator.engine import VirtualRig
    from simulator.faults import FaultLog

    spec = next(s for s in STANDARD_SET if s.letter == "j")
    rig = VirtualRig(damper, TcpPort(), seed=1, modbus_port=0, speed=10, log=FaultLog(sink=lambda line: None))
    c = rig.controller
    c.write_coils(0, [True])
    c.write_holding(1, [0, int(spec.static_position_mm * 100), int(spec.amplitude_mm * 100),
                        int(round(spec.frequency_hz * 1000)), 20])
    c.write_holding(0, [2])
    rig.daq.rate_hz = 2000
    rig.daq._handle("START")
    c0 = cpu_s()
    for k in range(1, int(seconds * 10) + 1):
        rig.step_to(k * 0.1)
        rig.daq._out.clear()
    cost = (cpu_s() - c0) / seconds
    rig.daq.port.close()
    return cost


def print_table(worlds: list[World], procedures: list[str]) -> None:
    tables = {(w.name, p): findings(w, p) for w in worlds for p in procedures}
    model = next(w for w in worlds if w.name == "model world")
    plant = next(w for w in worlds if w.name != "model world")
    rows = tables[(plant.name, procedures[0])]
    print()
    for i, row in enumerate(rows):
        print(f"{row.key}. {row.title}\n    paper:  {row.paper}")
        for p in procedures if row.by_procedure else procedures[:1]:
            m, pl = tables[(model.name, p)][i], tables[(plant.name, p)][i]
            if row.by_procedure:
                print(f"    [{p}'s procedure]" if p == "today" else "    [the paper's procedure]")
            print(f"      model world: {'shown    ' if m.holds else 'not shown'}  {m.shown}")
            print(f"      plant:       {verdict(pl, m):31} {pl.shown}")
    print("\nsummary (plant; discriminating: the model world does not show it under the same procedure)")
    print(f"  {'finding':62}" + "".join(f"{'the paper' if p == 'paper' else 'today':32}" for p in procedures))
    for i, row in enumerate(rows):
        cells = "".join(f"{verdict(tables[(plant.name, p)][i], tables[(model.name, p)][i]):32}" for p in procedures)
        print(f"  {row.key + '. ' + row.title:62}{cells}")
    for p in procedures:
        held = sum(r.holds for r in tables[(plant.name, p)])
        disc = sum(r.holds and not m.holds for r, m in zip(tables[(plant.name, p)], tables[(model.name, p)],
                                                           strict=True))
        print(f"  {PROCEDURES[p].title}: plant reproduces {held} of {len(rows)}, {disc} of them discriminating")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--procedure", choices=("paper", "today", "both"), default="both")
    parser.add_argument("--keep", help="keep the generated datasets in this folder")
    parser.add_argument("--reuse", action="store_true", help="with --keep: fit the datasets already there")
    parser.add_argument("--no-cost", action="store_true", help="skip the serving-cost measurement")
    args = parser.parse_args()
    procedures = ["paper", "today"] if args.procedure == "both" else [args.procedure]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        print("plant fidelity benchmark: the standard set, fits of the 1-dof and 2-dof models", flush=True)
        for p in procedures:
            print(f"  {PROCEDURES[p].title}")
        worlds = [run_world("model world", load_truth(), root / "model", args.seed, args.reuse, procedures),
                  run_world("plant", load_plant(), root / "plant", args.seed, args.reuse, procedures)]
    print_table(worlds, procedures)
    print()
    for w in worlds:
        for p, f in w.fits.items():
            joint2 = ", ".join(f"{k} = {plus_minus(f.joint2.value(k), f.joint2.honest_std(k))}" for k in ESTIMATE_2DOF)
            joint1 = ", ".join(f"{k} = {plus_minus(f.joint1.value(k), f.joint1.honest_std(k))}" for k in ESTIMATE_1DOF)
            print(f"{w.name} ({p}): joint 2-dof {joint2}; joint 1-dof {joint1}")
        print(f"{w.name}: generate {w.generate_s:.1f} s wall, {w.generate_cpu_s:.1f} s CPU for the standard set")
    if not args.no_cost:
        for name, damper in (("model", load_truth()), ("plant", load_plant())):
            cost = serving_cost(damper)
            print(f"{name}: serving costs {cost * 1e3:.0f} ms CPU per rig second (2 Hz experiment j, 0.1 s blocks): "
                  f"{1 / cost:.0f}x real time on one core")


if __name__ == "__main__":
    main()
