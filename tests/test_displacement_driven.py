"""Issue 33: identify on a damper test as test machines run it, displacement in and
force out, on measured data the project did not generate (tests/data/mr-damper: ten
sinusoidal tests of a small MR damper, 83-119 samples per period, drifting table).

The reference is an independent time-domain fit written here: the Dahl model's state
integrated by scipy's solve_ivp over each whole record (no folding, no periodic grid),
driven by a Savitzky-Golay velocity of the measured displacement, with Kx, Kw and F0
by linear least squares at each ρ and ρ by a bounded scalar search."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import minimize_scalar
from scipy.signal import savgol_filter

from identify.dataset import csv_bytes, read_dataset, write_manifest
from identify.differentiation import Grid
from identify.files import atomic_write_bytes
from identify.folding import fold
from identify.model import load_model
from identify.preparation import choose_points, prepare_periodic
from identify.result import _calibration_line, _with_std
from identify.start import Measured, measured_start

ROOT = Path(__file__).resolve().parents[1]
MR = ROOT / "tests" / "data" / "mr-damper"
DAHL = f"{ROOT / 'identify' / 'models' / 'dahl.py'}:Dahl"
LINEAR = ("Kx", "Kw", "F0")


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


def records() -> list[tuple[str, float, np.ndarray, np.ndarray, np.ndarray]]:
    manifest = json.loads((MR / "dataset.json").read_text())
    out = []
    for e in manifest["experiments"]:
        frame = pd.read_csv(MR / e["file"])
        t = frame["time_s"].to_numpy()
        x = frame["displacement_mm"].to_numpy() * 1e-3
        v = savgol_filter(x, 11, 3, deriv=1, delta=t[1] - t[0])
        out.append((e["label"], float(e["frequency_Hz"]), t, v, frame["force_N"].to_numpy()))
    return out


def dahl_state(rho: float, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """w(t) of the Dahl model from rest, solve_ivp over the whole record."""
    def rate(s: float, y: np.ndarray) -> np.ndarray:
        vs = np.interp(s, t, v)
        return rho * (vs - abs(vs) * y)

    return solve_ivp(rate, (t[0], t[-1]), [0.0], t_eval=t, method="LSODA", max_step=t[1] - t[0], rtol=1e-6,
                     atol=1e-9).y[0]


def reference(chosen: list) -> dict[str, float]:
    """Time-domain least squares over whole records (the first period left out: w starts at 0)."""

    def linear(rho: float) -> tuple[np.ndarray, float]:
        A, b = [], []
        for _, f, t, v, force in chosen:
            w = dahl_state(rho, t, v)
            keep = t >= 1.0 / f
            A.append(np.column_stack([v, w, np.ones_like(v)])[keep])
            b.append(force[keep])
        A_, b_ = np.vstack(A), np.concatenate(b)
        c = np.linalg.lstsq(A_, b_, rcond=None)[0]
        return c, float(np.sum((A_ @ c - b_) ** 2))

    best = minimize_scalar(lambda lr: linear(np.exp(lr))[1], bounds=(np.log(1e3), np.log(2e5)), method="bounded",
                           options={"xatol": 1e-3})
    c = linear(float(np.exp(best.x)))[0]
    return {"Kx": c[0], "Kw": c[1], "F0": c[2], "rho": float(np.exp(best.x))}


@pytest.fixture(scope="module")
def joint_reference() -> dict[str, float]:
    return reference(records())


@pytest.fixture(scope="module")
def per_record() -> dict[str, dict[str, float]]:
    return {rec[0]: reference([rec]) for rec in records()}


@pytest.fixture(scope="module")
def fits(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("dahl")
    (folder / "START.json").write_text(json.dumps({"model": "dahl", "parameters": {}}))
    out = {}
    for name, extra in (("joint", []), ("per", ["--per-experiment"]), ("spectral", ["--scheme", "spectral"])):
        proc = identify("fit", str(MR), "--model", DAHL, "--params", str(folder / "START.json"), "--estimate",
                        "Kx,Kw,rho,F0", "--output", str(folder / f"{name}.json"), *extra)
        out[name] = (proc, json.loads((folder / f"{name}.json").read_text()) if proc.returncode in (0, 1) else None)
    return out


def quoted_std(p: dict) -> float:
    return p.get("std_residual") or p["std"]


@pytest.mark.slow
def test_a_displacement_driven_dahl_fit_with_all_defaults_agrees_with_a_time_domain_fit(fits, joint_reference):
    proc, doc = fits["joint"]
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert doc["converged"] and doc["scheme"] == "bdf2" and doc["n"] == 83
    assert "n = 83, the fewest samples per period of the records (83.1, in e10)" in " ".join(proc.stderr.split())
    assert any("the mean of displacement_mm drifts within records (by e01 0.18, e02 0.96" in w and "e09 1.4" in w
               for w in doc["warnings"]), doc["warnings"]
    ref = joint_reference
    for name in LINEAR:
        p = doc["parameters"][name]
        assert abs(p["value"] - ref[name]) <= 3 * quoted_std(p), (name, p, ref)
    rho = doc["parameters"]["rho"]
    assert abs(np.log(rho["value"] / ref["rho"])) <= 3 * quoted_std(rho) / rho["value"], (rho, ref)


@pytest.mark.slow
def test_the_spectral_displacement_driven_fit_agrees_too(fits, joint_reference):
    proc, doc = fits["spectral"]
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert doc["n"] == 83 and doc["oversample"] == 4
    ref = joint_reference
    for name in (*LINEAR, "rho"):
        p = doc["parameters"][name]
        assert abs(p["value"] - ref[name]) <= 3 * quoted_std(p), (name, p, ref)


@pytest.mark.slow
def test_every_converged_per_record_fit_agrees_with_its_own_reference(fits, per_record):
    proc, doc = fits["per"]
    assert proc.returncode == 0, proc.stderr + proc.stdout
    for label, ref in per_record.items():
        fit = doc["per_experiment"][label]
        if not fit["converged"]:
            continue
        # On these records every one agrees (0.0-1.7 σ): the fallback, a warning naming
        # the cause, is not needed, so it is not accepted here either.
        off = [name for name in (*LINEAR, "rho")
               if abs(fit["parameters"][name]["value"] - ref[name]) > 3 * quoted_std(fit["parameters"][name])]
        assert not off, (label, off, fit["parameters"], ref)
        for p in fit["parameters"].values():  # issue 33.4: never below what the noise gives, offsets included
            if p.get("std_residual") is not None:
                assert p["std_residual"] >= p["std"]


def test_drift_is_removed_before_folding_and_named(tmp_path):
    """e09 has 87.0 samples per period and a table creeping by 1.4 mm: folded as
    measured its displacement zig-zags, and the scatter read as input noise."""
    ds = read_dataset(MR, ["displacement_mm", "force_N"], ["e09"])
    exp = ds.experiment("e09")
    folded = fold("e09", exp.time_s, {"displacement_mm": exp.column("displacement_mm")}, exp.frequency_hz, 83)
    assert 1.0 < folded.drift["displacement_mm"] < 2.0
    assert folded.noise_std["displacement_mm"] < 0.1  # mm; 0.4 with the drift folded in
    spectrum = np.abs(np.fft.rfft(folded.values["displacement_mm"]))
    assert spectrum[10:].max() < 1e-3 * spectrum[1]  # no zig-zag left at high harmonics


def test_the_spectral_grid_says_the_records_true_samples_per_period():
    model = load_model(DAHL)
    ds = read_dataset(MR, ["displacement_mm", "force_N"], None)
    n, why = choose_points(model, [ds.experiment(label) for label in ds.labels()], ["force_N"])
    assert n <= 83, why
    assert "the records' samples per period" not in why  # they are 83.1-119.1, not whole


def test_the_measured_start_on_an_oversampled_grid_takes_data_grid_inputs():
    """Issue 33.4's traceback: inputs on the data grid (128) handed to a function on the
    oversampled grid (512) in the measured start."""
    model = load_model(DAHL)
    ds = read_dataset(MR, ["displacement_mm", "force_N"], ["e07"])
    data = prepare_periodic(model, [ds.experiment("e07")], 64, ["force_N"])[0]
    grid = Grid(64, "spectral", oversample=4)
    theta = np.array([800.0, 56.0, 2.0e4, 135.0])
    X = measured_start(model, grid, data.inputs, theta, Measured([0], data.measured))
    assert X.shape == (1, 256) and np.all(np.abs(X) <= 1.5)


@pytest.mark.slow
def test_a_velocity_driven_spectral_fit_with_default_oversampling_agrees_per_record(tmp_path, per_record):
    """Issue 33.3 and 33.4: the user's own velocity column, a model whose output uses the
    input and has a kink, the spectral scheme with its default oversampling (4), per
    record: a traceback (data-grid inputs in the oversampled measured start) before,
    and e07 Kw 93.5 ± 1.5 against 57 with the drifting fold; F0 0.028* against a
    noise-only 0.155."""
    manifest = json.loads((MR / "dataset.json").read_text())
    for e in manifest["experiments"]:
        frame = pd.read_csv(MR / e["file"])
        t = frame["time_s"].to_numpy()
        velocity = savgol_filter(frame["displacement_mm"].to_numpy() * 1e-3, 11, 3, deriv=1, delta=t[1] - t[0])
        atomic_write_bytes(tmp_path / e["file"], csv_bytes({"time_s": t, "velocity_m_s": velocity,
                                                            "force_N": frame["force_N"].to_numpy()}))
    write_manifest(tmp_path, manifest)
    (tmp_path / "dahl_v.py").write_text(
        (ROOT / "identify" / "models" / "dahl.py").read_text()
        .replace('{"x": Channel("displacement_mm", "mm", scale=1e-3)}', '{"v": Channel("velocity_m_s", "m/s")}')
        .replace("s.x_t", "s.v").replace('name = "dahl"', 'name = "dahl-v"'))
    (tmp_path / "START.json").write_text(json.dumps({"model": "dahl-v", "parameters": {}}))
    proc = identify("fit", str(tmp_path), "--model", f"{tmp_path / 'dahl_v.py'}:Dahl", "--scheme", "spectral",
                    "--params", str(tmp_path / "START.json"), "--estimate", "Kx,Kw,rho,F0", "--per-experiment",
                    "--output", str(tmp_path / "R.json"), "--quiet")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    doc = json.loads((tmp_path / "R.json").read_text())
    assert "model solved on 4 x" in proc.stderr
    for label, ref in per_record.items():
        fit = doc["per_experiment"][label]
        assert fit["converged"], label
        off = [name for name in (*LINEAR, "rho")
               if abs(fit["parameters"][name]["value"] - ref[name]) > 3 * quoted_std(fit["parameters"][name])]
        assert not off, (label, off, fit["parameters"], ref)


def test_flat_directions_print_no_meaningless_digits_and_calibration_is_scoped():
    assert _with_std(0.0, 2.8e16) == "0"
    assert "×10" not in _with_std(1.0, 1.0e6)
    assert _with_std(56.1, 2.3) == "56.1 ± 2.3"
    line = _calibration_line("dahl", [0.5, 1.0], ["sigma0"]) or ""   # scoped by model, plan and parameters (#34)
    assert "σ not validated by Monte-Carlo for this fit (model dahl;" in line and "spread/σ" not in line


def test_a_grid_finer_than_the_records_is_refused_for_a_model_taking_input_derivatives(tmp_path):
    """Issue 33.2: bdf2 on 800 points over 83-119 samples per period gave Kw 338 against 56, exit 0."""
    (tmp_path / "START.json").write_text(json.dumps({"model": "dahl", "parameters": {}}))
    proc = identify("fit", str(MR), "--model", DAHL, "--params", str(tmp_path / "START.json"), "--estimate",
                    "Kx,Kw,rho,F0", "--n", "800", "--output", str(tmp_path / "R.json"))
    assert proc.returncode == 2
    errors = proc.stderr.strip().splitlines()
    assert len(errors) == 1 and "n = 800 is finer than the records (83.1 samples per period in e10)" in errors[0]
    assert "--n 83 or fewer" in errors[0] and not (tmp_path / "R.json").exists()


@pytest.mark.parametrize("spec, estimate", [
    ("damper_bouc_wen.py:BoucWenDamper", "c,k,alpha,beta,F0"),
    ("damper_coulomb.py:CoulombDamper", "k,c,Fc,delta,F0"),
])
def test_the_example_displacement_driven_dampers_fit_the_measured_records(tmp_path, spec, estimate):
    name = {"BoucWenDamper": "bouc-wen-damper", "CoulombDamper": "coulomb-damper"}[spec.rpartition(":")[2]]
    (tmp_path / "START.json").write_text(json.dumps({"model": name, "parameters": {}}))
    proc = identify("fit", str(MR), "--model", str(ROOT / "identify" / "models" / spec), "--params",
                    str(tmp_path / "START.json"), "--estimate", estimate, "--experiments", "e01,e05,e10",
                    "--output", str(tmp_path / "R.json"), "--quiet")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "R.json").read_text())
    assert doc["converged"]
    for e in doc["experiments"].values():  # N, of a force swinging over ~250 N: the loop is followed, not a mean
        assert abs(e["channels"]["force_N"]["residual_mean"]) < 10 and e["channels"]["force_N"]["residual_std"] < 15
