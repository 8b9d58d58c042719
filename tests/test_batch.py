"""identify batch on a LocalCluster of 2 single-threaded workers: 30 generated sessions
identified within 3 σ of their truths, a corrupt one failing alone, a rerun that fits
nothing, and a worker killed mid-batch without a result lost or written twice.  With
--db, the sessions that have a QC record are re-judged in the records database, once.

The sessions are small (experiments h and j, 3 periods at 1 kHz, n = 400) and generated
once for the module, on the same cluster; those of --db are production units on the
default QC spec's plan."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from identify import batch, sinks
from identify.cli import main
from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import STANDARD_SET, select
from rig.qc.records import Records
from rig.qc.run import qc_judge
from rig.qc.spec import load_spec
from simulator.generate import generate
from simulator.physics import Damper
from simulator.truth import load_truth

ESTIMATE = ("theta4", "theta6", "theta16")
N_SESSIONS = 30
CORRUPT = "unit-corrupt"


def truth(i: int) -> dict[str, float]:
    """A unit of the fleet: nominal but for the estimated parameters, each within ±20 %
    (the batch starts every session from one START, so the fixed ones must be right)."""
    rng = np.random.default_rng(7_000 + i)
    theta = Parameters(load_model("2dof")).as_dict()
    return theta | {k: theta[k] * rng.uniform(0.8, 1.2) for k in ESTIMATE}


@pytest.fixture(scope="module")
def client():
    with batch.connect(workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def sessions(client, tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("sessions")
    folders = [root / f"unit-{i:02d}" for i in range(N_SESSIONS)]
    plan = select(STANDARD_SET, ["h", "j"])
    client.gather(client.map(lambda folder, i: generate(folder, plan, Damper(truth(i), "2dof"), periods=3,
                                                        rate_hz=1000.0, seed=i),
                             folders, range(N_SESSIONS), pure=False))
    for i, folder in enumerate(folders):
        manifest = json.loads((folder / "dataset.json").read_text())
        manifest["unit"]["serial"] = f"SN-{i:04d}"
        (folder / "dataset.json").write_text(json.dumps(manifest))
    corrupt = shutil.copytree(folders[0], root / CORRUPT)
    csv_file = next(corrupt.glob("*j.csv"))
    lines = csv_file.read_text().splitlines()
    cells = lines[6].split(",")
    cells[1] = "nan"                                      # line 7, column stroke_mm
    lines[6] = ",".join(cells)
    csv_file.write_text("\n".join(lines) + "\n")
    return [*folders, corrupt]


@pytest.fixture(scope="module")
def settings() -> batch.FitSettings:
    return batch.FitSettings.resolve("2dof", None, list(ESTIMATE), n=400)


@pytest.fixture(scope="module")
def first_run(client, sessions, settings, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    rows = batch.run_batch(client, batch.check_sessions(sessions), settings, out)
    return out, rows


def read_summary(out: Path) -> list[dict[str, str]]:
    with (out / "summary.csv").open() as f:
        return list(csv.DictReader(f))


def test_every_session_is_identified_within_3_sigma_of_its_truth(first_run):
    out, rows = first_run
    good = [r for r in rows if r.session != CORRUPT]
    assert [r.session for r in good] == [f"unit-{i:02d}" for i in range(N_SESSIONS)]
    assert all(r.status == "ok" and r.converged for r in good), [r.status for r in good]
    z = np.array([[(r.values[k] - truth(i)[k]) / r.stds[k] for k in ESTIMATE] for i, r in enumerate(good)])
    assert np.all(np.abs(z) < 3), z
    assert [r.serial for r in good] == [f"SN-{i:04d}" for i in range(N_SESSIONS)]
    doc = json.loads((out / "unit-07.json").read_text())
    assert doc["converged"] and doc["parameters"]["theta4"]["value"] == good[7].values["theta4"]
    assert doc["batch"]["status"] == "ok" and len(doc["batch"]["key"]) == 64


def test_a_corrupt_session_fails_alone_with_its_reason(first_run, sessions):
    out, rows = first_run
    failed = [r for r in rows if r.failed]
    assert [r.session for r in failed] == [CORRUPT]
    assert failed[0].status.startswith(f"failed: {sessions[-1]}/")
    assert failed[0].status.endswith(".csv: line 7, column 'stroke_mm': 'nan' is not a finite number")
    summary = read_summary(out)
    assert list(summary[0]) == ["session", "serial", "status", "converged", "fit_s",
                                *[c for k in ESTIMATE for c in (k, f"{k}_std")], "std_from"]
    assert [s["session"] for s in summary] == [r.session for r in rows]
    assert summary[-1]["status"] == failed[0].status and summary[-1]["theta4"] == "" and summary[-1]["std_from"] == ""
    assert all(s["status"] == "ok" and s["converged"] == "True" and float(s["theta4_std"]) > 0 for s in summary[:-1])


def test_the_summary_quotes_the_residual_based_std_where_the_residuals_exceed_the_noise(tmp_path):
    """A result with model error carries both stds; the noise's understates the
    uncertainty (a unit whose fixed parameters are off: 120x), so the row quotes the
    residual-based one and says so, as the fit's report does."""
    def result(std_residual: float | None) -> dict:
        p = {"value": 0.82, "std": 1.7e-4, "estimated": True}
        return {"converged": True, "batch": {"serial": "U001", "fit_s": 0.2},
                "parameters": {"theta16": p | ({"std_residual": std_residual} if std_residual else {})}}

    rows = [batch._outcome(tmp_path / "model-error", result(0.0197), "ok"),
            batch._outcome(tmp_path / "clean", result(None), "ok")]
    assert [(r.stds["theta16"], r.residual_std) for r in rows] == [(0.0197, True), (1.7e-4, False)]
    summary = list(csv.DictReader(io.StringIO(batch.summary_csv(rows, ["theta16"]).decode())))
    assert [(s["theta16_std"], s["std_from"]) for s in summary] == [("0.0197", "residuals"), ("0.00017", "noise")]


