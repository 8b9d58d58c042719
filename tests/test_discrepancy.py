"""identify.discrepancy: the model-discrepancy σ from experiments a fit did not see."""

from __future__ import annotations

import numpy as np
import pytest

from identify.dataset import read_dataset
from identify.discrepancy import from_errors, relative_output_errors
from identify.model import load_model
from identify.plans import STANDARD_SET, select
from identify.preparation import prepare_periodic
from tests.independent_generator import generate_dataset


def test_sigma_delta_is_the_rms_of_the_held_out_errors_and_needs_some():
    d = from_errors([0.01, -0.03], "two")
    assert d.relative == pytest.approx(np.sqrt((0.01**2 + 0.03**2) / 2))
    assert d.std(-200.0) == pytest.approx(200.0 * d.relative) and d.n_experiments == 2
    with pytest.raises(ValueError, match="held-out"):
        from_errors([], "none")


def test_held_out_pressure_errors_are_the_noise_at_the_truth_and_the_model_error_off_it(tmp_path):
    folder = generate_dataset(tmp_path / "d", select(STANDARD_SET, ["h", "l"]), rate_hz=500.0, seed=2)
    model = load_model("2dof")
    outputs = ["stroke_mm", "pressure_bar"]
    data = prepare_periodic(model, read_dataset(folder).select(kind="periodic"), 400, outputs)
    theta = model.nominal_vector()
    at_truth = relative_output_errors(model, theta, data, outputs, 400)
    assert at_truth.shape == (2, 2) and np.all(at_truth < 2e-3)   # the noise, folded over 3 periods
    wrong = theta.copy()
    wrong[model.parameter_index("theta5")] *= 1.02   # 2 % more gas than the damper has
    off = relative_output_errors(model, wrong, data, outputs, 400)
    # force-driven, the pressure stays pinned to the force: the spring's error is in the stroke
    assert np.all(off[:, 0] > 0.02) and np.all(off[:, 1] < off[:, 0] / 3)
