"""Identification speed: the periodic-equilibrium fit against the conventional transient
approach, on the same simulated data (2-dof, standard set, n = 800, theta4/theta6/theta16
from examples/start-2dof.json, 15-40 % off).

Printed side by side:
  * the joint fit of all 14 experiments (target <= 0.3 s) and the whole
    ``python -m identify fit`` process (target <= 1.0 s), with the process's import
    time alone (``-X importtime``) beside it;
  * one periodic solve from the static guess, per experiment (target: median <= 10 ms);
  * on the subset the transient side can afford (experiment h, 0.5 Hz): our fit against
    solve_ivp (LSODA, hand-written right-hand side) integrated period by period until the
    state repeats, inside scipy.optimize.least_squares (target: >= 100x faster, equal or
    better accuracy).

    python benchmarks/bench_fit.py
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# One BLAS thread, set before numpy loads OpenBLAS: what `python -m identify` and Dask's
# workers use, so that the in-process figures measure the same code the same way.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.interpolate import CubicSpline  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from identify.dataset import read_dataset  # noqa: E402
from identify.differentiation import Grid  # noqa: E402
from identify.fit import fit_experiments  # noqa: E402
from identify.model import load_model  # noqa: E402
from identify.parameters import Parameters  # noqa: E402
from identify.periodic import PeriodicSolver  # noqa: E402
from identify.plans import STANDARD_SET  # noqa: E402
from identify.preparation import model_columns, prepare_periodic, resolve_outputs  # noqa: E402
from simulator.generate import generate  # noqa: E402
from simulator.truth import load_truth  # noqa: E402

ESTIMATE = ["theta4", "theta6", "theta16"]
START = ROOT / "examples" / "start-2dof.json"


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


def import_seconds(env: dict[str, str]) -> float:
    """What the fit process spends importing identify.cli and everything below it."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", "import identify.cli"], capture_output=True,
                          text=True, env=env)
    line = next(ln for ln in proc.stderr.splitlines() if ln.rstrip().endswith("| identify.cli"))
    return int(line.split("|")[1]) / 1e6


def main() -> int:
    truth = load_truth().theta
    model = load_model("2dof")
    outputs = resolve_outputs(model, None)
    params = Parameters.from_file(model, str(START))
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=1, date="261122")
        ds = read_dataset(tmp, model_columns(model, outputs))
        experiments = [e for e in ds.experiments if e.kind == "periodic"]

        fit_experiments(model, experiments[:1], params, ESTIMATE)  # warm the model cache, as a lab PC would be
        t0 = time.perf_counter()
        joint = fit_experiments(model, experiments, params, ESTIMATE)
        t_joint = time.perf_counter() - t0

        data = prepare_periodic(model, experiments, 800, outputs)
        solver = PeriodicSolver(model, Grid(800))
        theta = params.vector()
        solve_times, iterations = [], []
        for d in data:
            t0 = time.perf_counter()
            sol = solver.solve(d.inputs, d.frequency_hz, theta, label=d.label)
            solve_times.append(time.perf_counter() - t0)
            iterations.append(sol.iterations)

        env = dict(os.environ, PYTHONPATH=str(ROOT))
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "identify", "fit", tmp, "--params", str(START), "--estimate",
                               ",".join(ESTIMATE), "--output", os.path.join(tmp, "R.json"), "--quiet"],
                              capture_output=True, text=True, env=env)
        t_process = time.perf_counter() - t0
        t_imports = import_seconds(env)

        h = [e for e in experiments if e.label.endswith("h")]
        t0 = time.perf_counter()
        ours_h = fit_experiments(model, h, params, ESTIMATE)
        t_ours_h = time.perf_counter() - t0
        t_base, base_values, nfev = transient_fit(model, prepare_periodic(model, h, 800, outputs)[0], params)

    print("identification speed, 2-dof, n = 800, theta4/theta6/theta16 from a start 15-40 % off")
    print(f"  joint fit, 14 experiments:           {t_joint:7.2f} s  ({joint.iterations} iterations; target <= 0.3 s: "
          f"{'met' if t_joint <= 0.3 else 'NOT met'})   "
          f"errors: {rel_errors({k: joint.value(k) for k in ESTIMATE}, truth)}")
    print(f"  python -m identify fit (process):     {t_process:7.2f} s  (exit {proc.returncode}; target <= 1.0 s: "
          f"{'met' if t_process <= 1.0 else 'NOT met'}; of it imports {t_imports:.2f} s)")
    median = float(np.median(solve_times))
    print(f"  periodic solve from the static guess: median {1e3 * median:.1f} ms, max "
          f"{1e3 * max(solve_times):.0f} ms, {min(iterations)}-{max(iterations)} Newton iterations "
          f"(target median <= 10 ms: {'met' if median <= 0.01 else 'NOT met'})")
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
