"""A plan carries its purpose: rig design writes it, rig run and identify fit take the
parameters it was designed for, and a fit that leaves one at its prior says so first."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from identify.cli import main as identify_main
from identify.plans import ExperimentSpec, Purpose, Use
from rig.config import load_rig_config
from rig.design import Designed, drop_goal, parameter_goal, plan_text
from rig.planning.plans import Plan, PlanError, load_plan
from rig.session.run import RunOptions, prepare

DROP_SET = ("theta3", "theta4", "theta5", "theta6", "theta8", "theta16")


def _designed_plan(tmp_path: Path, goal) -> Path:
    """The plan file rig design writes for ``goal`` (the design itself is the slow part,
    tests/test_design.py; here one envelope experiment stands for its result)."""
    plan = Plan("designed", (ExperimentSpec("e", "envelope", 80.0, 79.0, 1.0, periods=2),), "", "fixed")
    sigma = goal.targets * 0.5 if np.all(np.isfinite(goal.targets)) else np.ones(len(goal.estimate))
    designed = Designed(plan, sigma, 53.0, True, None, plan.experiments, 1.0)
    out = tmp_path / "designed.toml"
    out.write_text(plan_text(designed, goal, "python -m rig design …"))
    return out


def test_the_purpose_round_trips_through_the_plan_file_and_rig_run_fits_it_by_default(tmp_path):
    goal = drop_goal("2dof", None, None, 0.04, 0.026, load_rig_config())
    path = _designed_plan(tmp_path, goal)
    plan = load_plan(str(path))
    assert plan.purpose == Purpose(Use.PREDICT_DROP, "2dof", DROP_SET)
    assert "with the model discrepancy" in path.read_text()
    opt = RunOptions(plan=str(path), shaker="tcp://127.0.0.1:1502", daq="socket://127.0.0.1:1503",
                     out=tmp_path / "session", identify=True)
    assert prepare(opt).options.estimate == list(DROP_SET)
    # Named on the command line, the operator's choice stands (and the fit will say what it leaves out).
    named = RunOptions(plan=str(path), shaker="tcp://127.0.0.1:1502", daq="socket://127.0.0.1:1503",
                       out=tmp_path / "session", identify=True, estimate=["theta4", "theta6", "theta16"])
    assert prepare(named).options.estimate == ["theta4", "theta6", "theta16"]
    # A plan without a purpose (the standard one) fits the model's default set, as before.
    standard = RunOptions(plan="standard", shaker="tcp://127.0.0.1:1502", daq="socket://127.0.0.1:1503",
                          out=tmp_path / "session", identify=True)
    assert prepare(standard).options.estimate == ["theta4", "theta6", "theta16"]


def test_a_parameter_plan_states_its_targets_as_its_purpose(tmp_path):
    goal = parameter_goal("2dof", None, ["theta4", "theta6"], [1e-8, 1e-6])
    plan = load_plan(str(_designed_plan(tmp_path, goal)))
    assert plan.purpose == Purpose(Use.PARAMETERS, "2dof", ("theta4", "theta6"))


def test_a_broken_purpose_is_refused_in_one_line(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text('name = "p"\n[purpose]\nuse = "landing"\nmodel = "2dof"\nestimate = ["theta4"]\n'
                    '[[experiment]]\nlabel = "a"\nstatic_mm = 80\namplitude_mm = 79\nfrequency_Hz = 1\n')
    with pytest.raises(PlanError, match="use 'landing' is not one of parameters, predict-drop, qc"):
        load_plan(str(path))


def test_the_session_dataset_keeps_the_purpose_and_identify_fit_takes_it(tmp_path, capsys):
    from rig.session.storage import Session
    from simulator.generate import generate
    from simulator.truth import load_truth

    purpose = Purpose(Use.PREDICT_DROP, "2dof", DROP_SET)
    Session.create(tmp_path / "s", plan_source="designed.toml", letters=["e"], periods=None, date="261128",
                   snapshot={}, unit={"serial": "SN-1"}, endpoints={}, purpose=purpose.to_document())
    assert json.loads((tmp_path / "s" / "dataset.json").read_text())["purpose"] == purpose.to_document()
    # A dataset of that plan's experiment (generated offline) with the session's purpose.
    data = generate(tmp_path / "d", [ExperimentSpec("e", "envelope", 80.0, 79.0, 1.0, periods=2)], load_truth(),
                    periods=None, rate_hz=1000.0, seed=3, date="261128")
    manifest = json.loads((data / "dataset.json").read_text())
    (data / "dataset.json").write_text(json.dumps({**manifest, "purpose": purpose.to_document()}))
    start = str(Path(__file__).resolve().parents[1] / "examples" / "start-2dof.json")
    code = identify_main(["fit", str(data), "--params", start, "--output", str(tmp_path / "r.json"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.splitlines()[0].startswith(f"estimating {', '.join(DROP_SET)}: what the plan was designed")
    assert json.loads((tmp_path / "r.json").read_text())["covariance"]["estimated"] == list(DROP_SET)
    code = identify_main(["fit", str(data), "--params", start, "--estimate", "theta4,theta6,theta16",
                          "--output", str(tmp_path / "r3.json"), "--quiet"])
    first = capsys.readouterr().err.splitlines()[0]
    assert code == 0
    assert first.startswith(f"warning: the plan was designed for {', '.join(DROP_SET)}") and \
        "holds theta3, theta5, theta8 at their prior values" in first
