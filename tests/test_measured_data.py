"""identify on data it was not built for (issue 28): measured Silverbox records and
independently integrated Bouc-Wen multisines.  No wrong number with exit 0: every path
here either gives the right one or refuses / warns in one line."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from identify.dataset import csv_bytes, read_dataset, write_manifest
from identify.files import atomic_write_bytes
from identify.model import load_model
from identify.preparation import choose_points
from tests import hysteresis_data as bw
from tests.conftest import SILVERBOX

# Start 27 % below the resonance (50 Hz against 68.7 Hz); k3's nominal is 0, so it needs a prior std.
START = {"model": "duffing", "parameters": {"m": 1e-5, "d": 1e-3, "k": 1.0, "k3": {"value": 0.0, "prior_std": 1.0}}}
ESTIMATE = "m,d,k,k3"


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


def one_line(text: str) -> str:
    return " ".join(text.split())


def resonance_hz(parameters: dict) -> float:
    return math.sqrt(parameters["k"]["value"] / parameters["m"]["value"]) / (2 * math.pi)


@pytest.fixture(scope="module")
def joint(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One joint Silverbox fit, as a user would start it: no --scheme, --stability, figures."""
    folder = tmp_path_factory.mktemp("silverbox")
    (folder / "START.json").write_text(json.dumps(START))
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(folder / "START.json"),
                    "--estimate", ESTIMATE, "--output", str(folder / "RESULT.json"), "--figures",
                    str(folder / "figures"), "--stability", "--quiet")
    return folder, proc


@pytest.mark.slow
def test_a_multisine_fitted_without_scheme_is_fitted_spectral_on_the_right_resonance(joint):
    folder, proc = joint
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert "scheme spectral: schroeder1 is broadband (168 excited lines up to harmonic 335)" in one_line(proc.stderr)
    doc = json.loads((folder / "RESULT.json").read_text())
    assert doc["scheme"] == "spectral" and doc["n"] == 1024
    assert 68.0 <= resonance_hz(doc["parameters"]) <= 69.5  # the measured FRF peaks there


@pytest.mark.slow
def test_bdf2_asked_for_on_a_multisine_it_cannot_resolve_is_warned_about(tmp_path):
    start = tmp_path / "START.json"
    start.write_text(json.dumps(START))
    result = tmp_path / "RESULT.json"
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--scheme", "bdf2", "--params", str(start),
                    "--estimate", ESTIMATE, "--output", str(result), "--quiet", "--max-iterations", "1")
    assert "warning: bdf2 on 800 points differentiates the highest excited line of schroeder1" in one_line(proc.stderr)
    assert any("use --scheme spectral" in w for w in json.loads(result.read_text())["warnings"])


@pytest.mark.slow
def test_the_report_states_the_priors_and_the_excited_lines_and_stability_reports_progress(joint):
    folder, proc = joint
    report = one_line(proc.stdout)
    assert "prior std 1 1/V² " in report          # k3's, as given: not "50 %"
    assert "prior std 50 % of its size" in report  # m's, d's, k's default
    # 168 excited odd lines in each of the two records, not the 1024-point grid's 2 x 321 lines with output
    assert "(336 excited frequency lines," in report
    assert "Floquet multipliers of schroeder1 (1 of 2) ..." in proc.stderr
    assert "Floquet multipliers of schroeder2: largest |μ|" in proc.stderr


def test_a_zero_nominal_parameter_without_prior_std_is_refused_in_one_line(tmp_path):
    start = tmp_path / "START.json"
    start.write_text(json.dumps({"model": "duffing", "parameters": {"m": 1e-5, "d": 1e-3, "k": 1.0}}))
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--scheme", "spectral", "--params", str(start),
                    "--estimate", ESTIMATE, "--output", str(tmp_path / "R.json"), "--quiet")
    assert proc.returncode == 2
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "no prior std for k3 (cubic: here" in errors[0] and "prior_std" in errors[0]
    assert not (tmp_path / "R.json").exists()


@pytest.mark.slow
def test_a_restart_from_result_json_keeps_the_priors_and_the_original_start(joint, tmp_path):
    folder, _ = joint
    uninterrupted = json.loads((folder / "RESULT.json").read_text())
    start = tmp_path / "START.json"
    start.write_text(json.dumps(START))
    first = tmp_path / "FIRST.json"
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(start), "--estimate", ESTIMATE,
                    "--output", str(first), "--quiet", "--max-iterations", "6")
    assert proc.returncode == 1, proc.stderr
    stopped = json.loads(first.read_text())
    assert stopped["parameters"]["k3"]["prior_std"] == 1.0 and stopped["parameters"]["k3"]["initial"] == 0.0
    final = tmp_path / "FINAL.json"
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(first), "--estimate", ESTIMATE,
                    "--output", str(final), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "scheme spectral, n = 1024, oversample 1: the fit's, from" in one_line(proc.stderr)
    restarted = json.loads(final.read_text())
    for name in ESTIMATE.split(","):
        p, q = restarted["parameters"][name], uninterrupted["parameters"][name]
        assert abs(p["value"] - q["value"]) <= 0.1 * q["std"], (name, p, q)
    assert "(init = 1e-05)" in proc.stdout and "(init = 0)" in proc.stdout  # the original start, not the restart's


