"""A fit report's σ claim is scoped to where the Monte-Carlo calibration on record
(identify/calibration.json, docs/uncertainty.md) validated it: the model, the plan and
the parameters estimated; anywhere else it says "not validated" (issue 34)."""

from __future__ import annotations

import json

from identify.plans import STANDARD_SET
from identify.result import CALIBRATION_FILE, _calibration_line

STANDARD_HZ = [e.frequency_hz for e in STANDARD_SET]
CALIBRATED = json.loads(CALIBRATION_FILE.read_text())


def test_the_calibration_names_its_scope():
    assert (CALIBRATED["model"], CALIBRATED["plan"]) == ("2dof", "standard")
    assert sorted(CALIBRATED["plan_frequencies_hz"]) == sorted(STANDARD_HZ)


def test_the_standard_plan_on_the_2dof_model_is_validated():
    line = _calibration_line("2dof", STANDARD_HZ, ["theta4", "theta6", "theta16"])
    lo, hi = CALIBRATED["spread_over_sigma_range"]
    assert line is not None and line.strip() == (
        "σ validated by Monte-Carlo for model 2dof, the standard plan (14 experiments), theta4, theta6, theta16 "
        f"estimated, 64 seeds per case: spread/σ {lo:.2f}–{hi:.2f} (benchmarks/bench_sigma.py, docs/uncertainty.md)")


def test_a_two_experiment_fit_is_not_validated():
    line = _calibration_line("2dof", [2.0, 4.0], ["theta4", "theta6", "theta16"])
    assert line is not None and line.strip().startswith(
        "σ not validated by Monte-Carlo for this fit (2 experiments not the standard plan): the calibration on record "
        "covers model 2dof, the standard plan (14 experiments)")
    assert "spread/σ" not in line


def test_a_user_model_is_not_validated_even_on_the_standard_plan():
    line = _calibration_line("dahl", STANDARD_HZ, ["sigma0", "alpha"])
    assert line is not None and "not validated" in line
    assert "(model dahl; sigma0, alpha estimated)" in line
