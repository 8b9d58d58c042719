"""Issue 42: a fit's warnings are codes and numbers; the sentence is rendered from them,
and QC decides from the code, never from the words."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from identify.fit_warnings import FitWarning, WarningCode
from identify.model import load_model
from identify.parameters import Parameters
from identify.result import FitResult
from rig.qc.characteristics import Identified
from rig.qc.evaluate import _for_the_verdict

MISFIT = FitWarning(WarningCode.MODEL_ERROR, {"output": "force_N", "ratio": 3.25, "worst": "A1", "input_share": None,
                                              "residual_based": False, "experiments": 2, "parameters": 3})


def _fit(findings: list[FitWarning], residual: np.ndarray | None = None) -> SimpleNamespace:
    model = load_model("2dof")
    fit = SimpleNamespace(params=Parameters(model), estimated=["theta4"], covariance=np.array([[1e-12]]),
                          covariance_residual=residual, converged=True, findings=findings)
    fit.honest_covariance = lambda: FitResult.honest_covariance(fit)  # type: ignore[arg-type]
    return fit


def test_the_model_error_sentence_is_rendered_from_its_numbers_as_it_was_written():
    assert str(MISFIT) == ("force_N: residuals up to 3.2x what the measurement noise explains (worst: A1): "
                           "systematic model or discretisation error; the standard deviations cover the noise "
                           "only; with 2 experiments for 3 parameters, and too few frequency lines carrying the "
                           "misfit, no residual-based ones can be given")
    assert MISFIT.to_json()["code"] == "model-error"


def test_qc_picks_the_sigma_basis_from_the_code_not_from_the_words():
    assert Identified.from_fit(_fit([MISFIT])).basis == "noise-misfit"
    assert Identified.from_fit(_fit([MISFIT], residual=np.array([[4e-12]]))).basis == "residual"
    # Another warning whose numbers happen to render a sentence about the noise: no misfit.
    noise = FitWarning(WarningCode.NOISE_NOT_ESTIMABLE)
    assert "measurement noise" in str(noise)
    assert Identified.from_fit(_fit([noise])).basis == "noise"


def test_the_verdict_words_a_model_error_from_its_code_and_leaves_the_others_as_they_are():
    said = _for_the_verdict(MISFIT, _fit([MISFIT]))
    assert said.startswith(MISFIT.finding) and "the verdict's σ is noise-only" in said
    assert "cover the noise only" not in said
    said = _for_the_verdict(MISFIT, _fit([MISFIT], residual=np.array([[4e-12]])))
    assert said.endswith("the verdict propagates the residual-based covariance, which includes it")
    unstable = FitWarning(WarningCode.UNSTABLE_ORBIT, {"records": ["A1", "B2"]})
    assert _for_the_verdict(unstable, _fit([unstable])) == str(unstable)


def test_a_stored_batch_result_gives_the_same_basis_from_its_codes():
    from rig.qc.batch_sink import identified_from_result

    model = load_model("2dof")
    result = {"model": "2dof", "parameters": {"theta4": {"value": 5e-3, "std": 1e-5, "estimated": True}},
              "covariance": {"estimated": ["theta4"], "noise": [[1e-10]], "residual": None},
              "warnings": [str(MISFIT)], "findings": [MISFIT.to_json()]}
    assert identified_from_result(model, result).basis == "noise-misfit"
    # The same words without the code (a result written before there were codes) decide nothing.
    assert identified_from_result(model, {**result, "findings": []}).basis == "noise"
    assert identified_from_result(model, {**result, "covariance": {**result["covariance"], "residual": [[4e-10]]}}
                                  ).basis == "residual"


def test_a_warning_read_back_from_result_json_renders_and_decides_the_same():
    import json

    from rig.qc.evaluate import verdict_note

    drift = FitWarning(WarningCode.DRIFT, {"column": "pressure_bar", "records": [("A1", 0.0123)], "unit": "bar"})
    for w in (MISFIT, drift):
        back = FitWarning.from_json(json.loads(json.dumps(w.to_json())))
        assert back.code is w.code and str(back) == str(w)
    assert verdict_note(FitWarning.from_json(MISFIT.to_json()), True).endswith("which includes it")
    with pytest.raises(ValueError):
        FitWarning.from_json({"code": "no-such-code"})
