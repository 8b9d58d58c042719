"""What the live view computes and the session's progress the plan table renders, without Qt or a rig."""

from __future__ import annotations

import math

import numpy as np
import pytest

from identify.exit_codes import EXIT_INTERRUPTED
from rig.config import load_rig_config
from rig.events import Event
from rig.gui import analysis
from rig.gui.plan_state import PlanProgress
from rig.planning.plans import load_plan
from rig.session.session_progress import ExperimentProgress, SessionProgress, predicted_cycles_left


def test_loop_energy_of_a_viscous_damper_is_pi_c_omega_a_squared():
    rate, f, a, c, cycles = 2000.0, 2.0, 0.01, 3000.0, 3
    t = np.arange(int(cycles * rate / f) + 1) / rate
    q = a * np.sin(2 * np.pi * f * t)
    force = 5000.0 + 1e5 * q + c * a * 2 * np.pi * f * np.cos(2 * np.pi * f * t)   # spring + viscous
    energy = analysis.loop_energy_j(q, force, cycles)
    assert math.isclose(energy, np.pi * c * 2 * np.pi * f * a**2, rel_tol=1e-4)


def test_velocity_of_a_sine_and_the_whole_cycles_in_view():
    rate, f, a = 2000.0, 1.0, 0.02
    t = np.arange(4000) / rate
    v = analysis.velocity_m_s(a * np.sin(2 * np.pi * f * t), rate, f)
    assert np.max(np.abs(v[100:-100] - a * 2 * np.pi * f * np.cos(2 * np.pi * f * t[100:-100]))) < 1e-3 * a * 2 * np.pi
    assert analysis.last_cycles(4000, rate, f, 3) == 4000          # only 2 whole cycles held
    assert analysis.last_cycles(4000, rate, f, 1) == 2000


def test_cycles_left_from_a_geometric_decay():
    thresholds = {"stroke_mm": 0.02, "pressure_bar": 0.0005}
    history = [(10, {"stroke_mm": 0.001, "pressure_bar": 0.004}), (20, {"stroke_mm": 0.001, "pressure_bar": 0.002})]
    # halves every 10 cycles: 0.002 → 0.0005 takes 20 more
    assert predicted_cycles_left(history, thresholds, 3, 1500) == 20
    assert predicted_cycles_left(history[:1], thresholds, 3, 1500) is None
    growing = [(10, {"stroke_mm": 0.001, "pressure_bar": 0.001}), (20, {"stroke_mm": 0.001, "pressure_bar": 0.002})]
    assert predicted_cycles_left(growing, thresholds, 3, 1500) is None
    settled = [(2, {"stroke_mm": 0.001, "pressure_bar": 0.0001})]
    assert predicted_cycles_left(settled, thresholds, 3, 1500) == 1     # the minimum still to come


def plan_progress(letters: list[str], date: str, config, pace: float = 1.0, clock=None) -> PlanProgress:
    """A plan table's progress of these experiments of the standard plan, its estimates the one prediction's."""
    from rig.planning.prediction import predict

    plan = load_plan("standard").select(letters)
    estimates = {f"{date}{d.letter}": d.total_s for d in predict(plan, config)}
    specs = {f"{date}{e.letter}": e for e in plan.experiments}
    session = SessionProgress(estimates, pace, clock or (lambda: 0.0), specs=specs, config=config)
    return PlanProgress(session, fed=False)


def test_plan_rows_follow_the_events_and_the_eta_scales_with_what_was_measured():
    now = [0.0]
    config = load_rig_config()
    progress = plan_progress(["j", "n"], "261122", config, pace=50.0, clock=lambda: now[0])
    j, n = progress.rows
    assert [r.status_text() for r in progress.rows] == ["pending", "pending"]
    assert math.isclose(progress.session_left_s(), (j.estimate_s + n.estimate_s) / 50)
    progress.apply(Event("phase", "261122j", {"phase": "moving"}))
    progress.apply(Event("progress", "261122j", {"phase": "settling", "cycles": 12, "change": {"stroke_mm": 0.1}}))
    assert j.status_text() == "settling 12" and progress.current is j
    progress.apply(Event("progress", "261122j", {"phase": "capturing", "fraction": 0.42}))
    assert j.status_text() == "capturing 42 %"
    now[0] = j.estimate_s / 10                          # took 5x longer than at 50x
    progress.apply(Event("experiment-done", "261122j", {"flags": []}))
    assert j.status_text() == "done"
    # the rest scaled by the ratio as far as the done ones are the session (their share of the estimate)
    share = j.estimate_s / (j.estimate_s + n.estimate_s)
    assert math.isclose(progress.rig_left_s(n), n.estimate_s * (1 + 4 * share))
    progress.apply(Event("phase", "261122n", {"phase": "settling"}))
    progress.apply(Event("session-end", None, {"message": "interrupted (SIGINT)", "exit_code": EXIT_INTERRUPTED,
                                               "exit_status": "interrupted"}))
    assert n.status == "interrupted" and progress.session_left_s() == 0.0


