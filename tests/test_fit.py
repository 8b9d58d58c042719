"""Identification end to end: simulated 2-dof data with known truth, and real Silverbox data."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SILVERBOX

TRUTH = {"theta4": 5.0e-3, "theta6": -3.0, "theta16": 0.85}


@pytest.mark.slow
def test_recovers_theta4_theta6_theta16_from_a_start_15_to_40_percent_off(standard_dataset, tmp_path):
    start = tmp_path / "start.json"
    start.write_text(json.dumps({"model": "2dof", "parameters": {"theta4": 5.0e-3 * 1.15, "theta6": -3.0 * 0.6,
                                                                  "heat_transfer": 0.85 * 1.4}}))
    result = tmp_path / "result.json"
    proc = subprocess.run([sys.executable, "-m", "identify", "fit", str(standard_dataset), "--model", "2dof",
                           "--params", str(start), "--estimate", "theta4,theta6,theta16", "--output", str(result),
                           "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    doc = json.loads(result.read_text())
    assert doc["converged"] is True
    for key in ("model", "iterations", "parameters", "correlation", "channels", "experiments"):
        assert key in doc
    p = doc["parameters"]
    assert abs(p["theta4"]["value"] / TRUTH["theta4"] - 1) < 1e-3
    assert abs(p["theta6"]["value"] / TRUTH["theta6"] - 1) < 1e-3
    assert abs(p["theta16"]["value"] / TRUTH["theta16"] - 1) < 1e-2
    assert p["theta1"]["std"] is None and p["theta1"]["estimated"] is False
    assert len(doc["experiments"]) == 14
    for e in doc["experiments"].values():
        assert set(e) >= {"residual_mean", "residual_std"}


@pytest.mark.slow
def test_predict_writes_the_model_columns_on_the_record_time_base(standard_dataset, tmp_path):
    import pandas as pd

    out = tmp_path / "pred.csv"
    proc = subprocess.run([sys.executable, "-m", "identify", "predict", str(standard_dataset), "--model", "2dof",
                           "--experiment", "h", "--output", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    pred = pd.read_csv(out)
    meas = pd.read_csv(standard_dataset / "261122h.csv")
    assert list(pred.columns[:1]) == ["time_s"]
    assert {"stroke_mm", "force_N", "pressure_bar", "gas_temperature_C"} <= set(pred.columns)
    assert len(pred) == len(meas)
    # With the true parameters the prediction follows the measurement to within ~noise.
    assert (pred["stroke_mm"] - meas["stroke_mm"]).abs().max() < 0.1
    assert (pred["pressure_bar"] - meas["pressure_bar"]).abs().max() < 0.02


@pytest.mark.slow
def test_silverbox_duffing_spectral(tmp_path):
    start = tmp_path / "start.json"
    start.write_text(json.dumps({"model": "duffing", "parameters": {"m": 1e-5, "d": 1e-3, "k": 1.0, "k3": 1.0,
                                                             "k2": {"value": 0.0, "prior_std": 1.0}}}))
    result = tmp_path / "result.json"
    proc = subprocess.run([sys.executable, "-m", "identify", "fit", str(SILVERBOX), "--model", "duffing",
                           "--scheme", "spectral", "--n", "1024", "--params", str(start),
                           "--estimate", "m,d,k,k2,k3", "--output", str(result), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert_silverbox_oscillator(json.loads(result.read_text()))


def assert_silverbox_oscillator(doc: dict) -> None:
    """The circuit of the Silverbox records as a fitted Duffing oscillator (RESULT.json):
    natural frequency, damping ratio and stiffening in the ranges its literature gives."""
    p = {k: v["value"] for k, v in doc["parameters"].items()}
    fn = math.sqrt(p["k"] / p["m"]) / (2 * math.pi)
    zeta = p["d"] / (2 * math.sqrt(p["k"] * p["m"]))
    assert 68.0 <= fn <= 69.5
    assert 0.04 <= zeta <= 0.06
    assert 2.5 <= p["k3"] / p["k"] <= 5.5
    import pandas as pd

    rms = max(pd.read_csv(SILVERBOX / f)["output"].pow(2).mean() ** 0.5 for f in ("schroeder1.csv", "schroeder2.csv"))
    assert math.sqrt(doc["channels"]["output"]["variance"]) < 0.015 * rms


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_friction_from_force_jumps_gives_the_linear_law_and_feeds_a_fit(standard_dataset, tmp_path):
    out = tmp_path / "FRICTION.json"
    proc = identify("friction", str(standard_dataset), "--output", str(out), "--figure", str(tmp_path / "f.png"))
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert doc["set"]["theta8"] == pytest.approx(80.0, rel=0.05)        # truth: nominal friction law
    assert doc["set"]["theta9"] == pytest.approx(4.0e-5, rel=0.1)
    assert doc["set"]["theta10"] == pytest.approx(2000.0, rel=0.2)
    assert len(doc["experiments"]) == 14 and (tmp_path / "f.png").stat().st_size > 0
    result = tmp_path / "R.json"
    proc = identify("fit", str(standard_dataset), "--estimate", "theta4,theta6", "--friction", str(out),
                    "--experiments", "b,h,j", "--output", str(result), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(result.read_text())["parameters"]["theta4"]["value"] == pytest.approx(5.0e-3, rel=2e-3)
    clash = identify("fit", str(standard_dataset), "--estimate", "theta8", "--friction", str(out),
                     "--experiments", "b", "--output", str(result))
    assert clash.returncode == 2 and "estimated and also fixed" in clash.stderr


@pytest.mark.slow
def test_compare_1dof_and_2dof_table_and_ratio(standard_dataset, tmp_path):
    out = tmp_path / "COMPARE.json"
    proc = identify("compare", str(standard_dataset), "--experiments", "a,b,j,c", "--output", str(out))
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert [r["label"][-1] for r in doc["experiments"]] == ["a", "b", "j", "c"]
    assert doc["ratio_1dof_2dof"] > 5            # the thermal model explains what the polytropic one cannot
    assert "ratio 1-dof/2-dof" in proc.stdout
    assert "warning (1dof): stroke_mm: residuals up to" in proc.stdout  # the fits' warnings are not dropped


@pytest.mark.slow
def test_stability_reports_floquet_multipliers(standard_dataset, tmp_path):
    result = tmp_path / "R.json"
    proc = identify("fit", str(standard_dataset), "--estimate", "theta4", "--experiments", "h,c",
                    "--stability", "--output", str(result), "--quiet")
    assert proc.returncode == 0, proc.stderr
    for e in json.loads(result.read_text())["experiments"].values():
        assert e["stable"] and 0 < e["floquet_max_multiplier"] < 1


@pytest.mark.slow
@pytest.mark.parametrize("generator", ["independent", "simulator"])
def test_reported_standard_deviations_match_the_monte_carlo_spread(generator):
    """Spread of θ4, θ6, θ16 over 20 fixed noise seeds within [0.7, 1.4] of the mean
    reported σ, on the independent generator's data and on the simulator's, and σ itself
    the same from seed to seed.

    Experiments b, l, m, n: b (0.1 Hz, full stroke about the middle) carries the heat
    transfer θ16, whose 10 s time constant it straddles, and with l, m, n (0.5-2 Hz near
    full extension, a soft gas spring) separates θ4 and θ6.  In l, m, n the force noise
    dominates the stroke residual through a few low harmonics; weights taken from each
    experiment's own residuals then followed the noise realisation, and σ was 1.3-1.8x
    the spread on the standard set.  On these four experiments that shows most clearly
    in σ varying between seeds: coefficient of variation 0.13-0.16 then, 0.02-0.04 now
    (some remains: the channel factor λ is estimated from the residuals of four
    experiments only).  Spread/σ, known to ±0.16 from 20 seeds, was 0.66-0.68 for θ4
    and θ6 on the independent generator's data then, 0.74-1.16 now."""
    import numpy as np

    from tests.sigma_calibration import ESTIMATE, Case, fit_seed, summarise

    case = Case(generator, 1000.0, 3, ("b", "l", "m", "n"))
    fits = [fit_seed(case, seed) for seed in range(200, 220)]
    stds = np.array([f[1] for f in fits])
    s = summarise(np.array([f[0] for f in fits]), stds, sum(f[2] for f in fits))
    variation = np.std(stds, axis=0) / np.mean(stds, axis=0)
    figures = {k: (round(r, 2), round(c, 3)) for k, r, c in zip(ESTIMATE, s.spread_over_sigma, variation, strict=True)}
    assert s.converged == 20
    assert np.all((s.spread_over_sigma >= 0.7) & (s.spread_over_sigma <= 1.4)), figures
    assert np.all(variation < 0.06), figures



