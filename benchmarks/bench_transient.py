"""Transient fits (issue 36): is their σ honest, and do they stay O(N)?

1. Monte-Carlo: ``--seeds`` noise realisations of records captured from RUN on (the
   simulator's streaming plant from rest: actuator, gas heating up, 16-bit sensors; not
   the fitted model's discretisation), each fitted as a transient from a start 10 % off;
   spread of the estimates / mean reported σ per parameter (target 0.8–1.2: σ within
   ±20 % of the spread) and ±2σ coverage, for two cases:
     lab  experiments j and n of the standard set (2 Hz, 10 mm), 3 s each from RUN,
          θ4 θ6 θ16 — about 6 s of capture against minutes of settling;
     qc   the default QC spec's experiment (14 ± 20 mm at 4 Hz), 3 s from RUN,
          its estimates θ3 θ5 θ6 θ8 θ15.
2. Scaling: one fit of experiment j from RUN on records of 10⁴, 10⁵ and 10⁶ samples
   (2 kHz: 5 s, 50 s, 500 s of rig time), each in a child process: wall time and peak
   resident memory, and both per sample.

    python benchmarks/bench_transient.py                    # 24 seeds, 2 workers, sizes 1e4,1e5,1e6
    python benchmarks/bench_transient.py --seeds 4 --sizes 1e4,1e5   # a quick look
"""

from __future__ import annotations

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import _setup  # noqa: F401  (one BLAS thread, the repository importable)
import numpy as np  # noqa: E402

from identify.dataset import read_dataset  # noqa: E402
from identify.fit import fit_experiments  # noqa: E402
from identify.model import load_model  # noqa: E402
from identify.parameters import Parameters  # noqa: E402
from identify.plans import STANDARD_SET, ExperimentSpec, select  # noqa: E402
from identify.preparation import model_columns, resolve_outputs  # noqa: E402
from simulator.generate import generate  # noqa: E402
from simulator.truth import load_truth  # noqa: E402

SPREAD_TARGET = (0.8, 1.2)
RATE_HZ = 2000.0
RAMP_S = 1.0
QC_SPEC = ExperimentSpec("a", "designed", 14, 20, 4.0)  # rig/qc/specs/default.toml's experiment


@dataclass(frozen=True)
class Case:
    name: str
    specs: tuple[ExperimentSpec, ...]
    periods: int
    estimate: tuple[str, ...]


CASES = (
    Case("lab", tuple(select(STANDARD_SET, ["j", "n"])), 6, ("theta4", "theta6", "theta16")),
    Case("qc", (QC_SPEC,), 12, ("theta3", "theta5", "theta6", "theta8", "theta15")),
)


def fit_record(folder: Path, estimate: tuple[str, ...], start_factor: float = 1.1):
    """One transient fit of every record in ``folder`` from a start ``start_factor`` off."""
    model = load_model("2dof")
    outputs = resolve_outputs(model, None)
    ds = read_dataset(folder, model_columns(model, outputs))
    params = Parameters(model)
    for name in estimate:
        params[name].value *= start_factor
    return fit_experiments(model, ds.experiments, params, list(estimate))


def _seed(args: tuple[Case, int]) -> tuple[str, np.ndarray, np.ndarray, bool, float]:
    case, seed = args
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, list(case.specs), load_truth(), periods=case.periods, rate_hz=RATE_HZ, seed=seed,
                 date="261126", capture="transient", ramp_s=RAMP_S)
        t0 = time.perf_counter()
        result = fit_record(Path(tmp), case.estimate)
        elapsed = time.perf_counter() - t0
    return (case.name, np.array([result.value(k) for k in case.estimate]),
            np.array([result.std[k] for k in case.estimate]), result.converged, elapsed)


def monte_carlo(seeds: int, workers: int) -> bool:
    truth = load_truth().theta
    tasks = [(c, s) for c in CASES for s in range(seeds)]
    results: dict[str, list] = {c.name: [] for c in CASES}
    t0 = time.perf_counter()
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        for name, value, std, conv, elapsed in pool.imap_unordered(_seed, tasks):
            results[name].append((value, std, conv, elapsed))
    print(f"σ of transient fits: {seeds} seeds per case, start 10 % off, {time.perf_counter() - t0:.0f} s with "
          f"{workers} workers; target spread/σ {SPREAD_TARGET[0]}–{SPREAD_TARGET[1]} (σ within ±20 % of the "
          f"spread), ±2σ coverage about 95 %")
    print(f"(statistical uncertainty of each spread/σ: ±{1 / np.sqrt(2 * (seeds - 1)):.2f})")
    ok = True
    for case in CASES:
        rows = results[case.name]
        values = np.array([r[0] for r in rows])
        stds = np.array([r[1] for r in rows])
        true = np.array([truth[k] for k in case.estimate])
        spread = values.std(axis=0, ddof=1)
        ratio = spread / stds.mean(axis=0)
        coverage = np.mean(np.abs(values - true) <= 2 * stds, axis=0)
        bias = (values.mean(axis=0) - true) / (spread / np.sqrt(len(rows)))
        fit_s = np.median([r[3] for r in rows])
        capture_s = case.periods / case.specs[0].frequency_hz * len(case.specs)
        within = bool(np.all((ratio >= SPREAD_TARGET[0]) & (ratio <= SPREAD_TARGET[1])))
        ok &= within
        print(f"{case.name}: {len(case.specs)} record(s), {capture_s:g} s of capture from RUN, fit {fit_s:.1f} s "
              f"(median), converged {sum(r[2] for r in rows)}/{len(rows)}  {'ok' if within else 'OUTSIDE TARGET'}")
        print(f"    {'parameter':10s} {'truth':>11s} {'mean σ':>10s} {'spread':>10s} {'spread/σ':>9s} "
              f"{'cov ±2σ':>8s} {'bias/se':>8s}")
        for i, k in enumerate(case.estimate):
            print(f"    {k:10s} {true[i]:11.5g} {stds[:, i].mean():10.3g} {spread[i]:10.3g} {ratio[i]:9.2f} "
                  f"{100 * coverage[i]:7.0f}% {bias[i]:+8.2f}")
    return ok