def test_peak_decimation_keeps_the_extremes_in_time_order():
    t = np.arange(20000) / 2000.0
    y = np.sin(2 * np.pi * t)
    y[12345] = 5.0                                          # a spike
    td, yd = analysis.peak_decimate(t, y, 1000)
    assert len(td) == 2000 and np.all(np.diff(td) > 0)
    assert yd.max() == 5.0 and math.isclose(yd.min(), y.min())
    short_t, short_y = analysis.peak_decimate(t[:1500], y[:1500], 1000)    # under 2 samples a bucket: as is
    assert np.array_equal(short_t, t[:1500]) and np.array_equal(short_y, y[:1500])


def test_the_steady_state_view_shows_the_criterion_that_decides(qtbot):
    """Under the drift criterion the bias bound is the deciding line and the cycles left
    come from its decay; the changes stay, pale, for information (they were coloured as
    failing thresholds that did not apply), saying under or over their threshold.  Under the
    change criterion, as before."""
    from identify.notation import significant
    from rig.config import DEFAULT_RIG_CONFIG
    from rig.gui.plan_panel import INFO_OVER, INFO_UNDER, SteadyStateView

    config = load_rig_config(DEFAULT_RIG_CONFIG)
    assert config.steady_state.drift is not None
    fraction = config.steady_state.drift.fraction
    view = SteadyStateView(config)
    qtbot.addWidget(view)
    assert "drift criterion decides" in view.title()
    row = ExperimentProgress("261124a", 100.0, load_plan("standard").experiments[0])
    change = {"stroke_mm": 1e-4, "force_N": 0.5, "pressure_bar": 0.002, "gas_temperature_C": 0.04}
    row.settling = [(40, change | {"bias_sigma": 4 * fraction}), (50, change | {"bias_sigma": 2 * fraction})]
    row.status, row.cycles = "settling", 50
    session = SessionProgress({"261124a": 100.0}, specs={"261124a": row.spec}, config=config)
    session.experiments["261124a"] = row
    view.show_row(row)
    view.show_count(row, session.cycles_left(row))
    assert f"up to {significant(2 * fraction)} σ; captures below {fraction:g} σ" in view.bound.text()
    # The bound is over its limit: the deciding line says not steady, and no bar is green beside it.
    assert view.bound.text().startswith("NOT STEADY") and "#2e7d32" not in view.bound.styleSheet()
    assert all(bar.property("colour") not in ("#43a047", "#a5d6a7") for bar in view.bars)
    assert view.table.horizontalHeaderItem(2).text() == "÷ threshold (info)"
    assert "predicted cycles left: 10" in view.cycles.text()     # halves every 10 cycles: 10 more
    # 13x its change threshold: pale orange (over, for information), not the change criterion's orange;
    # the stroke's change, under its threshold, grey (not green: only the bound passes a capture)
    assert view.bars[3].property("colour") == INFO_OVER and view.bars[0].property("colour") == INFO_UNDER

    from dataclasses import replace

    change_config = replace(config, steady_state=replace(config.steady_state, criterion="change"))
    plain = SteadyStateView(change_config)
    qtbot.addWidget(plain)
    assert plain.title() == "Steady state (change criterion)"
    plain.show_row(row)
    assert plain.bars[3].property("colour") == "#fb8c00"
    # A QC spec's session brings its own criterion: the view takes it (the drift bound's
    # field is absent from its reports; the cycles left come from the changes).
    row.settling.append((60, change | {"bias_sigma": fraction / 2}))
    view.show_row(row)
    assert view.bound.text().startswith("steady by the drift criterion") and "#2e7d32" in view.bound.styleSheet()
    view.configure(change_config)
    assert view.title() == "Steady state (change criterion)" and not view.bound.isVisibleTo(view)
    row.settling = [(40, dict(change)), (50, {k: v / 2 for k, v in change.items()})]
    view.show_row(row)
    view.show_count(row, 10)
    assert "predicted cycles left:" in view.cycles.text() and view.bars[3].property("colour") == "#fb8c00"


