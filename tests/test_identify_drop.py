"""identify drop: the virtual drop test of a fit, against the simulator's own landings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from identify.cli import main as identify_main
from identify.drop import DropDiscrepancy, Landing, load_fitted, peak, predict_drop, type_test
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import ExperimentSpec

ROOT = Path(__file__).resolve().parents[1]
# The experiment rig design --predict drop requires: the drop's stroke at its speed.
ENVELOPE = ExperimentSpec("e", "envelope", 80.0, 79.0, 1.0, periods=2)   # 1 mm clear of the top-out stop
ESTIMATE = ["theta3", "theta4", "theta5", "theta6", "theta8", "theta16"]   # the drop plan's purpose


def _fitted_folder(out: Path, damper, seed: int) -> Path:
    """The envelope experiment of ``damper`` generated (with its drop record), fitted for
    the drop plan's parameters from the example start; RESULT.json in the folder."""
    from simulator.generate import generate

    generate(out, [ENVELOPE], damper, periods=None, rate_hz=1000.0, seed=seed, drop=True, date="261128")
    from identify.dataset import read_dataset

    model = load_model("2dof")
    experiments = read_dataset(out).select(kind="periodic")
    start = Parameters.from_file(model, ROOT / "examples" / "start-2dof.json")
    result = fit_experiments(model, experiments, start, ESTIMATE)
    assert result.converged
    result.write_json(out / "RESULT.json")
    return out


@pytest.fixture(scope="module")
def model_world(tmp_path_factory) -> Path:
    from simulator.truth import load_truth

    return _fitted_folder(tmp_path_factory.mktemp("model") / "unit", load_truth(), 1)


def test_the_predicted_landing_is_the_model_worlds_own_within_its_sigma(model_world, capsys):
    from simulator.physics import drop_test
    from simulator.truth import load_truth

    code = identify_main(["drop", str(model_world / "RESULT.json")])
    out = capsys.readouterr().out
    assert code == 0
    assert "350 kg landing at 0.5 m/s" in out and "no model discrepancy given" in out.splitlines()[0]
    fitted = load_fitted(model_world / "RESULT.json")
    pred = predict_drop(fitted)
    truth = drop_test(load_truth(), 350.0, 0.5, pred.t)
    true_peak = peak(truth.axle_force)
    assert pred.peak_force.fit_std > 0 and pred.peak_force.discrepancy_std == 0
    # The model world: the fit sees the truth's own equations, so the landing is right
    # within the fit's σ (a few of them: the drop is a fifth of a second of a nonlinear
    # integration) and far within the 2 % the lab asks for.
    assert abs(pred.peak_force.value - true_peak) <= 4 * pred.peak_force.fit_std + 1e-4 * true_peak
    assert abs(pred.peak_force.value - true_peak) / true_peak < 2e-3
    assert pred.peak_stroke.value == pytest.approx(peak(truth.stroke), rel=2e-3)
    assert f"{pred.peak_force.value / 1e3:.3f}"[:4] in out


def test_histories_and_figure_are_written_with_their_sigma_and_the_discrepancy_widens_them(model_world, tmp_path,
                                                                                            capsys):
    csv, png = tmp_path / "drop.csv", tmp_path / "drop.png"
    code = identify_main(["drop", str(model_world / "RESULT.json"), "--discrepancy", "0.02", "--duration", "1",
                          "--csv", str(csv), "--plot", str(png)])
    out = capsys.readouterr().out
    assert code == 0 and png.stat().st_size > 10_000
    df = pd.read_csv(csv)
    assert list(df.columns)[:7] == ["time_s", "force_N", "force_sigma_N", "stroke_mm", "stroke_sigma_mm",
                                    "pressure_bar", "pressure_sigma_bar"]
    assert df["time_s"].iloc[-1] == pytest.approx(1.0)
    i = int(df["force_N"].idxmax())
    assert df["force_sigma_N"].iloc[i] == pytest.approx(0.02 * df["force_N"].iloc[i], rel=0.05)
    assert "2 %, given (--discrepancy)" in out and "no model discrepancy" not in out


def test_a_type_test_gives_the_discrepancy_from_reference_units_own_drops(model_world, tmp_path):
    from simulator.truth import load_truth

    # A reference unit without RESULT.json: fitted as the RESULT.json was, then dropped
    # at its record's own conditions (this simulator releases the mass at rest).
    ref = _fitted_folder(tmp_path / "ref", load_truth(unit="good", unit_seed=4), 2)
    (ref / "RESULT.json").unlink()
    fitted = load_fitted(model_world / "RESULT.json")
    delta, units = type_test(fitted, [ref])
    assert len(units) == 1 and delta.force.n_experiments == 1
    # The good unit's other parameters scatter, which θ3, θ4, θ6, θ16 absorb only in part:
    # a discrepancy, small in the model world, and never zero.
    assert 0 < delta.force.relative < 0.05 and delta.force.relative == pytest.approx(abs(units[0].force_error))
    assert delta.stroke.relative > 0


