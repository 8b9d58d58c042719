"""The spectral scheme at scale: dense LU against matrix-free Newton–Krylov, side by side.

Bouc-Wen oscillator (identify/models/bouc_wen.py, 2 states), random-phase multisine
5-150 Hz, 50 N RMS, 750 Hz, n samples per period for n = 1024, 4096, 8192 (made by
tests/hysteresis_data.py), model solved on the data's n points (no oversampling) so
that both solvers solve the same equations.  Printed per n:

  * one periodic solve: Newton from the transient start to convergence (the same start
    for both), and its Newton iterations;
  * one fit of all six parameters from a start 15-20 % off (1 % output noise);
  * the matrix-free fit's GMRES solves and their mean iterations.

A dense LU of 2·n unknowns costs O(n³) time and O(n²) memory (2 GB at n = 8192): beyond
``--dense-max`` (default 1024) its times are extrapolated as (2n)³ from LUs measured at
n = 512 and 1024, times the factorisations the matrix-free run made, and marked "~".
Last, the acceptance case: n = 8192 with the default 4x model grid (target <= 60 s).
On a loaded machine BLAS threads stall the dense LU (and only it) by up to 5x;
OMP_NUM_THREADS=1 gives steadier dense figures.

    python benchmarks/bench_spectral.py [--dense-max 8192]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from identify import spectral  # noqa: E402
from identify.dataset import read_dataset  # noqa: E402
from identify.differentiation import Grid  # noqa: E402
from identify.fit import fit_experiments  # noqa: E402
from identify.model import CompiledModel, load_model  # noqa: E402
from identify.parameters import Parameters  # noqa: E402
from identify.periodic import PeriodicSolver  # noqa: E402
from identify.preparation import prepare_periodic  # noqa: E402
from identify.spectral import gmres  # noqa: E402
from identify.start import transient_start  # noqa: E402
from tests import hysteresis_data  # noqa: E402

SIZES = (1024, 4096, 8192)
START = {"m": 2.3, "c": 8.0, "k": 6.0e4, "alpha": 4.2e4, "beta_gamma": 950.0, "beta_delta": -900.0}
COLUMNS = ["force_N", "displacement_mm"]


class GmresCount:
    """identify.spectral.gmres, keeping every solve's iteration count."""

    def __init__(self) -> None:
        self.iterations: list[int] = []

    def __call__(self, *args: Any, **kwargs: Any) -> tuple[np.ndarray, int]:
        x, count = gmres(*args, **kwargs)
        self.iterations.append(count)
        return x, count


def dense_lu_seconds(model: CompiledModel, n: int, u: np.ndarray, f: float, theta: np.ndarray,
                     start: np.ndarray) -> float:
    """One dense factorisation of the Newton matrix at the start (median of 3)."""
    grid = Grid(n, "spectral", "dense")
    DX, DDX = grid.derivatives(start, f)
    jac = model.residual_jacobian(start, DX, DDX, u, theta)
    grid.factorize(*jac, f)  # builds the dense D1, D2 once
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        grid.factorize(*jac, f)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dense-max", type=int, default=1024, help="largest n run densely (beyond: extrapolated)")
    args = parser.parse_args()
    model = load_model("bouc-wen")
    theta = model.nominal_vector()
    params = Parameters.from_document(model, {"model": "bouc-wen", "parameters": START})
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        lu: dict[int, float] = {}
        for n in SIZES:
            folder = hysteresis_data.write_dataset(Path(tmp) / str(n), samples=n)
            experiments = read_dataset(folder, COLUMNS).experiments
            data = prepare_periodic(model, experiments, n, ["displacement_mm"])[0]
            u, f = data.inputs, data.frequency_hz
            start = transient_start(model, Grid(n, "spectral"), u, f, theta, np.zeros(2))
            row: dict[str, object] = {"n": n}
            for solver in ("krylov", "dense"):
                if solver == "dense" and n > args.dense_max:
                    continue
                t0 = time.perf_counter()
                sol = PeriodicSolver(model, Grid(n, "spectral", solver)).solve(u, f, theta, start=start)
                row[f"{solver} solve"] = time.perf_counter() - t0
                row["newton"] = sol.iterations
                counted = GmresCount()
                # Each factorize is a dense LU, or a preconditioner for the matrix-free solves.
                with mock.patch.object(Grid, "factorize", autospec=True, side_effect=Grid.factorize) as factorize, \
                        mock.patch.object(spectral, "gmres", counted):
                    t0 = time.perf_counter()
                    fit = fit_experiments(model, experiments, params, list(START), n=n, scheme="spectral",
                                          oversample=1, linear_solver=solver)
                    row[f"{solver} fit"] = time.perf_counter() - t0
                row[f"{solver} factorisations"] = factorize.call_count
                if counted.iterations:
                    row["gmres"] = f"{len(counted.iterations)} x {np.mean(counted.iterations):.0f}"
                row[f"{solver} converged"] = fit.converged
            if n <= 1024:
                for m in (n // 2, n):
                    lu[m] = dense_lu_seconds(model, m, data.inputs if m == n else data.inputs[:, ::2], f, theta,
                                             start if m == n else start[:, ::2])
            rows.append(row)
        # t_LU(n) ~ c·n³, c from the two measured sizes (geometric mean)
        c = float(np.sqrt(np.prod([t / m**3 for m, t in lu.items()])))
        for row in rows:
            n = int(row["n"])  # type: ignore[call-overload]
            if "dense solve" not in row:
                row["dense solve"] = f"~{int(row['newton']) * c * n**3:.0f}"  # type: ignore[call-overload]
                row["dense fit"] = f"~{int(row['krylov factorisations']) * c * n**3:.0f}"  # type: ignore[call-overload]

        folder = hysteresis_data.write_dataset(Path(tmp) / "acceptance")
        t0 = time.perf_counter()
        acceptance = fit_experiments(model, read_dataset(folder, COLUMNS).experiments, params, list(START), n=None,
                                     scheme="spectral", oversample=None)
        t_acceptance = time.perf_counter() - t0

    def cell(value: object) -> str:
        return f"{value:8.2f}" if isinstance(value, float) else f"{value!s:>8}"

    print("spectral scheme, Bouc-Wen (2 states), multisine 5-150 Hz at 750 Hz; seconds (~: extrapolated O(n^3))")
    print(f"{'n':>6} {'unknowns':>9} | {'periodic solve':^19} | {'fit (6 parameters)':^19} | {'Newton':>6} "
          f"{'GMRES in the fit':>16}")
    print(f"{'':>6} {'':>9} | {'dense':>8} {'krylov':>8}  | {'dense':>8} {'krylov':>8}  |")
    for row in rows:
        n = int(row["n"])  # type: ignore[call-overload]
        print(f"{n:6d} {2 * n:9d} | {cell(row['dense solve'])} {cell(row['krylov solve'])}  | "
              f"{cell(row['dense fit'])} {cell(row['krylov fit'])}  | {row['newton']!s:>6} "
              f"{row['gmres']!s:>16} solves x iterations")
    print("dense LU measured: " + ", ".join(f"n = {m}: {t:.3f} s" for m, t in sorted(lu.items())))
    print(f"acceptance: n = {acceptance.n_grid}, model on {acceptance.n_grid * acceptance.oversample} points, "
          f"fit {t_acceptance:.1f} s (target <= 60 s: {'met' if t_acceptance <= 60 else 'NOT met'}), "
          f"{acceptance.iterations} iterations, converged {acceptance.converged}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