def _with_lost_rows(source: Path, out: Path, labels: list[str], fraction: float, seed: int) -> Path:
    """A copy of ``labels`` of the dataset ``source`` with about ``fraction`` of each CSV's
    rows absent (single samples and bursts, as a line loses them), declared in the manifest."""
    import numpy as np
    import pandas as pd

    from identify.dataset import write_manifest

    rng = np.random.default_rng(seed)
    manifest = json.loads((source / "dataset.json").read_text())
    manifest["experiments"] = [e for e in manifest["experiments"] if e["label"] in labels]
    out.mkdir()
    for entry in manifest["experiments"]:
        df = pd.read_csv(source / entry["file"], dtype=str)
        lost = np.zeros(len(df), dtype=bool)
        while lost.mean() < fraction:
            start = rng.integers(1, len(df) - 40)
            lost[start:start + rng.integers(1, 20)] = True
        (out / entry["file"]).write_text(df[~lost].to_csv(index=False))
        entry["lost_samples"] = int(lost.sum())
    write_manifest(out, manifest)
    return out


@pytest.mark.slow
def test_lost_samples_cost_what_fewer_samples_cost_in_sigma(standard_dataset, tmp_path):
    """Experiments a (0.04 Hz, 150,000 samples) and l with 1.6 % of their rows lost: σ of
    θ4, θ6, θ16 within 5 % of the full records' and the estimates within 1 σ of them.
    Each noise estimate was read from the scatter about the folded curve, or from rows
    one period apart that were no longer a period apart: σ came out up to 8x larger."""
    from identify.dataset import read_dataset
    from identify.fit import fit_experiments
    from identify.model import load_model
    from identify.parameters import Parameters

    start = Path(__file__).resolve().parents[1] / "examples" / "start-2dof.json"
    model = load_model("2dof")
    labels = ["261122a", "261122l"]
    holed = _with_lost_rows(standard_dataset, tmp_path / "holed", labels, 0.016, seed=5)
    fits = []
    for folder in (standard_dataset, holed):
        experiments = read_dataset(folder, labels=labels).select(labels)
        fits.append(fit_experiments(model, experiments, Parameters.from_file(model, start),
                                    ["theta4", "theta6", "theta16"]))
    full, lost = fits
    assert lost.converged
    for k in ("theta4", "theta6", "theta16"):
        assert abs(lost.std[k] / full.std[k] - 1) < 0.05, (k, lost.std[k], full.std[k])
        assert abs(lost.params[k].value - full.params[k].value) < full.std[k], k