def _scaling_child(samples: int) -> None:
    """In a child process: a record of ``samples`` from RUN, one fit; prints JSON."""
    spec = select(STANDARD_SET, ["j"])
    periods = int(np.ceil(samples / RATE_HZ * spec[0].frequency_hz))
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, spec, load_truth(), periods=periods, rate_hz=RATE_HZ, seed=1, date="261126",
                 capture="transient", ramp_s=RAMP_S)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        result = fit_record(Path(tmp), ("theta4", "theta6", "theta16"), 1.02)
        elapsed = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"samples": int(np.ceil(periods * RATE_HZ / spec[0].frequency_hz)), "fit_s": elapsed,
                      "iterations": result.iterations, "converged": result.converged,
                      "peak_mib": peak / 1024, "before_mib": before / 1024}))


def _kernel_child(samples: int) -> None:
    """In a child process: one Newton step of the record's system (the model's Jacobian
    at every point, the banded LU, a solve) and the sensitivities' solve for three
    parameters, on ``samples`` points of a 2 Hz record; prints JSON."""
    from identify.trajectory import TrajectorySolver, TransientData, Unfolded

    model = load_model("2dof")
    theta = Parameters(model).vector()
    t = np.arange(samples) / RATE_HZ
    force = 4500.0 + 300.0 * np.sin(2 * np.pi * 2.0 * t)
    data = TransientData("k", 2.0, 1 / RATE_HZ, force[None], np.zeros((2, samples)), np.ones(2), np.ones(1),
                         Unfolded(samples))
    solver = TrajectorySolver(model, data, [model.output_index(o) for o in resolve_outputs(model, None)])
    X = np.vstack([np.full(samples, 0.133), np.full(samples, 293.15)])
    z0 = np.array([0.133, 293.15, 0.0])
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    DX, DDX = solver.stencils.derivatives(X, np.zeros(2))
    jac = model.residual_jacobian(X, DX, DDX, data.inputs, theta)
    fac = solver._factorize(*jac)
    G = solver._residual(X, DX, DDX, data.inputs, theta, z0[:2])
    fac.solve(np.ascontiguousarray(G.T).ravel())
    step_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    gth = model.residual_dtheta(X, DX, DDX, data.inputs, theta)[:, [3, 5, 15], :]
    fac.solve(np.transpose(gth, (2, 0, 1)).reshape(-1, 3))
    sens_s = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"samples": samples, "step_s": step_s, "sens_s": sens_s, "grown_mib": (peak - before) / 1024}))


def kernel(sizes: list[int]) -> None:
    print("kernel: one Newton step over the whole record (the model's Jacobian at every point, the banded LU, "
          "a solve) and the sensitivities' solve (3 parameters), each size in its own process")
    print(f"    {'samples':>9s} {'Newton step':>12s} {'µs/sample':>10s} {'sensitivities':>14s} {'memory':>9s} "
          f"{'bytes/sample':>13s}")
    for n in sizes:
        proc = subprocess.run([sys.executable, __file__, "--kernel-child", str(n)], capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"    {n:9d}  failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else '?'}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        print(f"    {n:9d} {r['step_s']:11.3f}s {1e6 * r['step_s'] / n:10.2f} {r['sens_s']:13.3f}s "
              f"{r['grown_mib']:6.0f} MiB {r['grown_mib'] * 2**20 / n:13.0f}")


def scaling(sizes: list[int]) -> None:
    print(f"scaling: one transient fit of experiment j from RUN (2 Hz at {RATE_HZ:g} samples/s), θ4 θ6 θ16 from "
          f"2 % off, each size in its own process (peak RSS includes Python, numpy and the generated record)")
    print(f"    {'samples':>9s} {'rig time':>9s} {'fit':>8s} {'iter':>5s} {'µs/sample':>10s} {'peak RSS':>9s} "
          f"{'fit memory':>11s} {'bytes/sample':>13s}")
    for n in sizes:
        proc = subprocess.run([sys.executable, __file__, "--child", str(n)], capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"    {n:9d}  failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else '?'}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        grown = r["peak_mib"] - r["before_mib"]
        print(f"    {r['samples']:9d} {r['samples'] / RATE_HZ:8.0f}s {r['fit_s']:7.1f}s {r['iterations']:5d} "
              f"{1e6 * r['fit_s'] / r['samples']:10.1f} {r['peak_mib']:7.0f} MiB {grown:7.0f} MiB "
              f"{grown * 2**20 / r['samples']:13.0f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=24)
    ap.add_argument("--workers", type=int, default=2, choices=(1, 2))
    ap.add_argument("--sizes", default="1e4,1e5,1e6", help="record lengths of the scaling run (samples)")
    ap.add_argument("--fit-sizes", default=None, help="record lengths of the whole-fit scaling run (default: --sizes)")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--kernel-child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _scaling_child(args.child)
        return 0
    if args.kernel_child:
        _kernel_child(args.kernel_child)
        return 0
    ok = monte_carlo(args.seeds, args.workers) if args.seeds > 0 else True
    sizes = [int(float(s)) for s in args.sizes.split(",") if s.strip()]
    if sizes:
        kernel(sizes)
    fit_sizes = sizes if args.fit_sizes is None else [int(float(s)) for s in args.fit_sizes.split(",") if s.strip()]
    if fit_sizes:
        scaling(fit_sizes)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