def test_a_second_run_fits_nothing_that_is_done(first_run, client, sessions, settings):
    out, rows = first_run
    good = [out / f"{p.name}.json" for p in sessions[:-1]]
    before = [(p.stat().st_ino, p.stat().st_mtime_ns) for p in good]
    again = batch.run_batch(client, batch.check_sessions(sessions), settings, out)
    assert [r.status for r in again[:-1]] == ["skipped"] * N_SESSIONS
    assert [(p.stat().st_ino, p.stat().st_mtime_ns) for p in good] == before   # not one result rewritten
    assert [r.values for r in again[:-1]] == [r.values for r in rows[:-1]]
    assert again[-1].failed                                                    # only converged fits count as done
    assert [s["status"] for s in read_summary(out)] == ["skipped"] * N_SESSIONS + [again[-1].status]


def test_a_retried_task_reuses_what_its_first_attempt_wrote(sessions, settings, tmp_path):
    first = batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-1")
    written = (tmp_path / "unit-00.json").stat()
    retry = batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-1")
    later = batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-2")
    assert (first.status, retry.status, later.status) == ("ok", "ok", "skipped")
    assert retry == first and later.values == first.values
    assert (tmp_path / "unit-00.json").stat().st_mtime_ns == written.st_mtime_ns
    assert sorted(p.name for p in tmp_path.iterdir()) == ["unit-00.json"]


