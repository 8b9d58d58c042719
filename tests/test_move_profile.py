"""Issue 42: the controller's move to a static position is one definition
(identify.move_profile), which the rig's planning takes from its configuration and the
simulated controller and the plant's plan sequence command."""

from __future__ import annotations

import numpy as np
import pytest

from identify.move_profile import CONTROLLER_MOVE, MoveProfile
from identify.plans import STANDARD_SET
from rig.config import DEFAULT_RIG_CONFIG, ConfigError, load_rig_config
from rig.planning.plans import Plan, estimate_experiment_durations
from simulator.controller import Mode, ShakerController
from simulator.physics import Actuator
from simulator.plant.sequence import Segment

TARGET_M = 0.130


def test_the_simulated_controller_moves_on_the_one_profile():
    controller = ShakerController()
    controller.write_coils(0, [True])
    controller.write_holding(2, [round(TARGET_M * 1e5)])
    controller.write_holding(0, [Mode.STATIC])
    duration = CONTROLLER_MOVE.duration_s(TARGET_M)
    t = np.array([0.0, duration / 2, duration, 2 * duration])
    q, v, _ = MoveProfile.stroke(0.0, TARGET_M, duration, t)
    assert controller.setpoint(t) == pytest.approx(q, abs=1e-12)
    assert v[1] == pytest.approx(CONTROLLER_MOVE.peak_speed_m_s) and v[3] == 0.0


def test_the_plant_sequence_moves_on_the_one_profile():
    spec = STANDARD_SET[0]
    segment = Segment.after(spec, Actuator(), 0.0, 10.0)
    static = spec.static_position_mm * 1e-3
    assert segment.move_s == CONTROLLER_MOVE.duration_s(static)
    sigma = np.array([-segment.move_s, -segment.move_s / 2])
    q, v, _ = segment.stroke(sigma)
    assert q[0] == pytest.approx(0.0, abs=1e-12) and q[1] == pytest.approx(static / 2)
    # the oscillation has not begun before σ = 0: the midpoint's speed is the profile's peak
    assert abs(v[1]) == pytest.approx(CONTROLLER_MOVE.peak_speed_m_s)


def test_planning_takes_the_move_from_the_rigs_configuration(tmp_path):
    assert load_rig_config().move == CONTROLLER_MOVE
    no_holds = DEFAULT_RIG_CONFIG.read_text().replace("max_hold_s = 300.0", "max_hold_s = 0.0")
    shipped, faster = tmp_path / "shipped.toml", tmp_path / "faster.toml"
    shipped.write_text(no_holds)
    faster.write_text(no_holds.replace("[limits]\n", "[limits]\nmove_speed_m_s = 0.1\n"))
    plan = Plan("one", (STANDARD_SET[0],))
    as_shipped = estimate_experiment_durations(plan, load_rig_config(shipped), noise_draws=0)[0]
    configured = estimate_experiment_durations(plan, load_rig_config(faster), noise_draws=0)[0]
    assert as_shipped.move_s == CONTROLLER_MOVE.duration_s(STANDARD_SET[0].static_position_mm * 1e-3)
    assert configured.move_s == pytest.approx(as_shipped.move_s / 2)


def test_a_bad_move_speed_is_one_line_naming_the_key(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text(DEFAULT_RIG_CONFIG.read_text().replace("[limits]\n", "[limits]\nmove_speed_m_s = -1\n"))
    with pytest.raises(ConfigError, match=r"\[limits\] move_speed_m_s = -1: not a positive number of m/s"):
        load_rig_config(bad)
