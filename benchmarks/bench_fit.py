"""Identification speed: the periodic-equilibrium fit against the conventional transient
approach, on the same simulated data (2-dof, standard set, n = 800, theta4/theta6/theta16
from examples/start-2dof.json, 15-40 % off).

Printed side by side:
  * the joint fit of all 14 experiments (target <= 0.3 s) and the whole
    ``python -m identify fit`` process (target <= 1.0 s), with the process's import
    time alone (``-X importtime``) beside it;
  * one periodic solve from the static guess, per experiment (target: median <= 10 ms),
    and the Newton iterations of the same cold solves from the measurements (the start a
    fit uses) beside it; the banded factorisations one joint fit makes;
  * on the subset the transient side can afford (experiment h, 0.5 Hz): our fit against
    solve_ivp (LSODA, hand-written right-hand side) integrated period by period until the
    state repeats, inside scipy.optimize.least_squares (target: >= 100x faster, equal or
    better accuracy).

The machine may be shared: the per-fit figures are taken ``--repeat`` times and their
minimum and median printed, wall time and beside it CPU time (which other jobs' load
inflates less); ``--skip-transient`` leaves out the transient side (minutes).

    python benchmarks/bench_fit.py [--repeat 5] [--skip-transient]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

from _setup import ESTIMATE, START, fit_command, fit_env  # first: one BLAS thread, set before numpy loads

# isort: split
import numpy as np
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares

from identify.dataset import read_dataset
from identify.differentiation import Grid
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.periodic import PeriodicSolver
from identify.plans import STANDARD_SET
from identify.preparation import model_columns, prepare_periodic, resolve_outputs
from identify.start import Measured
from simulator.generate import generate
from simulator.truth import load_truth


def rel_errors(values: dict[str, float], truth: dict[str, float]) -> str:
    return "  ".join(f"{k} {values[k] / truth[k] - 1:+.1e}" for k in ESTIMATE)


def transient_fit(model, data, params) -> tuple[float, dict[str, float], int]:
    """The conventional approach on one experiment: integrate to the periodic steady state
    for every parameter vector least_squares asks for."""
    theta0 = params.vector()
    names = params.names()
    idx = [names.index(k) for k in ESTIMATE]
    period = 1.0 / data.frequency_hz
    n = data.inputs.shape[1]
    tau = np.arange(n + 1) / n
    force = CubicSpline(tau * period, np.append(data.inputs[0], data.inputs[0, 0]), bc_type="periodic")
    sigma = np.sqrt(data.grid_variance)  # channels scaled by their folded measurement noise
    solver = PeriodicSolver(model, Grid(n))
    warm: list[np.ndarray] = []

    def outputs(theta: np.ndarray) -> np.ndarray:
        t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11, t12, _, _, t15, t16, t17 = theta

        def rhs(t, y):
            q, v, T = y
            p = t5 * T / (1 + t6 * q + t7 * T)
            a = (float(force(t % period)) - t11 - t3 * v * abs(v) - t4 * p
                 - (t8 + t9 * p) * math.atan(t10 * v)) / t1 - t2
            return [v, a, (-t16 * (1 + t6 * q) * (T + t17) + (t4 * p + t11) * v) / t15]

        if warm:  # like the periodic solver, start from the last steady state found
            y = warm[-1]
        else:
            x0 = solver.static_equilibrium(data.inputs.mean(axis=1), theta)
            y = np.array([x0[0], 0.0, x0[1]])
        for _ in range(400):  # period by period until the state repeats
            sol = solve_ivp(rhs, (0, period), y, method="LSODA", rtol=1e-8, atol=[1e-10, 1e-8, 1e-7],
                            t_eval=tau * period)
            end = sol.y[:, -1]
            change, y = np.abs(end - y), end
            if change[0] < 1e-8 and change[2] < 1e-5:
                break
        warm[:] = [y]
        q, T = sol.y[0, :-1], sol.y[2, :-1]
        p = t5 * T / (1 + t6 * q + t7 * T)
        return np.vstack([q + t12, p])

    def residuals(x: np.ndarray) -> np.ndarray:
        theta = theta0.copy()
        theta[idx] = x * theta0[idx]
        return ((data.measured - outputs(theta)) / sigma[:, None]).ravel()

    t0 = time.perf_counter()
    res = least_squares(residuals, np.ones(len(idx)), method="trf", x_scale="jac", max_nfev=60)
    elapsed = time.perf_counter() - t0
    return elapsed, {k: res.x[i] * theta0[idx[i]] for i, k in enumerate(ESTIMATE)}, res.nfev


def count_factorisations(run) -> int:
    """How many Newton matrices ``run()`` factorises (every periodic Newton iteration is one)."""
    calls = 0
    original = Grid.factorize

    def counting(self, *args, **kwargs):
        nonlocal calls
        calls += 1
        return original(self, *args, **kwargs)

    Grid.factorize = counting  # type: ignore[method-assign]
    try:
        run()
    finally:
        Grid.factorize = original  # type: ignore[method-assign]
    return calls


def import_seconds(env: dict[str, str]) -> float:
    """What the fit process spends importing identify.cli and everything below it."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", "import identify.cli"], capture_output=True,
                          text=True, env=env)
    line = next(ln for ln in proc.stderr.splitlines() if ln.rstrip().endswith("| identify.cli"))
    return int(line.split("|")[1]) / 1e6