def test_changed_data_or_settings_are_fitted_again(sessions, settings, tmp_path):
    session = Path(shutil.copytree(sessions[1], tmp_path / "unit-01"))
    out = tmp_path / "out"
    assert batch.fit_session(str(session), settings, str(out), "a").status == "ok"
    other = batch.FitSettings.resolve("2dof", None, ["theta4", "theta6"], n=400)
    assert batch.fit_session(str(session), other, str(out), "b").status == "ok"
    csv_file = next(session.glob("*h.csv"))
    os.utime(csv_file, ns=(0, 0))                        # touched, not changed: the digest says so
    assert batch.fit_session(str(session), other, str(out), "c").status == "skipped"
    lines = csv_file.read_text().splitlines()
    cells = lines[-1].split(",")
    cells[1] = f"{float(cells[1]) + 0.01:.9g}"           # one sample 10 µm off
    csv_file.write_text("\n".join(lines[:-1] + [",".join(cells)]) + "\n")
    assert batch.fit_session(str(session), other, str(out), "d").status == "ok"
    assert batch.fit_session(str(session), other, str(out), "e").status == "skipped"
    # While size and modification time are those stored, the data are not read again
    # (a resumed batch of 100,000 sessions must not re-read terabytes): an edit that
    # keeps both is, by design, not seen.
    before = csv_file.stat()
    csv_file.write_text(csv_file.read_text().replace(cells[1], cells[1][:-1] + ("1" if cells[1][-1] != "1" else "2")))
    os.utime(csv_file, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert csv_file.stat().st_size == before.st_size
    assert batch.fit_session(str(session), other, str(out), "f").status == "skipped"


def test_a_worker_with_another_model_version_fails_its_sessions_with_that_reason(sessions, settings, tmp_path):
    client_side = dataclasses.replace(settings, model_version="0123456789abcdef0123")
    outcome = batch.fit_session(str(sessions[2]), client_side, str(tmp_path), "a")
    assert outcome.status.startswith(f"failed: model '2dof' on this worker is version {settings.model_version}, "
                                     "the client's is 0123456789abcdef0123")
    assert json.loads((tmp_path / "unit-02.json").read_text())["converged"] is False
    # The state is data, in the outcome and in the stored result; the sentence is rendered from it.
    assert (outcome.state, outcome.failed) == (batch.BatchState.FAILED, True)
    assert outcome.status == f"failed: {outcome.reason}"
    stored = json.loads((tmp_path / "unit-02.json").read_text())["batch"]
    assert (stored["state"], stored["reason"], stored["status"]) == ("failed", outcome.reason, outcome.status)


def test_a_result_is_skipped_on_its_stored_state_and_an_older_one_on_its_bare_ok(sessions, settings, tmp_path):
    first = batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-1")
    assert first.state is batch.BatchState.OK and first.reason == "" and not first.failed
    path = tmp_path / "unit-00.json"
    doc = json.loads(path.read_text())
    doc["batch"]["status"] = "ok, reworded"           # the sentence is not read back
    path.write_text(json.dumps(doc))
    assert batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-2").state is batch.BatchState.SKIPPED
    for key in ("state", "reason"):                   # written before the state was stored
        del doc["batch"][key]
    doc["batch"]["status"] = "ok"
    path.write_text(json.dumps(doc))
    assert batch.fit_session(str(sessions[0]), settings, str(tmp_path), "run-3").state is batch.BatchState.SKIPPED


def test_a_sink_written_with_the_state_words_still_delivers_enums():
    from identify.sinks import Delivery, DeliveryState

    assert Delivery("written", "PASS").state is DeliveryState.WRITTEN
    assert batch.SessionOutcome("s", "", "skipped").state is batch.BatchState.SKIPPED


def test_killing_a_worker_mid_batch_still_yields_every_result_exactly_once(client, sessions, settings, tmp_path):
    chosen = sessions[:10]                                 # enough to be mid-batch at the first result
    pids = client.run(os.getpid)
    killed = []  # (worker, the keys it was processing)

    def kill_a_busy_worker(outcome: batch.SessionOutcome) -> None:
        if killed:
            return
        busy = {w: keys for w, keys in client.processing().items() if keys}
        worker, keys = next(iter(busy.items()))
        os.kill(pids[worker], signal.SIGKILL)
        killed.append((worker, keys))

    rows = batch.run_batch(client, batch.check_sessions(chosen), settings, tmp_path, kill_a_busy_worker)
    assert killed and killed[0][1], "no worker was busy when one was killed"
    assert killed[0][0] not in client.scheduler_info()["workers"]             # it died; the nanny started another
    assert [r.session for r in rows] == [p.name for p in chosen]
    assert [r.status for r in rows] == ["ok"] * len(chosen)
    # (a worker killed inside atomic_write_bytes may leave a hidden .tmp file: never a result)
    assert sorted(p.name for p in tmp_path.glob("*.json")) == sorted(f"{p.name}.json" for p in chosen)
    assert [s["session"] for s in read_summary(tmp_path)] == [p.name for p in chosen]
    # the restarted worker too runs without Dask's MALLOC_TRIM_THRESHOLD_ (a fit took 1.7x the CPU with it)
    assert set(client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_")).values()) == {None}


# ------------------------------------------------------------------------------------------
# The command line


def test_the_command_runs_a_list_on_the_plants_scheduler(client, sessions, tmp_path):
    client.wait_for_workers(2)                            # a worker killed above may still be restarting
    listing = tmp_path / "sessions.txt"
    listing.write_text(f"# two units\n{sessions[2]}\n\n{os.path.relpath(sessions[3], tmp_path)}  # relative\n")
    proc = subprocess.run([sys.executable, "-m", "identify", "batch", "--list", str(listing), "--model", "2dof",
                           "--estimate", "area,volume_slope,heat_transfer", "--n", "400", "--out",
                           str(tmp_path / "out"), "--scheduler", client.scheduler.address],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "2 sessions: 2 ok, 0 failed, 0 skipped" in proc.stdout
    assert "unit-02" in proc.stdout and "SN-0003" in proc.stdout
    assert "in 2 sessions on 2 workers" in proc.stderr
    assert [s["session"] for s in read_summary(tmp_path / "out")] == ["unit-02", "unit-03"]


# ------------------------------------------------------------------------------------------
# --db: re-judgements in the QC records database

QC_SPEC = load_spec("default")
QC_UNITS = {"good-3": ("good", 3), "leak-4": ("gas-leak", 4), "good-5": ("good", 5)}  # good-5 has no record


@pytest.fixture(scope="module")
def qc_station(client, tmp_path_factory) -> tuple[list[Path], Path]:
    """Three units measured on the default spec's plan; the first two judged by `qc judge`
    into a records database (its first records), the third never judged."""
    root = tmp_path_factory.mktemp("station")
    folders = [root / name for name in QC_UNITS]
    plan = list(QC_SPEC.plan.experiments)
    client.gather(client.map(lambda folder, unit, seed: generate(folder, plan, load_truth(None, "2dof", unit, seed),
                                                                 periods=None, seed=seed, date="261122",
                                                                 serial=f"SN-{seed:04d}"),
                             folders, *zip(*QC_UNITS.values(), strict=True), pure=False))
    db = root / "records.sqlite"
    Records.open(str(db), create=True).close()   # one process creates the schema; the judges write side by side
    verdicts = client.gather(client.map(lambda folder: qc_judge(folder, "default", str(db), "qe"), folders[:2],
                                        pure=False))
    assert verdicts == [0, 1]      # PASS, FAIL (gas leak)
    with sqlite3.connect(db) as conn, sqlite3.connect(root / "first-records.sqlite") as copy:
        conn.backup(copy)          # the first records alone, whatever the tests then add to db
    (root / "results").mkdir()     # the batch's results, shared: a test after the first fits nothing again
    return folders, db


def _batch_db(client, sessions: list[Path], out: Path, db: str, *estimate: str) -> subprocess.CompletedProcess[str]:
    client.wait_for_workers(2)     # a worker killed above may still be restarting
    return subprocess.run([sys.executable, "-m", "identify", "batch", *map(str, sessions), "--estimate",
                           ",".join(estimate or QC_SPEC.estimate), "--n", "800", "--out", str(out), "--db", db,
                           "--scheduler", client.scheduler.address], capture_output=True, text=True, timeout=300)


def test_db_adds_a_rejudgement_that_refers_to_the_first_record_once(client, qc_station, tmp_path):
    folders, db = qc_station
    proc = _batch_db(client, folders, db.parent / "results", str(db))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (f"QC records in sqlite:///{db}: 2 sessions re-judged (1 FAIL, 1 PASS), 0 re-judged before, "
            "1 without a QC record, 0 not re-judged, 0 failed") in proc.stdout, proc.stdout
    records = Records.open(str(db))
    found = records.find()
    firsts = {r.serial: r for r in found[:2]}             # judged side by side: in either order
    new = sorted(found[2:], key=lambda r: r.serial)       # written in the order the results arrived
    assert [(r.serial, r.verdict, r.rejudges) for r in new] == [("SN-0003", "PASS", firsts["SN-0003"].uid),
                                                                 ("SN-0004", "FAIL", firsts["SN-0004"].uid)]
    for r in new:
        first = firsts[r.serial]
        assert (r.data_sha256, r.spec_sha256, r.status) == (first.data_sha256, QC_SPEC.sha256, "COMPLETE")
        assert any(n.startswith("identified by identify batch: result key ") for n in r.notes), r.notes
        # The batch fitted what qc judge fits (model, estimated set, start, grid): the same
        # numbers, σ propagated from the stored covariance (the residual-based one for the leak)
        for c, d in zip(first.characteristics, r.characteristics, strict=True):
            assert (d.name, d.outcome) == (c.name, c.outcome)
            assert d.value == pytest.approx(c.value, rel=1e-9) and d.std_fit == pytest.approx(c.std_fit, rel=1e-6)
    assert not list(folders[2].glob("qc-record*"))        # nothing written into a session folder by the batch

    again = _batch_db(client, folders, db.parent / "results", str(db))
    assert again.returncode == 0, again.stdout + again.stderr
    assert "3 sessions: 0 ok, 0 failed, 3 skipped" in again.stdout
    assert "0 sessions re-judged, 2 re-judged before (1 FAIL, 1 PASS), 1 without a QC record" in again.stdout
    assert len(records.find()) == 4                       # no duplicate of the same result
    records.close()


def test_db_re_judges_only_where_the_spec_applies_and_reports_what_it_could_not_write(client, qc_station,
                                                                                     tmp_path):
    folders, db = qc_station
    pristine = shutil.copy(db.parent / "first-records.sqlite", tmp_path / "records.sqlite")
    other = _batch_db(client, folders[:1], tmp_path / "other", str(pristine), "theta3", "theta5", "theta6")
    assert other.returncode == 0, other.stdout + other.stderr
    assert "0 sessions re-judged, 0 re-judged before, 0 without a QC record, 1 not re-judged, 0 failed" in other.stdout
    assert ("1 not re-judged (good-3): spec default 1.3.0 estimates theta15, theta3, theta5, theta6, theta8; "
            "the batch theta3, theta5, theta6") in other.stdout

    with sqlite3.connect(pristine) as conn:               # a database that refuses every new record
        conn.execute("CREATE TRIGGER full BEFORE INSERT ON qc_record BEGIN SELECT RAISE(ABORT, 'disk full'); END")
    refused = _batch_db(client, folders, db.parent / "results", str(pristine))
    assert refused.returncode == 1, refused.stdout + refused.stderr
    assert {s["status"] for s in read_summary(db.parent / "results")} <= {"ok", "skipped"}   # the fits did not fail
    assert "0 sessions re-judged, 0 re-judged before, 1 without a QC record, 0 not re-judged, 2 failed" \
        in refused.stdout
    for name in ("good-3", "leak-4"):
        assert f"{name}: not written to sqlite:///{pristine}: records database sqlite:///{pristine} refused the " \
               "record: disk full" in refused.stdout
    assert "Traceback" not in refused.stdout + refused.stderr


def test_identify_imports_no_rig():
    """rig uses identify, never the other way: the batch finds the records sink by entry point."""
    code = ("import sys, identify.cli, identify.batch, identify.sinks; "
            "print(sorted(m for m in sys.modules if m == 'rig' or m.startswith('rig.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("args, message", [
    ([], "no sessions: name session folders or give --list FILE"),
    (["--list", "{tmp}/missing.txt"], "missing.txt: session list not found"),
    (["{tmp}/a/unit", "{tmp}/b/unit"], "share the folder name 'unit'"),
    (["{tmp}/a/unit", "--model", "3dof"], "unknown model '3dof'"),
    (["{tmp}/a/unit", "--estimate", "theta4,theta99"], "model '2dof' has no parameter 'theta99'"),
    (["{tmp}/a/unit", "--params", "{tmp}/nope.json"], "nope.json: parameter file not found"),
    (["{tmp}/a/unit", "--scheduler", "nonsense"], "'nonsense': not a scheduler address"),
    (["{tmp}/a/unit", "--scheduler", "tcp://127.0.0.1:{port}"], "cannot reach the scheduler"),
    (["{tmp}/a/unit", "--workers", "0"], "--workers must be at least 1, got 0"),
])
def test_bad_input_is_one_line_and_exit_2(args, message, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, port=_closed_port()) for a in args]
    if "--estimate" not in argv:
        argv += ["--estimate", "theta4"]
    assert main(["batch", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("db, message", [
    ("{tmp}/missing.sqlite", "--db: records database sqlite:///{tmp}/missing.sqlite does not exist"),
    ("sqlite:///{tmp}/missing.sqlite", "does not exist (qc run creates it"),
    ("{tmp}/plain.sqlite", "--db: sqlite:///{tmp}/plain.sqlite is not a QC records database (no qc_schema table)"),
    ("mysql://qe@db.plant/qc", "unsupported database 'mysql' (sqlite or postgresql)"),
    ("postgresql://qe:s3cret@127.0.0.1:{port}/qc", "--db postgresql://qe:***@127.0.0.1"),
    ("postgresql://qe:s3cret@127.0.0.1:{port}/qc", "must not carry the password"),
    ("postgresql://qe@127.0.0.1:{port}/qc", "--db: records database postgresql+psycopg://qe@127.0.0.1"),
])
def test_a_database_that_is_not_there_is_one_line_and_exit_2_before_any_fit(db, message, tmp_path, capsys):
    sqlite3.connect(tmp_path / "plain.sqlite").close()    # an SQLite file, but no one's QC records
    port = _closed_port()
    argv = ["batch", str(tmp_path / "a" / "unit"), "--estimate", "theta4", "--out", str(tmp_path / "out"),
            "--db", db.format(tmp=tmp_path, port=port)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message.format(tmp=tmp_path) in err, err
    assert "s3cret" not in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "missing.sqlite").exists()


def test_without_the_records_sink_installed_db_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sinks, "GROUP", "identify.result_sinks.none")   # as if identify were installed alone
    db = tmp_path / "records.sqlite"
    Records.open(str(db), create=True).close()
    assert main(["batch", str(tmp_path / "unit"), "--estimate", "theta4", "--out", str(tmp_path / "out"),
                 "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert err == ("error: --db: no result sink 'db' is installed (entry point group identify.result_sinks.none); "
                   "it comes with the damper-rig project's rig package: install the project, not identify alone\n")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value, std, text", [
    (0.85006, 6.0e-5, "0.850060(60)"), (0.0049999994, 9.01e-9, "0.0049999994(90)"),
    (-3.0000003, 4.58e-6, "-3.0000003(46)"), (1234.4, 37.0, "1234(37)"), (2.5e-12, 1.3e-14, "2.500(13)e-12"),
    (0.85, 0.0996, "0.85(10)"), (5.0, 9.96, "5(10)"), (12.0, None, "12"), (0.5, 0.0, "0.5"),
])
def test_value_and_std_in_concise_notation(value, std, text):
    from identify.notation import concise

    assert concise(value, std) == text


def test_the_batch_table_fits_an_80_column_terminal(monkeypatch, capsys):
    """Three parameters with their stds, a serial and a session name: no cell folded or
    cut, every line within 80 columns (it folded each cell over three lines), with the
    widest values a demo session gives and a row whose stds are residual-based (marked)."""
    from identify.cli import _batch_table

    monkeypatch.setenv("COLUMNS", "80")
    values = {"theta4": 0.0050000155, "theta6": -2.9999986, "theta16": 0.849982}
    stds: dict[str, float | None] = {"theta4": 6.7e-9, "theta6": 3.6e-6, "theta16": 6.0e-5}
    rows = [batch.SessionOutcome(f"SN-2026-00{i}", "", "ok", "SIM-0001", True, 0.43, values, stds) for i in range(3)]
    rows.append(batch.SessionOutcome("demo-session", "", "ok", "SIM-0002", True, 1.07,
                                     {"theta4": 0.00512, "theta6": -2.91, "theta16": 0.821},
                                     {"theta4": 3.3e-5, "theta6": 0.011, "theta16": 0.0197}, residual_std=True))
    rows.append(batch.SessionOutcome("SN-2026-009", "", batch.BatchState.FAILED,
                                     reason="SN-2026-009/261122h.csv: line 7: not a number"))
    _batch_table(rows, ESTIMATE)
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) <= 80, out
    for cell in ("SN-2026-001", "SIM-0001", "0.0050000155(67)", "-2.9999986(36)", "0.849982(60)", "0.43",
                 "demo-session", "0.005120(33)*", "0.821(20)*", "1.07", "residual-based"):
        assert cell in out, (cell, out)
    assert "SN-2026-009: failed: SN-2026-009/261122h.csv: line 7: not a number" in out