def test_on_the_plant_the_drop_plan_fit_predicts_the_paper_landing_within_its_stated_sigma(tmp_path):
    pytest.importorskip("simulator.plant")
    from simulator.plant.damper import PlantDamper
    from simulator.plant.drop import simulate_drop
    from simulator.plant.units import unit_constants

    folder = _fitted_folder(tmp_path / "plant", PlantDamper(unit_constants("good", 3)), 3)
    fitted = load_fitted(folder / "RESULT.json")
    assert fitted.residual_based   # the 2-dof model is not the plant: the fit says so
    landing = Landing()
    record = simulate_drop("good", 3, mass_kg=landing.mass_kg, velocity_m_s=landing.velocity_m_s,
                           duration_s=1.0, rate_hz=1000.0)
    pred = predict_drop(fitted, landing, record.t, DropDiscrepancy.given(0.026))
    error = pred.peak_force.value - peak(record.force_N)
    assert abs(error) / peak(record.force_N) < 0.05
    # The fit's σ alone is the shaker's; the stated σ carries the type test's 2.6 %.
    assert abs(error) <= 2 * pred.peak_force.std


def _one_line_refusal(capsys, argv: list[str], words: str) -> None:
    code = identify_main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert words in err and len(err.strip().splitlines()) == 1


def test_a_fit_that_held_a_landing_parameter_at_its_prior_says_so_first(tmp_path, capsys):
    from identify.dataset import read_dataset
    from simulator.generate import generate
    from simulator.truth import load_truth

    folder = generate(tmp_path / "d", [ENVELOPE], load_truth(), periods=None, rate_hz=1000.0, seed=5, date="261128")
    model = load_model("2dof")
    start = Parameters.from_file(model, ROOT / "examples" / "start-2dof.json")
    fit_experiments(model, read_dataset(folder).select(kind="periodic"), start,
                    ["theta4", "theta6", "theta16"]).write_json(tmp_path / "R.json")
    assert identify_main(["drop", str(tmp_path / "R.json"), "--discrepancy", "0.02"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("warning: this fit held theta3 (the orifice's damping), theta5") and "theta8" in first


def test_bad_input_is_refused_in_one_line(model_world, tmp_path, capsys):
    result = model_world / "RESULT.json"
    _one_line_refusal(capsys, ["drop", str(tmp_path / "missing.json")], "not found")
    one_dof = json.loads(result.read_text())
    one_dof["model"] = "1dof"
    (tmp_path / "1dof.json").write_text(json.dumps(one_dof))
    _one_line_refusal(capsys, ["drop", str(tmp_path / "1dof.json")], "no gas temperature")
    failed = {"model": "2dof", "converged": False, "message": "line search failed",
              "parameters": {"theta4": 0.005}}
    (tmp_path / "failed.json").write_text(json.dumps(failed))
    _one_line_refusal(capsys, ["drop", str(tmp_path / "failed.json")], "line search failed")
    _one_line_refusal(capsys, ["drop", str(result), "--mass", "-3"], "positive")
    _one_line_refusal(capsys, ["drop", str(result), "--discrepancy", "1.5"], "--discrepancy")
    # The measured drop landed at the paper's 0.5 m/s: predicting 0.3 m/s beside it compares nothing.
    _one_line_refusal(capsys, ["drop", str(result), "--measured", str(model_world), "--velocity", "0.3"],
                      "other conditions")
    _one_line_refusal(capsys, ["drop", str(result), "--type-test", str(tmp_path / "nowhere")], "not a folder")


def test_a_measured_drop_is_predicted_at_its_own_conditions_and_compared(model_world, capsys):
    code = identify_main(["drop", str(model_world / "RESULT.json"), "--measured", str(model_world),
                          "--duration", "1.5", "--discrepancy", "0.01"])
    out = capsys.readouterr().out
    assert code == 0
    assert "landing at 0.5 m/s, 1.5 s" in out
    line = next(x for x in out.splitlines() if x.startswith("measured peak force"))
    assert "within 2σ" in line
    assert np.isfinite(float(line.split("predicted ")[1].split(" %")[0]))
