"""QC records that cannot lie and statistics a quality engineer trusts (#25): where a record
was measured, databases that readers never create, record identity in the export, I-MR
limits from a baseline, numbers shown by their uncertainty, one honest note on σ, and the
console's progress and table read from the run's output."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from identify.fit_warnings import FitWarning, WarningCode
from rig.cli import build_parser, main
from rig.config import load_rig_config
from rig.drivers.daq import Calibration, Daq
from rig.drivers.peer_identity import Peers
from rig.drivers.shaker import Shaker
from rig.events import Event, Kind
from rig.gui.qc import QcProgress, QcRequest, QcTracker, done_from
from rig.qc.evaluate import _for_the_verdict
from rig.qc.history import MIN_CAPABILITY_N, capability, imr_limits, index
from rig.qc.judge import Outcome
from rig.qc.present import limits_text, shown, sigma_note
from rig.qc.records import ADDED_IN_2, ADDED_IN_3, ADDED_IN_4, CharacteristicRecord, QcRecord, Records, RecordStatus
from rig.qc.run import Prediction, QcOutcome
from rig.qc.spec import load_spec
from simulator.generate import generate
from simulator.truth import load_truth
from tests.test_qc_records import qc, record

SPEC = load_spec("default")
README = Path(__file__).resolve().parent.parent / "README.md"


# ----- where a record was measured ---------------------------------------------------------------------
def test_the_served_simulator_names_itself_on_both_links(virtual_rig):
    sim = virtual_rig(speed=10)
    shaker = Shaker(sim.modbus_url, load_rig_config(None).limits)
    shaker.connect(heartbeat=False)
    try:
        controller = shaker.identify()
    finally:
        shaker.close()
    daq = Daq(sim.daq_url, Calibration.from_file())
    try:
        idn = daq.open()
    finally:
        daq.close()
    assert controller["model_name"] == "SIMULATOR" and controller["firmware"] == "1.23"
    assert idn.startswith("DAQ4,") and idn.endswith(",SIMULATOR")
    assert Peers(controller, idn).simulated
    assert Peers(controller, "DAQ4,SN42,2.01").simulated            # either link is enough
    assert Peers({"firmware": "1.23"}, idn).simulated


class NoIdentificationClient:
    """A controller without Read Device Identification (illegal function), firmware 2.05."""

    def connect(self) -> bool:
        return True

    def close(self) -> None:
        pass

    def read_device_information(self, **kwargs):
        return SimpleNamespace(isError=lambda: True, exception_code=1)

    def read_input_registers(self, address, count, device_id):
        return SimpleNamespace(isError=lambda: False, registers=[0, 0, 0, 0, 0, 0, 205][address:address + count])


def test_a_controller_without_device_identification_is_named_by_its_firmware():
    shaker = Shaker("tcp://127.0.0.1:1", load_rig_config(None).limits, client=NoIdentificationClient())
    controller = shaker.identify()
    assert controller == {"firmware": "2.05"}
    peers = Peers(controller, "DAQ4,SN42,2.01")
    assert not peers.simulated and peers.describe() == "controller firmware 2.05; DAQ DAQ4,SN42,2.01"


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("generated")
    return generate(root / "good", list(SPEC.plan.experiments), load_truth(None, "2dof", "good", 3), periods=None,
                    seed=3, date="261122", serial="SN-0003")


def test_a_simulated_record_stays_simulated_and_is_marked_everywhere(generated, tmp_path, capsys):
    db = tmp_path / "r.sqlite"
    code, out = qc(capsys, "judge", str(generated), "--db", str(db), "--create-db", "--operator", "qe")
    assert code == 0 and "SIMULATED" in out.splitlines()[0]
    code, out = qc(capsys, "judge", str(generated), "--db", str(db))        # a re-judgement: simulated too
    assert code == 0
    first, second = Records.open(str(db)).find()
    assert first.simulated and second.simulated and second.rejudges == first.uid
    (report,) = generated.glob(f"qc-report-*-{second.uid[:8]}.html")
    assert "class=watermark" in report.read_text() and "a SIMULATOR, not hardware" in report.read_text()
    code, out = qc(capsys, "history", "--db", str(db))
    assert "PASS SIMULATED" in out
    with sqlite3.connect(db) as conn, pytest.raises(sqlite3.DatabaseError, match="never changed or deleted"):
        conn.execute("UPDATE qc_record SET simulated = 0")
    assert all(r.simulated for r in Records.open(str(db)).find())


def characteristic(value: float, outcome: Outcome = Outcome.PASS) -> CharacteristicRecord:
    return CharacteristicRecord("damping_force_0.3_N", "N", value, 2.0, 1.0, 1.7, 405.0, 495.0, 450.0, outcome,
                                "Damping force at 0.3 m/s", "residual")


def unit(i: int, value: float, *, simulated: bool = False, status: RecordStatus = RecordStatus.COMPLETE) -> QcRecord:
    base = record(f"SN-{i:04d}", f"u{i}")
    verdict = (Outcome.PASS if 405 < value < 495 else Outcome.FAIL) if status is RecordStatus.COMPLETE else None
    chars = (characteristic(value, verdict),) if verdict else ()
    return replace(base, verdict=verdict, status=status, simulated=simulated,
                   characteristics=chars, k=2.0)


def test_statistics_leave_simulated_and_aborted_runs_out_unless_asked(tmp_path, capsys):
    records = [unit(i, 450.0 + (i % 3)) for i in range(5)] + [unit(5, 300.0, simulated=True),
                                                                unit(6, 0.0, status=RecordStatus.ABORTED)]
    (cap,) = capability(records)
    assert (cap.n_units, cap.passed, cap.failed) == (5, 5, 0)
    (cap,) = capability(records, include_simulated=True)
    assert (cap.n_units, cap.failed) == (6, 1)
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    db = Records.open(url, create=True)
    for r in records:
        db.add(r)
    db.close()
    out = qc(capsys, "history", "--db", url)[1]
    assert "simulated left out" in out.replace("\n", " ") and "FAIL SIMULATED" in out
    assert "ABORTED" in out


# ----- databases are opened, never created, by readers -----------------------------------------------
@pytest.mark.parametrize("command", [["history"], ["judge", "SESSION"]])
def test_readers_refuse_a_database_that_does_not_exist_and_create_none(command, generated, tmp_path, capsys):
    missing = tmp_path / "typo" / "qc-recrods.sqlite"
    args = [str(generated) if a == "SESSION" else a for a in command]
    code, err = qc(capsys, *args, "--db", str(missing))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "does not exist" in err, err
    assert not missing.exists() and not missing.parent.exists()
    code, err = qc(capsys, *args, "--db", str(tmp_path))       # a station folder instead of its database
    assert code == 2 and "a folder, not a database file" in err and "qc-records.sqlite" in err


def test_a_run_that_never_started_writes_nothing(tmp_path, capsys):
    station = tmp_path / "station"
    code, err = qc(capsys, "run", "--serial", "SN-0042", "--shaker", "tcp://127.0.0.1:9", "--daq",
                   "socket://127.0.0.1:9", "--out", str(station))
    assert code in (2, 3) and "no Modbus controller answers" in err, err
    assert not (station / "qc-records.sqlite").exists() and not list(station.glob("SN-0042-*"))


# ----- record identity in the export -------------------------------------------------------------------
def test_the_export_tells_a_rejudgement_from_the_original(generated, tmp_path, capsys):
    db = str(tmp_path / "r.sqlite")
    qc(capsys, "judge", str(generated), "--db", db, "--create-db")
    qc(capsys, "judge", str(generated), "--db", db)
    latest = json.loads(qc(capsys, "history", "--db", db, "--json")[1])
    everything = json.loads(qc(capsys, "history", "--db", db, "--json", "--all")[1])
    assert len(latest) == 1 and len(everything) == 2
    first, second = everything
    assert latest == [second]
    assert (first["rejudges"], first["superseded_by"]) == (None, second["uid"])
    assert (second["rejudges"], second["superseded_by"]) == (first["uid"], None)
    assert first["uid"] != second["uid"] and first["judged_at"] <= second["judged_at"]
    c = second["characteristics"]["gas_precharge_bar"]
    assert c["title"] == "Gas pre-charge" and c["sigma_basis"] in ("noise", "residual", "noise-misfit")
    assert c["acceptance"] == [pytest.approx(c["low"] + 2 * c["std"]), pytest.approx(c["high"] - 2 * c["std"])]
    assert second["measured_on"] == {"controller": None, "daq": None} and second["simulated"] is True


# ----- statistics as the SPC references do them -------------------------------------------------------
def test_a_point_beyond_the_limits_is_flagged_and_left_out_of_their_estimate():
    x = np.array([450, 452, 449, 451, 448, 450, 453, 447, 451, 343, 450, 452, 449], dtype=float)
    keep, mean, mr_bar = imr_limits(x)
    assert list(np.flatnonzero(~keep)) == [9]
    assert mean == pytest.approx(np.delete(x, 9).mean())
    assert mean + 3 * mr_bar / 1.128 < 495.0                                  # the UCL below the USL again
    records = [unit(i, v) for i, v in enumerate(x)]
    (cap,) = capability(records)
    assert cap.flagged == (9,) and cap.n == 12 and cap.failed == 1
    # from a baseline of the first 5 units: the later ones are judged against its limits
    (base,) = capability(records, baseline=5)
    assert base.n == 5 and base.mean == pytest.approx(x[:5].mean()) and 9 in base.flagged


def test_capability_shows_n_and_is_marked_not_meaningful_below_25():
    few = capability([unit(i, 450.0 + (i % 4)) for i in range(MIN_CAPABILITY_N - 1)])[0]
    enough = capability([unit(i, 450.0 + (i % 4)) for i in range(MIN_CAPABILITY_N)])[0]
    assert not few.meaningful and index(few.cp, few).startswith("(")
    assert enough.meaningful and not index(enough.cp, enough).startswith("(") and enough.n == MIN_CAPABILITY_N


def test_history_prints_n_and_marks_capability_from_few_units(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    db = Records.open(url, create=True)
    for i, v in enumerate((449.0, 451.0, 450.0)):
        db.add(unit(i, v))
    db.close()
    out = qc(capsys, "history", "--db", url)[1]
    row = next(line for line in out.splitlines() if "Damping force at 0.3 m/s" in line)
    cells = [c.strip() for c in row.strip("│").split("│")]
    assert cells[1] == "3" and cells[5].startswith("(") and cells[7] == "450 N ± 10 %"
    assert all(cells[i].endswith(" N") for i in (2, 3))
    assert "not meaningful, fewer than 25 units" in out


# ----- presentation by the uncertainty ---------------------------------------------------------------
def test_a_characteristic_is_shown_by_its_uncertainty_with_units():
    rec = replace(record("SN-0001", "p"), k=2.0)
    c = CharacteristicRecord("dissipated_energy_J", "J", 65.61234, 0.5123, 0.2, 0.5, 67.4645, 91.2755, 79.37,
                             Outcome.FAIL, "Energy dissipated per cycle", "scatter")
    s = shown(rec, c)
    # k·σ is k times the σ shown (2 × 0.51), both at σ's place: 65.6 ± 1.0 beside 0.51 read as a slip
    assert s.value == "65.61 ± 1.02 J" and s.sigma == "0.51 J" and s.basis == "period scatter"
    assert s.limits == "79.37 J ± 15 %"                       # as the spec states them, not 67.4645 … 91.2755
    assert s.acceptance == "68.49 … 90.25 J"                  # the limits moved in by 2σ, at the value's place
    assert s.title == "Energy dissipated per cycle" and s.name == "dissipated_energy_J"
    assert limits_text(120.0, 60.0, 150.0, "N") == "60 … 150 N" and limits_text(0.0, None, 3.0, "m^2") == "≤ 3 m²"


def test_the_report_states_which_sigma_the_verdict_used_and_never_contradicts_it():
    residual = CharacteristicRecord("gas_precharge_bar", "bar", 6.0, 0.02, 0.005, 0.02, 5.7, 6.3, 6.0, Outcome.PASS,
                                    "Gas pre-charge", "residual")
    assert "residual-based" in sigma_note(residual) and "u_cal 0.02 bar" in sigma_note(residual)
    assert "noise only" in sigma_note(replace(residual, sigma_basis="noise"))
    warning = FitWarning(WarningCode.MODEL_ERROR, {"output": "stroke_mm", "ratio": 2.2, "worst": "l",
                                                   "input_share": None, "residual_based": True, "experiments": 5,
                                                   "parameters": 3})
    assert str(warning) == ("stroke_mm: residuals up to 2.2x what the measurement noise explains (worst: l): "
                            "systematic model or discretisation error; the standard deviations cover the noise only; "
                            "residual-based standard deviations, which include it, are given beside them")
    with_residual = _for_the_verdict(warning, SimpleNamespace(covariance_residual=np.eye(2)))
    assert "cover the noise only" not in with_residual and "verdict propagates the residual-based" in with_residual
    without = _for_the_verdict(warning, SimpleNamespace(covariance_residual=None))
    assert "the verdict's σ is noise-only" in without


def test_the_report_has_titles_acceptance_limits_units_and_a_sigma_note_per_characteristic(generated, tmp_path,
                                                                                              capsys):
    code, out = qc(capsys, "judge", str(generated), "--db", str(tmp_path / "r.sqlite"), "--create-db")
    assert code == 0
    page = Path(out.splitlines()[-1].removeprefix("report ").split("; record ")[0]).read_text()
    assert "σ fit / cal" not in page and "acceptance limits" in page
    for c in SPEC.characteristics:
        assert c.title in page
    assert page.count("<li>") >= len(SPEC.characteristics)
    assert "Which σ the verdict used" in page


# ----- the console's QC panel, from the session's events and the stored record -------------------------
def test_the_console_progress_follows_the_session_and_its_re_prediction():
    """The QC tab renders the session's one progress (rig.session.session_progress), which the
    bus feeds before the tab hears an event."""
    from rig.session.session_progress import SessionProgress

    posted: list[QcProgress] = []
    now = [0.0]                               # the session's clock [s]; the links at 10x
    progress = SessionProgress({"261126l": 100.0, "261126v": 200.0}, lambda: 10.0, lambda: now[0])
    tracker = QcTracker(progress, posted.append)

    def hear(e: Event) -> None:               # the bus: the progress inline, then the tab (queued)
        progress(e)
        tracker(e)

    assert posted[-1].fraction == 0 and posted[-1].rig_left_s == 300 and not posted[-1].predicted_after
    hear(Event(Kind.PHASE, "261126l", {"phase": "moving", "target_mm": 40.0}))
    assert posted[-1].text == "experiment 1 of 2 (261126l): moving"
    now[0] = 5.0                              # 50 rig seconds into l
    hear(Event(Kind.PROGRESS, "261126l", {"phase": "settling", "cycles": 3, "change": {}}))
    assert posted[-1].fraction == pytest.approx(50 / 300) and posted[-1].rig_left_s == pytest.approx(250)
    assert "settling" in posted[-1].text
    now[0] = 30.0                             # longer than its estimate: at most 95 % of it until written
    hear(Event(Kind.PROGRESS, "261126l", {"phase": "capturing", "fraction": 0.5}))
    assert posted[-1].fraction == pytest.approx(95 / 300) and "capturing" in posted[-1].text
    hear(Event(Kind.PHASE, "261126v", {"phase": "moving", "target_mm": 133.0}))   # begun before l is written
    assert posted[-1].fraction == pytest.approx(95 / 300)                           # l still counts
    hear(Event(Kind.EXPERIMENT_DONE, "261126l", {"file": "l.csv", "samples": 1, "lost": 0, "flags": []}))
    # l took 3x its estimate (300 rig s): v is expected longer, as far as l is the session (a third)
    v_left = 200 * (1 + (3 - 1) * 100 / 300)
    assert posted[-1].rig_left_s == pytest.approx(v_left) and posted[-1].fraction == pytest.approx(100 / (100 + v_left))
    assert "experiment 2 of 2" in posted[-1].text
    # A faulty unit: the rest of the plan predicted again from the parameters identified so far.
    hear(Event(Kind.PREDICTION, None, {"rig_time_left_s": 450.0, "basis": "the parameters identified from 261126l",
                                       "message": "…"}))
    tracker.predicted(Prediction(("261126l",), ("damping_force_N",), 450.0))
    assert posted[-1].rig_left_s == pytest.approx(450) and posted[-1].predicted_after == "261126l"
    assert posted[-1].fraction == pytest.approx(100 / 550)
    said = len(posted)
    hear(Event(Kind.LOG, None, {"message": "anything"}))      # nothing the panel shows
    assert len(posted) == said


def test_the_console_table_comes_from_the_stored_record():
    stored = replace(record("SN-0042", "abc"), k=2.0, simulated=True,
                     diagnosis=("Gas precharge too low: a gas leak",))
    outcome = QcOutcome(1, stored, Path("/tmp/x/qc-report.html"), 2.0, "sqlite:///x")
    done = done_from(QcRequest("SN-0042"), outcome, SPEC)
    (row,) = done.rows
    # the gas pressure's "bar" is absolute: the console names it so, as its plots do
    cells = shown(stored, replace(stored.characteristics[0], unit="bar abs."), 2.0)
    assert (row.title, row.value, row.limits, row.acceptance, row.outcome) == (
        cells.title, cells.value, cells.limits, cells.acceptance, "FAIL")
    assert done.shown == "FAIL" and done.simulated and done.causes == ["Gas precharge too low: a gas leak"]
    assert done.retest_periods is None and done.report == Path("/tmp/x/qc-report.html")
    # traceable beside the values: who, which rules (revision and hash), which k
    assert done.trace == (f"Operator {stored.operator} (the login name: no operator typed) · spec "
                          f"{stored.spec_name} revision {stored.spec_version} (sha256 {stored.spec_sha256[:12]}…) · "
                          "values ± kσ with k = 2")
    aborted = replace(stored, verdict=None, status="ABORTED", characteristics=(), reason="session interrupted")
    done = done_from(QcRequest("SN-0042"), QcOutcome(130, aborted, outcome.report, 2.0, "x"), SPEC)
    assert (done.shown, done.exit_code, done.reason, done.rows) == ("ABORTED", 130, "session interrupted", [])


def test_gui_unit_and_fault_go_to_the_simulated_rig_only(capsys):
    args = build_parser().parse_args(["gui", "--simulate", "--unit", "worn-seal", "--fault", "estop@30"])
    assert (args.unit, args.fault) == ("worn-seal", ["estop@30"])
    code = main(["gui", "--unit", "gas-leak", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9"])
    assert code == 2 and "give --simulate too" in capsys.readouterr().err


# ----- the README's worked example ---------------------------------------------------------------------
def test_the_readme_has_a_short_worked_qc_example_that_parses():
    """The README's QC quick start is the worked example (tests/test_docs.py runs it as
    pasted); here: short, every rig command one the parser takes, and the text says which
    report judge writes and which runs are recorded as ABORTED and which write nothing."""
    section = README.read_text().split("## Quick start: quality control")[1].split("\n## ")[0]
    example = section.split("```sh\n")[1].split("```")[0].splitlines()
    assert 4 <= len(example) <= 10
    parser = build_parser()
    for line in example:
        words = line.split("#")[0].split()
        if words[:3] == ["python", "-m", "rig"]:
            parser.parse_args([w for w in words[3:] if w != "&"])
    assert "qc-report-<time>-<uid>.html" in section and "recorded as ABORTED" in section
    assert "writes nothing" in section


def test_records_refuse_any_change_to_where_they_were_measured(tmp_path):
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    db = Records.open(url, create=True)
    db.add(replace(unit(1, 450.0), controller={"model_name": "X"}, daq="DAQ4,SN1,1.0"))
    for statement in ("UPDATE qc_record SET daq = 'DAQ4,SIM'", "UPDATE qc_record SET controller = NULL"):
        with pytest.raises(SQLAlchemyError, match="never changed or deleted"), db.engine.begin() as conn:
            conn.execute(text(statement))
    (r,) = db.find()
    assert (r.controller, r.daq, r.simulated) == ({"model_name": "X"}, "DAQ4,SN1,1.0", False)
    db.close()


def test_a_version_1_database_is_upgraded_without_changing_a_record(tmp_path):
    path = tmp_path / "v1.sqlite"
    db = Records.open(str(path), create=True)
    db.add(unit(1, 450.0))
    db.close()
    with sqlite3.connect(path) as conn:         # back to version 1: its columns, its one version row
        conn.execute("DROP INDEX ix_qc_record_station")
        for added in (ADDED_IN_2, ADDED_IN_3, ADDED_IN_4):
            for table, columns in added.items():
                for column in columns:
                    conn.execute(f"ALTER TABLE {table} DROP COLUMN {column}")
        conn.execute("DROP TABLE qc_release")
        conn.execute("DROP TABLE qc_study")      # version 4's table, with its triggers
        conn.execute("DROP TRIGGER qc_schema_no_update")
        conn.execute("UPDATE qc_schema SET version = 1")
    (r,) = Records.open(str(path)).find()
    assert (r.serial, r.verdict, r.simulated, r.controller, r.daq, r.station) == \
        ("SN-0001", Outcome.PASS, False, None, None, None)
    assert r.characteristics[0].value == 450.0 and r.characteristics[0].title is None
    with sqlite3.connect(path) as conn:
        assert sorted(v for (v,) in conn.execute("SELECT version FROM qc_schema")) == [1, 2, 3, 4, 5]
        # the study table is back, and as immutable as the records
        assert {n for (n,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'trigger'")} >= \
            {"qc_study_no_update", "qc_study_no_delete"}
