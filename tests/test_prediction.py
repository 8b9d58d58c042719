"""One prediction of rig time (issue 34): rig design, rig run's announcement, qc run's
re-prediction and the console call rig.planning.prediction.predict, at the links'
measured pace and latencies (kept per computer from the last probe) or at a rig's own
pace, saying which."""

from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
from rich.console import Console

from identify.model import load_model
from identify.parameters import Parameters
from rig.config import load_rig_config
from rig.design import rig_seconds
from rig.events import Event, EventBus, Kind
from rig.planning.plans import load_plan
from rig.planning.prediction import NOT_MEASURED, LinkTiming, last_measured, predict_s, remember, timing_file
from rig.session.progress import ConsoleProgress
from rig.session.run import SessionRunner
from tests.virtual_rig_inprocess import InProcessRig, quick_rig_config

CONFIG = load_rig_config(None)
AT_10X = LinkTiming(10.0, 0.02, 0.06, "a test's", "2026-11-26T12:00:00+00:00", "tcp://x and socket://y")


@pytest.fixture
def state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    return tmp_path / "state"


def test_without_a_measurement_the_prediction_says_what_it_assumed(state):
    assert last_measured() == NOT_MEASURED
    assert NOT_MEASURED.describe() == ("at a rig's own pace and no line latency (none measured on this computer yet: "
                                       "a simulator faster than the rig takes longer)")


def test_the_last_measured_timing_is_kept_and_named(state):
    remember(AT_10X)
    assert timing_file() == state / "damper-rig" / "link-timing.json"
    back = last_measured()
    assert (back.pace, back.answer_s, back.overhead_s, back.links) == (10.0, 0.02, 0.06, "tcp://x and socket://y")
    assert back.describe() == ("at 10 rig seconds per second, 60 ms of polls and commands per experiment, 20 ms from "
                               "a hold's end to RUN (the pace probe of 2026-11-26T12:00:00+00:00 on tcp://x and "
                               "socket://y, the last measured on this computer)")
    timing_file().write_text("{not json")
    assert last_measured() == NOT_MEASURED          # a broken file costs the basis, never a command


def test_design_and_the_session_predict_with_the_same_function():
    plan = load_plan("standard").select(["j", "c", "n"]).ordered(CONFIG)
    params = Parameters(load_model("2dof"))
    for timing in (NOT_MEASURED, AT_10X):
        assert rig_seconds(plan, CONFIG, params, timing) == pytest.approx(predict_s(plan, CONFIG, timing, 0.0, params))
    # at 10x the links' polls and commands and the holds a slow answer rules out cost rig time
    assert predict_s(plan, CONFIG, AT_10X) > predict_s(plan, CONFIG, NOT_MEASURED)


def test_a_session_announces_the_prediction_at_its_measured_timing_and_keeps_it(state, tmp_path):
    vrig = InProcessRig(quick_rig_config(tmp_path))
    vrig.connect()
    runners: list[SessionRunner] = []
    try:
        result = vrig.run_session(tmp_path / "s", ["j", "n"], on_runner=lambda r: r and runners.append(r))
    finally:
        vrig.close()
    runner = runners[0]
    timing = runner.timing()
    assert timing.is_measured and timing.basis == "this session's pace probe"
    announced = json.loads((tmp_path / "s" / "session.json").read_text())["estimated_rig_time_s"]
    plan = runner.prep.plan
    assert announced == pytest.approx(predict_s(plan, runner.prep.config, timing, runner.links.start_position_m),
                                      abs=0.06)
    assert result.exit_code == 0 and last_measured().pace == timing.pace


def test_qc_run_publishes_its_re_prediction_as_an_event(monkeypatch, tmp_path):
    import rig.qc.run as qc_run
    from rig.qc.judge import Outcome
    from rig.qc.spec import load_spec
    from rig.session.run import RunOptions, prepare

    spec = load_spec("default")
    prep = prepare(RunOptions(plan="standard", shaker="tcp://x:1", daq="socket://x:1", out=tmp_path / "s",
                              experiments=["j", "c", "n"]))
    params = Parameters(load_model("2dof"))
    evaluation = SimpleNamespace(
        judgement=SimpleNamespace(characteristics=[SimpleNamespace(name="gas_precharge_bar",
                                                                   outcome=Outcome.INCONCLUSIVE)]),
        fit=SimpleNamespace(converged=True, params=params))
    monkeypatch.setattr(qc_run, "evaluate", lambda spec, path, **options: evaluation)
    bus, events = EventBus(), []
    bus.subscribe(events.append, inline=True)
    session = SimpleNamespace(path=tmp_path, label=lambda letter: f"261126{letter}")
    result = SimpleNamespace(session=session, captured=[SimpleNamespace(label="261126j")])
    runner = SimpleNamespace(bus=bus, timing=lambda: AT_10X)
    told: list = []
    assert qc_run.decider(spec, prep, told.append, lambda: runner)(result) is None
    (e,) = [e for e in events if e.kind == Kind.PREDICTION]
    rest = replace(prep.plan, experiments=prep.plan.experiments[1:])
    assert e.data["rig_time_left_s"] == pytest.approx(predict_s(rest, prep.config, AT_10X, 0.133, params), abs=0.06)
    assert e.data["basis"] == "the parameters identified from 261126j"
    (p,) = told   # the console's QC panel hears the same figure (rig.qc.run.Prediction)
    assert (p.after, p.undecided, p.rig_left_s) == (("261126j",), ("gas_precharge_bar",), pytest.approx(
        e.data["rig_time_left_s"], abs=0.06))


def test_the_terminal_takes_the_re_prediction_over():
    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=300), {"261126a": 30.0, "261126b": 30.0}, 10.0)
    progress(Event(Kind.PREDICTION, None, {"rig_time_left_s": 55.0, "basis": "the parameters identified from 261126a",
                                           "message": "gas pre-charge not yet decided after 261126a: the rest of the "
                                                      "plan (1 experiment) predicted again from the parameters "
                                                      "identified from 261126a: 55 s of rig time"}))
    assert out.getvalue().splitlines()[-1].endswith("55 s of rig time. About 0:05 left (m:s of wall clock).")


def test_design_measures_the_links_it_is_given_and_nothing_moves(virtual_rig, state):
    from rig.session.run import probe_timing

    sim = virtual_rig(speed=50)
    timing = probe_timing(sim.modbus_url, sim.daq_url, CONFIG)
    assert timing.is_measured and 25 < timing.pace < 75 and timing.links == f"{sim.modbus_url} and {sim.daq_url}"
    assert last_measured().pace == pytest.approx(timing.pace)
    assert "hydraulics on" not in sim.log()


def test_design_needs_both_links_or_neither(capsys, tmp_path):
    from rig.cli import main

    code = main(["design", "--target", "theta4", "--sigma", "1e-8", "--shaker", "tcp://127.0.0.1:9",
                 "--out", str(tmp_path / "p.toml")])
    assert code == 2 and "--shaker and --daq go together" in capsys.readouterr().err