@pytest.mark.slow
def test_model_error_adds_a_residual_based_sigma_to_the_report_and_result(tmp_path):
    from identify.plans import STANDARD_SET, select
    from tests.independent_generator import generate_dataset

    data = generate_dataset(tmp_path / "data", select(STANDARD_SET, ["j", "c", "m", "n"]), seed=3)
    runs = {}
    for name, damping in (("right", 5.0e3), ("wrong", 1.0e4)):  # theta3 fixed at the truth / at twice it
        start = tmp_path / f"{name}.json"
        start.write_text(json.dumps({"model": "2dof", "parameters": {"theta3": damping}}))
        report = tmp_path / f"{name}.txt"
        proc = identify("fit", str(data), "--params", str(start), "--estimate", "theta4,theta6",
                        "--output", str(tmp_path / f"{name}-result.json"), "--report", str(report), "--quiet")
        assert proc.returncode == 0, proc.stderr
        runs[name] = json.loads((tmp_path / f"{name}-result.json").read_text()), report.read_text()
    doc, report = runs["right"]
    assert all("std_residual" not in p for p in doc["parameters"].values())
    assert "residual-based" not in report
    # identify/calibration.json (bench_sigma.py --record) validated the standard plan, θ4, θ6, θ16: not this fit
    assert "σ not validated by Monte-Carlo for this fit (4 experiments not the standard plan; theta4, theta6 " \
           "estimated)" in report
    doc, report = runs["wrong"]
    for k in ("theta4", "theta6"):
        assert doc["parameters"][k]["std_residual"] > 3 * doc["parameters"][k]["std"]
    assert any("residual-based standard deviations" in w for w in doc["warnings"])
    assert "* residual-based σ" in report