@pytest.mark.slow
def test_a_per_experiment_result_is_refused_as_one_set_and_read_per_label(tmp_path):
    start = tmp_path / "START.json"
    start.write_text(json.dumps(START))
    result = tmp_path / "RESULT.json"
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(start), "--estimate", ESTIMATE,
                    "--output", str(result), "--quiet", "--per-experiment", "--figures", str(tmp_path / "figures"),
                    "--report", str(tmp_path / "report.txt"))
    assert proc.returncode == 0, proc.stderr
    # stdout is a pipe here: the table is widened, no number cut (rich cut them to `-5.16528…` at 80 columns)
    assert "…" not in proc.stdout and "(5.374" in proc.stdout and "k3 [1/V²]" in proc.stdout
    for label in ("schroeder1", "schroeder2"):
        assert {p.name for p in (tmp_path / "figures" / label).iterdir()} == {"fit_output.png", "frf_output.png",
                                                                            "residuals.png"}
        assert f"=== experiment {label} ===" in (tmp_path / "report.txt").read_text()

    prediction = tmp_path / "prediction.csv"
    for params in (str(result), f"{result}#nowhere"):
        proc = identify("predict", str(SILVERBOX), "--model", "duffing", "--params", params, "--experiment",
                        "schroeder2", "--output", str(prediction))
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert "schroeder1, schroeder2" in proc.stderr and not prediction.exists()
    proc = identify("fit", str(SILVERBOX), "--model", "duffing", "--params", str(result), "--estimate", ESTIMATE,
                    "--output", str(tmp_path / "R2.json"))
    assert proc.returncode == 2 and "a --per-experiment result" in proc.stderr

    proc = identify("predict", str(SILVERBOX), "--model", "duffing", "--params", f"{result}#schroeder1",
                    "--experiment", "schroeder2", "--output", str(prediction))
    assert proc.returncode == 0, proc.stderr
    assert "scheme spectral, n = 1024, oversample 1: the fit's" in one_line(proc.stderr)
    predicted = pd.read_csv(prediction)["output"].to_numpy()
    measured = pd.read_csv(SILVERBOX / "schroeder2.csv")["output"].to_numpy()
    error = np.sqrt(np.mean((predicted - measured) ** 2) / np.mean(measured**2))
    assert error < 0.01, error  # one repeat's fit predicts the other to its model error


@pytest.mark.slow
def test_predict_takes_the_fits_scheme_n_and_oversample_from_result_json(tmp_path):
    """Issue 27 point 4: a spectral Bouc-Wen fit predicted on bdf2's default 800 points was
    95 % off without a word."""
    data = bw.write_dataset(tmp_path / "other", phase_seed=2, noise=0.0, samples=1024)
    result = tmp_path / "RESULT.json"
    result.write_text(json.dumps({"model": "bouc-wen", "converged": True, "scheme": "spectral", "n": 1024,
                                  "oversample": 4, "parameters": {k: {"value": v, "estimated": True}
                                                                  for k, v in bw.TRUTH.items()}}))
    measured = pd.read_csv(data / "bw.csv")["displacement_mm"].to_numpy()

    def error(*options: str) -> tuple[float, str]:
        out = tmp_path / "prediction.csv"
        proc = identify("predict", str(data), "--model", "bouc-wen", "--params", str(result), "--experiment", "bw",
                        "--output", str(out), *options)
        assert proc.returncode == 0, proc.stderr
        predicted = pd.read_csv(out)["displacement_mm"].to_numpy()
        return float(np.sqrt(np.mean((predicted - measured) ** 2) / np.mean(measured**2))), one_line(proc.stderr)

    inherited, said = error()
    assert "scheme spectral, n = 1024, oversample 4: the fit's, from" in said
    assert inherited < 0.01, inherited
    told, said = error("--scheme", "bdf2", "--n", "800")  # told otherwise: obeyed, and warned about
    assert told > 0.1 and "warning: bdf2 on 800 points differentiates" in said


def test_the_automatic_grid_is_never_finer_than_the_records_samples(tmp_path):
    """Every other Silverbox sample: 512 per period, output with content up to the new
    Nyquist line, where 2 x 1.25 x the highest harmonic would ask for 1024 points."""
    frame = pd.read_csv(SILVERBOX / "schroeder1.csv").iloc[::2]
    atomic_write_bytes(tmp_path / "half.csv", csv_bytes({c: frame[c].to_numpy() for c in frame.columns}))
    manifest = json.loads((SILVERBOX / "dataset.json").read_text())
    experiment = dict(manifest["experiments"][0], file="half.csv", samples_per_period=512,
                      sample_rate_Hz=manifest["experiments"][0]["sample_rate_Hz"] / 2)
    write_manifest(tmp_path, {**manifest, "experiments": [experiment]})
    model = load_model("duffing")
    ds = read_dataset(tmp_path, ["input", "output"], ["schroeder1"])
    n, why = choose_points(model, ds.select(["schroeder1"]), ["output"])
    assert n == 512
    assert "the records' samples per period: 2 x 1.25 x the highest harmonic with signal" in why
    assert "would ask for 1024, more points than were sampled" in why
