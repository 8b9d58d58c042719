"""Production units from the simulator, judged with the default spec on generated data
(``simulator generate`` with the spec's plan, then ``qc judge``): a good unit passes, each
faulty preset fails on its characteristic with its cause, a unit on a limit is not a
PASS, and a re-judgement adds a record that refers to the first.

The 20 + 20 confusion table over seeded units is ``benchmarks/bench_qc.py``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rig.cli import main
from rig.qc.records import Records
from rig.qc.spec import load_spec
from simulator.generate import generate
from simulator.truth import load_truth

SPEC = load_spec("default")
PHYSICAL = ("gas_precharge_bar", "damping_force_0.3_N", "friction_10bar_N")


def unit_dataset(out: Path, unit: str | None, seed: int, params: Path | None = None) -> Path:
    truth = load_truth(params, "2dof", unit, seed)
    return generate(out, list(SPEC.plan.experiments), truth, periods=None, seed=seed, date="261122",
                    serial=f"SN-{seed:04d}")


def judge(capsys: pytest.CaptureFixture[str], session: Path, db: Path) -> tuple[int, str]:
    capsys.readouterr()
    code = main(["qc", "judge", str(session), "--db", str(db), "--create-db", "--operator", "qe"])
    return code, capsys.readouterr().out


def test_a_good_unit_passes_and_a_rejudgement_refers_to_the_first(tmp_path, capsys):
    session = unit_dataset(tmp_path / "unit", "good", 3)
    db = tmp_path / "records.sqlite"
    code, out = judge(capsys, session, db)
    assert code == 0 and out.startswith("SN-0003: PASS"), out
    assert judge(capsys, session, db)[0] == 0

    records = Records.open(str(db))
    first, second = records.find()
    records.close()
    assert (first.rejudges, second.rejudges) == (None, first.uid)
    assert first.data_sha256 == second.data_sha256 and first.uid != second.uid
    assert [c.outcome for c in first.characteristics] == ["PASS"] * len(SPEC.characteristics)
    assert set(first.files) == {"dataset.json", *(f"261122{e.letter}.csv" for e in SPEC.plan.experiments)}
    reports = sorted(session.glob("qc-report-*.html"))
    assert len(reports) == 2                                   # the first report is not overwritten
    assert "PASS" in reports[0].read_text() and "data:image/png;base64," in reports[0].read_text()
    stored = [json.loads(p.read_text()) for p in sorted(session.glob("qc-record-*.json"))]
    assert [d["uid"] for d in stored] == [first.uid, second.uid]


FAULTS = {"gas-leak": ("gas_precharge_bar", "low", "gas leak or under-serviced"),
          "worn-seal": ("friction_10bar_N", "high", "seal wear"),
          "worn-orifice": ("damping_force_0.3_N", "low", "orifice wear or wrong oil")}


@pytest.mark.parametrize("unit", FAULTS)
def test_a_faulty_unit_fails_on_its_characteristic_and_names_the_cause(unit, tmp_path, capsys):
    name, side, cause = FAULTS[unit]
    code, out = judge(capsys, unit_dataset(tmp_path / unit, unit, 1), tmp_path / "records.sqlite")
    assert code == 1 and out.startswith("SN-0001: FAIL"), out
    (record,) = Records.open(str(tmp_path / "records.sqlite")).find()
    failed = {c.name for c in record.characteristics if c.outcome == "FAIL"}
    assert failed & set(PHYSICAL) == {name}, record.characteristics
    title = next(c.title for c in SPEC.characteristics if c.name == name)
    assert f"{title} too {side}: {cause}" in record.diagnosis
    assert f"likely cause: {title} too {side}: {cause}" in out


@pytest.mark.parametrize(("parameter", "characteristic"), [("theta5", "gas_precharge_bar"),
                                                          ("theta8", "friction_10bar_N")])
def test_a_unit_exactly_on_a_limit_is_not_a_pass(parameter, characteristic, tmp_path, capsys):
    nominal = load_truth().theta
    t = -nominal["theta17"]
    if parameter == "theta5":        # pre-charge 5.70 bar at q = 0, 20 °C: the lower limit
        value = 5.70e5 * (1 + nominal["theta7"] * t) / t
    else:                            # friction 150 N at 10 bar: the upper limit
        value = 150.0 - nominal["theta9"] * 10e5
    truth = tmp_path / "TRUTH.json"
    truth.write_text(json.dumps({"model": "2dof", "parameters": {parameter: value}}))
    code, out = judge(capsys, unit_dataset(tmp_path / "unit", None, 2, truth), tmp_path / "records.sqlite")
    (record,) = Records.open(str(tmp_path / "records.sqlite")).find()
    outcome = {c.name: c.outcome for c in record.characteristics}
    assert outcome[characteristic] == "INCONCLUSIVE" and record.verdict == "INCONCLUSIVE" and code == 4, out
    assert record.remedy and f"--periods {SPEC.retest_periods()}" in record.remedy


def test_the_unit_option_overrides_are_those_of_the_truth_file(tmp_path):
    truth = tmp_path / "TRUTH.json"
    truth.write_text(json.dumps({"theta5": 2000.0}))
    leak = load_truth(None, "2dof", "gas-leak", 5).theta
    both = load_truth(truth, "2dof", "gas-leak", 5).theta
    assert both["theta5"] == 2000.0 and both["theta3"] == leak["theta3"] != load_truth().theta["theta3"]
