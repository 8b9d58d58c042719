"""Transient fits (issue 36): the model over a whole record from a fitted initial state.

The numerics are checked against an independent integrator (scipy's solve_ivp) and
against their own finite differences; the fit on records the simulator made from rest
(its streaming plant: another discretisation, an actuator, quantised sensors), on
steady-state records beside the periodic fit, and on the measured Silverbox records.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from identify.model import compile_model
from identify.models.duffing import Duffing
from identify.start import Measured
from identify.trajectory import (
    Stencils,
    TrajectorySolver,
    TransientData,
    Unfolded,
    refinement,
    white_noise_std,
)
from tests.conftest import SILVERBOX
from tests.test_fit import assert_silverbox_oscillator

ESTIMATE = "theta4,theta6,theta16"
TRUTH = {"theta4": 5.0e-3, "theta6": -3.0, "theta16": 0.85}


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


def generate(out, capture: str, periods: int, letters: str = "j,n", seed: int = 0) -> None:
    proc = subprocess.run([sys.executable, "-m", "simulator", "generate", "--experiments", letters, "--periods",
                           str(periods), "--capture", capture, "--ramp", "0.5", "--seed", str(seed), "--date", "261126",
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


# --------------------------------------------------------------------------------------
# Numerics


def test_stencils_are_exact_for_quadratics_from_the_first_point_and_their_transpose_is_exact():
    h, n = 0.01, 40
    t = np.arange(n) * h
    x = 1 + 2 * t + 3 * t**2
    st = Stencils((2, 1), h, n)
    d1, d2 = st.derivatives(np.vstack([x, x]), np.array([2.0, 0.0]))
    assert np.max(np.abs(d1[0] - (2 + 6 * t))) < 1e-10 and np.max(np.abs(d2[0] - 6)) < 1e-8
    # A first-order state starts with one backward Euler step, BDF2 from the second on.
    assert abs(d1[1, 1] - (x[1] - x[0]) / h) < 1e-10 and np.max(np.abs(d1[1, 2:] - (2 + 6 * t[2:]))) < 1e-10
    rng = np.random.default_rng(1)
    w1, w2, y = rng.standard_normal((3, 2, n))
    a1, a2 = st.derivatives(y, np.zeros(2))
    assert np.sum(a1 * w1 + a2 * w2) == pytest.approx(np.sum(y * st.derivatives_transposed(w1, w2)), rel=1e-12)


def test_refinement_interpolates_quadratics_exactly_inside_the_record():
    n, k = 30, 4
    s = np.arange(n, dtype=float)
    fine = np.arange((n - 1) * k + 1) / k
    R = refinement(n, k)
    assert np.max(np.abs(R @ (s**2 - 3 * s) - (fine**2 - 3 * fine))[k:-k]) < 1e-9
    assert np.allclose(R @ np.ones(n), 1.0)


def test_white_noise_from_differences_ignores_a_smooth_signal_and_sparse_jumps():
    rng = np.random.default_rng(3)
    t = np.arange(20000) / 2000.0
    signal = 100 * np.sin(2 * np.pi * 2 * t) + 150 * np.sign(np.cos(2 * np.pi * 2 * t))  # friction-like jumps
    assert white_noise_std(signal + 2.0 * rng.standard_normal(t.size)) == pytest.approx(2.0, rel=0.05)


def _oscillator(oversample: int):
    """A lightly damped linear oscillator released off rest under a sine force, the
    record integrated by solve_ivp to 1e-10 (not by the scheme under test)."""
    model = compile_model(Duffing)
    theta = np.array([1e-5, 1e-3, 1.0, 0.0, 0.0])
    fs, n = 2000.0, 3000
    t = np.arange(n) / fs
    u = 0.1 * np.sin(2 * np.pi * 30 * t)
    ref = solve_ivp(lambda s, y: [y[1], (0.1 * np.sin(2 * np.pi * 30 * s) - theta[1] * y[1] - theta[2] * y[0])
                                  / theta[0]], (0, t[-1]), [0.01, 0.0], t_eval=t, rtol=1e-10, atol=1e-12).y[0]
    data = TransientData("osc", 30.0, 1 / fs, u[None], ref[None], np.array([1e-10]), np.array([1e-8]), Unfolded(n),
                         oversample)
    return model, theta, data, ref


def test_the_record_solution_converges_at_second_order_to_an_independent_integration():
    errors = []
    for oversample in (2, 4):
        model, theta, data, ref = _oscillator(oversample)
        solver = TrajectorySolver(model, data, [0])
        sol = solver.solve(data.inputs, 30.0, theta, label="osc", measured=Measured([0], data.measured))
        errors.append(np.max(np.abs(solver.outputs(sol, theta, [0])[0] - ref)) / np.max(np.abs(ref)))
        initial = sol.initial
    # The initial state is fitted: the release point and velocity come back (to the
    # scheme's error, which the fitted initial state absorbs in part).
    assert initial[0] == pytest.approx(0.01, rel=0.05) and abs(initial[1]) < 0.05 * 0.01 * 314
    assert errors[1] < 0.005
    assert 3.0 < errors[0] / errors[1] < 5.0  # second order: halving the step quarters the error


def test_sensitivities_are_the_refitted_outputs_derivatives_and_the_adjoint_is_the_transpose():
    model, theta, data, _ = _oscillator(4)
    solver = TrajectorySolver(model, data, [0])
    measured = Measured([0], data.measured)
    sol = solver.solve(data.inputs, 30.0, theta, label="osc", measured=measured)
    y = solver.outputs(sol, theta, [0])[0]
    _, dY = solver.sensitivities(sol, theta, [1, 2], [0])
    for col, j in enumerate((1, 2)):
        moved = theta.copy()
        moved[j] *= 1 + 1e-5
        other = TrajectorySolver(model, data, [0])  # cold: its own initial-state fit
        y2 = other.outputs(other.solve(data.inputs, 30.0, moved, label="osc", measured=measured), moved, [0])[0]
        fd = (y2 - y) / (moved[j] - theta[j])
        assert np.max(np.abs(fd - dY[0, :, col])) < 0.01 * np.max(np.abs(fd))
    rng = np.random.default_rng(5)
    du, w = rng.standard_normal((2, 1, data.inputs.shape[1], 3))
    forward = solver.input_response(sol, theta, [0], du)
    assert np.sum(forward * w) == pytest.approx(np.sum(solver.input_adjoint(sol, theta, [0], w) * du), rel=1e-9)


# --------------------------------------------------------------------------------------
# Fits


def _fit(folder, *extra: str) -> dict:
    out = folder / f"R{len(list(folder.glob('R*.json')))}.json"
    proc = identify("fit", str(folder), "--estimate", ESTIMATE, "--output", str(out), "--quiet", *extra)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    return {"doc": json.loads(out.read_text()), "stdout": proc.stdout, "stderr": proc.stderr}


@pytest.mark.slow
def test_a_record_from_run_on_is_fitted_as_transient_because_the_dataset_says_so(tmp_path):
    generate(tmp_path, "transient", periods=6)
    manifest = json.loads((tmp_path / "dataset.json").read_text())
    assert all(e["capture"] == "transient" for e in manifest["experiments"])
    fit = _fit(tmp_path)
    assert "fitted as transient records" in fit["stderr"]
    doc = fit["doc"]
    assert doc["converged"] is True
    assert {e["capture"] for e in doc["experiments"].values()} == {"transient"}
    for name, truth in TRUTH.items():
        p = doc["parameters"][name]
        assert abs(p["value"] - truth) < 3 * p["std"], (name, p, truth)
    assert doc["parameters"]["theta16"]["std"] < 0.2 * TRUTH["theta16"]  # the transient carries the heat transfer


@pytest.mark.slow
def test_transient_and_periodic_fits_of_the_same_steady_state_records_agree_within_their_sigma(tmp_path):
    generate(tmp_path, "steady", periods=3)
    periodic = _fit(tmp_path)["doc"]
    transient = _fit(tmp_path, "--capture", "transient")["doc"]
    assert "capture" not in next(iter(periodic["experiments"].values()))
    assert {e["capture"] for e in transient["experiments"].values()} == {"transient"}
    for name in TRUTH:
        p, t = periodic["parameters"][name], transient["parameters"][name]
        combined = math.hypot(p["std"], t["std"])
        assert abs(p["value"] - t["value"]) < 2 * combined, (name, p, t)
        # The transient fit does not assume periodicity (its initial gas temperature is
        # free), so it knows at most a little less; never orders of magnitude.
        assert 0.5 < t["std"] / p["std"] < 10, (name, p, t)


@pytest.mark.slow
def test_measured_silverbox_records_fitted_as_transients_give_the_periodic_fits_oscillator(tmp_path):
    start = tmp_path / "start.json"
    start.write_text(json.dumps({"model": "duffing", "parameters": {"m": 1e-5, "d": 1e-3, "k": 1.0, "k3": 1.0,
                                                                    "k2": {"value": 0.0, "prior_std": 1.0}}}))
    out = tmp_path / "R.json"
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(start), "--estimate", "m,d,k,k2,k3",
                    "--experiments", "schroeder1", "--capture", "transient", "--transient-oversample", "8",
                    "--output", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr + proc.stdout
    doc = json.loads(out.read_text())
    assert_silverbox_oscillator(doc)   # the ranges of the periodic (spectral) fit
    assert doc["experiments"]["schroeder1"]["capture"] == "transient"


def test_a_record_with_lost_samples_is_refused_as_a_transient_in_one_line(tmp_path):
    generate(tmp_path, "transient", periods=2, letters="j")
    csv = next(tmp_path.glob("*.csv"))
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(lines[:100] + lines[101:]) + "\n")
    manifest = json.loads((tmp_path / "dataset.json").read_text())
    manifest["experiments"][0]["lost_samples"] = 1
    (tmp_path / "dataset.json").write_text(json.dumps(manifest))
    proc = identify("fit", str(tmp_path), "--estimate", ESTIMATE, "--output", str(tmp_path / "R.json"), "--quiet")
    assert proc.returncode == 2, proc.stderr
    assert "lost samples: a transient fit needs every sample" in proc.stderr
    assert "Traceback" not in proc.stderr