def children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def spread(values: list[float], unit: float = 1.0, digits: int = 2) -> str:
    """Minimum and median of repeated figures, in ``unit`` (1e-3: ms)."""
    return f"min {min(values) / unit:.{digits}f}, median {float(np.median(values)) / unit:.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="times each per-fit figure is taken")
    parser.add_argument("--skip-transient", action="store_true",
                        help="leave out the transient comparison (minutes of solve_ivp)")
    args = parser.parse_args()
    truth = load_truth().theta
    model = load_model("2dof")
    outputs = resolve_outputs(model, None)
    params = Parameters.from_file(model, str(START))
    env = fit_env()
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=1, date="261122")
        ds = read_dataset(tmp, model_columns(model, outputs))
        experiments = [e for e in ds.experiments if e.kind == "periodic"]

        fit_experiments(model, experiments[:1], params, ESTIMATE)  # warm the model cache, as a lab PC would be
        data = prepare_periodic(model, experiments, 800, outputs)
        theta = params.vector()
        factorisations = count_factorisations(lambda: fit_experiments(model, experiments, params, ESTIMATE))
        index = [model.output_index(o) for o in outputs]
        from_measured = sum(PeriodicSolver(model, Grid(800)).solve(
            d.inputs, d.frequency_hz, theta, label=d.label, measured=Measured(index, d.measured)).iterations
            for d in data)
        t_joint, t_process, t_imports, solve_medians = [], [], [], []
        cpu_joint, cpu_process, cpu_solve_medians = [], [], []
        solve_max, iterations = 0.0, []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            joint = fit_experiments(model, experiments, params, ESTIMATE)
            t_joint.append(time.perf_counter() - t0)
            cpu_joint.append(time.process_time() - c0)

            solver = PeriodicSolver(model, Grid(800))
            solve_times, solve_cpu = [], []
            for d in data:
                t0, c0 = time.perf_counter(), time.process_time()
                sol = solver.solve(d.inputs, d.frequency_hz, theta, label=d.label)
                solve_times.append(time.perf_counter() - t0)
                solve_cpu.append(time.process_time() - c0)
                iterations.append(sol.iterations)
            solve_medians.append(float(np.median(solve_times)))
            cpu_solve_medians.append(float(np.median(solve_cpu)))
            solve_max = max(solve_max, *solve_times)

            t0, c0 = time.perf_counter(), children_cpu()
            proc = subprocess.run(fit_command(tmp, os.path.join(tmp, "R.json")), capture_output=True, text=True,
                                  env=env)
            t_process.append(time.perf_counter() - t0)
            cpu_process.append(children_cpu() - c0)
            t_imports.append(import_seconds(env))

        if not args.skip_transient:
            h = [e for e in experiments if e.label.endswith("h")]
            t0 = time.perf_counter()
            ours_h = fit_experiments(model, h, params, ESTIMATE)
            t_ours_h = time.perf_counter() - t0
            t_base, base_values, nfev = transient_fit(model, prepare_periodic(model, h, 800, outputs)[0], params)

    load = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"identification speed, 2-dof, n = 800, theta4/theta6/theta16 from a start 15-40 % off; "
          f"{args.repeat} repeats; {os.cpu_count()} cores, load average {load}")
    print(f"  joint fit, 14 experiments:           {spread(t_joint)} s  ({joint.iterations} iterations; "
          f"target <= 0.3 s by the minimum: {'met' if min(t_joint) <= 0.3 else 'NOT met'})   "
          f"errors: {rel_errors({k: joint.value(k) for k in ESTIMATE}, truth)}")
    print(f"  {'':37s}CPU {spread(cpu_joint)} s")
    print(f"  python -m identify fit (process):     {spread(t_process)} s  (exit {proc.returncode}; "
          f"target <= 1.0 s by the minimum: {'met' if min(t_process) <= 1.0 else 'NOT met'}; of it imports "
          f"{spread(t_imports)} s)")
    print(f"  {'':37s}CPU {spread(cpu_process)} s")
    print(f"  periodic solve from the static guess: median of the 14 {spread(solve_medians, 1e-3, 1)} ms, "
          f"max {1e3 * solve_max:.0f} ms, {min(iterations)}-{max(iterations)} Newton iterations "
          f"(target median <= 10 ms by the minimum: {'met' if min(solve_medians) <= 0.01 else 'NOT met'})")
    print(f"  {'':37s}CPU median of the 14 {spread(cpu_solve_medians, 1e-3, 1)} ms")
    print(f"  the 14 cold solves at the start values: {sum(iterations[:len(data)])} Newton iterations from the static "
          f"guess, {from_measured} from the measurements (a fit's start); one joint fit: {factorisations} banded "
          f"factorisations")
    if args.skip_transient:
        return 0
    print("  subset the transient side can afford: experiment h (0.5 Hz)")
    print(f"    periodic equilibrium + Bayesian Gauss-Newton: {t_ours_h:8.2f} s   "
          f"errors: {rel_errors({k: ours_h.value(k) for k in ESTIMATE}, truth)}")
    print(f"    solve_ivp to steady state + least_squares:   {t_base:8.2f} s   errors: {rel_errors(base_values, truth)}"
          f"   ({nfev} model evaluations)")
    speedup = t_base / t_ours_h
    print(f"    speed-up: {speedup:.0f}x (target >= 100x: {'met' if speedup >= 100 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
