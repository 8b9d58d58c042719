"""rig design --predict drop: the goal at the conditions of use (the paper's drop test)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.cli import main as rig_main
from rig.config import load_rig_config
from rig.design import drop_goal, drop_peak_stroke, envelope_experiment
from rig.drivers.shaker import check_waveform
from rig.errors import BadInput


def test_the_envelope_experiment_spans_the_drops_stroke_at_the_drops_velocity_within_the_limits():
    config = load_rig_config()
    e = envelope_experiment(config, 0.087)
    assert e.static_position_mm - e.amplitude_mm <= 10.0
    assert e.static_position_mm + e.amplitude_mm >= 87.0
    assert not check_waveform(config.limits, e.static_position_mm * 1e-3, e.amplitude_mm * 1e-3, e.frequency_hz)
    velocity = 2 * math.pi * e.frequency_hz * e.amplitude_mm * 1e-3
    assert velocity >= 0.45  # the drop's 0.5 m/s within the rig's 0.6 m/s limit, not a slow cycle
    with pytest.raises(BadInput, match="spans the drop"):
        envelope_experiment(config, 0.5)  # beyond the rig's stroke


def test_drop_goal_targets_leave_the_discrepancy_its_share_and_name_the_remaining_risk():
    goal = drop_goal("2dof", None, None, 0.03, 0.02, load_rig_config())
    assert goal.estimate == ("theta3", "theta4", "theta5", "theta6", "theta8", "theta16")
    force_n, stroke_m = goal.targets / math.sqrt(0.03**2 - 0.02**2)
    assert 3e3 < force_n < 6e3 and 0.05 < stroke_m < 0.12   # 350 kg at 0.5 m/s on the nominal damper
    assert stroke_m == pytest.approx(drop_peak_stroke(goal.model, goal.params.vector(), 350.0, 0.5), rel=1e-9)
    assert goal.required and goal.required[0].group == "envelope"
    assert goal.quantities.jacobian.shape == (2, 6) and np.all(np.isfinite(goal.quantities.jacobian))
    assert abs(goal.quantities.jacobian[0, 0]) > 0   # θ3 moves the peak force: it is estimated for a reason
    assert any("discrepancy" in r for r in goal.risks) and any("prior values" in r for r in goal.risks)


@pytest.mark.parametrize(("args", "words"), [
    (["--accuracy", "0.01", "--discrepancy", "0.02"], "discrepancy alone"),
    (["--accuracy", "2"], "between 0 and 1"),
    (["--estimate", "theta3,nonsense"], "nonsense"),
])
def test_predict_drop_refuses_bad_input_in_one_line(tmp_path, capsys, args, words):
    code = rig_main(["design", "--predict", "drop", *args, "--out", str(tmp_path / "p.toml")])
    err = capsys.readouterr().err
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p.toml").exists()