def test_a_new_excitation_starts_the_loops_afresh():
    """The loops take only the samples after the mark a new excitation sets; a new stream
    (the DAQ restarted at a session's RUN) starts with no mark."""
    from rig.drivers.daq import RingBuffer
    from rig.gui.live import LiveHistory

    class Source:
        ring = RingBuffer(1000)

    history, daq = LiveHistory(100.0, seconds=5.0), Source()
    daq.ring.append(np.arange(300), np.zeros((300, 4)))
    assert history.update(daq) and history.since_mark() == 300
    history.set_mark()
    assert history.since_mark() == 0
    daq.ring.append(np.arange(300, 350), np.ones((50, 4)))
    history.update(daq)
    assert history.since_mark() == 50
    daq.ring.append(np.arange(20), np.ones((20, 4)))          # a new stream
    history.update(daq)
    assert history.n == 20 and history.since_mark() == 20


def test_the_time_left_and_the_settling_view_count_the_same_cycles(qtbot):
    """Under the drift criterion the table's rig time left for the settling experiment
    comes from the cycles its bias bound's decay predicts, as the settling view says them
    (it came from the change thresholds, already met: '0:02' beside '257 cycles left')."""

    from rig.config import DEFAULT_RIG_CONFIG
    from rig.gui.plan_panel import SteadyStateView

    config = load_rig_config(DEFAULT_RIG_CONFIG)
    fraction = config.steady_state.drift.fraction
    plan = load_plan("standard")
    progress = plan_progress([plan.experiments[0].letter], "261124", config)
    (row,) = progress.rows
    change = {"stroke_mm": 1e-5, "force_N": 0.01, "pressure_bar": 1e-5, "gas_temperature_C": 1e-4}   # all met
    row.settling = [(40, change | {"bias_sigma": 4 * fraction}), (50, change | {"bias_sigma": 2 * fraction})]
    row.status, row.cycles, row.started = "settling", 50, 0.0
    view = SteadyStateView(config)
    qtbot.addWidget(view)
    view.show_count(row, progress.cycles_left(row))
    assert "predicted cycles left: 10" in view.cycles.text()
    ss, f = config.steady_state, row.spec.frequency_hz
    assert progress.rig_left_s(row) == pytest.approx((10 + row.spec.periods) / f + ss.ramp_time_s)


def test_the_parameter_table_marks_an_estimate_that_did_not_move_from_its_start(qtbot):
    """0.004999978 ± 0.000000023 beside a start of 0.005 after two iterations: recovered or
    never moved?  The move from the start in σ beside it, and an estimate within 1 σ of its
    start is marked and warned about; one that moved is not."""
    from rig.gui.fit_view import NOT_MOVED, fill_parameter_table, parameter_table

    table = parameter_table()
    qtbot.addWidget(table)
    doc = {"parameters": {
        "theta4": {"value": 0.004999978, "std": 2.3e-8, "initial": 0.005, "estimated": True, "unit": "m^2"},
        "theta16": {"value": 0.85181, "std": 0.00069, "initial": 0.80, "estimated": True, "unit": "W/K"},
        "theta1": {"value": 1.0, "std": None, "initial": 1.0, "estimated": False, "unit": ""}}}
    warnings = fill_parameter_table(table, doc)
    assert table.rowCount() == 2
    assert table.item(0, 5).text() == "0.005" and table.item(0, 6).text() == "-0.96 σ"
    assert "not told from one never moved" in table.item(0, 6).toolTip()
    assert table.item(0, 1).background().color().name() == NOT_MOVED
    assert table.item(1, 5).text() == "0.8" and table.item(1, 6).text() == "75 σ"
    assert table.item(1, 1).background().color().name() != NOT_MOVED
    assert [w.split(":")[0] for w in warnings] == ["theta4"] and "start value 0.005" in warnings[0]
