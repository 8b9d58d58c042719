"""QC records an auditor trusts (issue 44), against one throwaway PostgreSQL server:

- least privilege: the schema is the administrator's; a station's role cannot UPDATE,
  DELETE, TRUNCATE or disable a trigger, and ``qc run`` refuses a role that owns the tables;
- the per-station hash chain: ``qc history --verify`` finds a record the administrator
  changed, deleted or inserted (PostgreSQL and SQLite);
- commissioning: a wrong database port fails ``station check`` and ``qc run`` then refuses;
  a queue older than its limit warns on the next run; a queued record goes to the database
  it was queued for;
- who did what: ``qc judge`` on a PostgreSQL station with station.toml only records the
  re-judging operator and why; ``qc release`` needs a second person; a PIN identifies;
- the report: station, operator as identified, software, equipment, ambient, a flagged
  capture, an archive id and no machine path, page numbers and the running head.
"""

from __future__ import annotations

import datetime as _dt
import getpass
import hashlib
import json
import re
import sqlite3
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import psycopg
import pytest

from rig.cli import main
from rig.qc.commissioning import Commissioning, Configuration, Item, NotCommissioned, require_commissioned, write
from rig.qc.evaluate import evaluate
from rig.qc.queue import RecordQueue, queue_warning
from rig.qc.records import ADDED_IN_4, QcRecord, Records, TooPrivileged, init_schema, parse_url, safe_url
from rig.qc.report import render_report
from rig.qc.run import judged_record
from rig.qc.spec import load_spec
from rig.qc.station import StationConfigError, identify_operator, load_station_config, pin_hash
from rig.qc.trace import trace_session
from simulator.generate import generate
from simulator.truth import load_truth
from tests.pgserver import STATION_PASSWORD, pg_server  # noqa: F401 — the fixture
from tests.stations import make_station
from tests.test_qc_records import record

SPEC = load_spec("default")


@pytest.fixture
def rig_qc(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch):
    """``python -m rig qc …`` in this process (the interpreter's start is most of a
    command's time here): its exit status, stdout and stderr."""
    def run(*args: str, env: dict[str, str] | None = None) -> SimpleNamespace:
        capsys.readouterr()
        with monkeypatch.context() as m:
            for k, v in (env or {}).items():
                m.setenv(k, v)
            code = main(["qc", *args])
        out = capsys.readouterr()
        return SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err)

    return run


def chained(records: Records, station: str, n: int, tag: str) -> list[QcRecord]:
    for i in range(n):
        assert records.add(replace(record(f"SN-{i:04d}", f"{tag}-{i}"), station=station))
    return [r for r in records.find() if r.station == station]


def station_connection(pg, database: str) -> psycopg.Connection:
    return psycopg.connect(host="127.0.0.1", port=pg.port, user="station", password=STATION_PASSWORD,
                           dbname=database, autocommit=True)


def admin_connection(pg, database: str) -> psycopg.Connection:
    return psycopg.connect(host="127.0.0.1", port=pg.port, user=pg.user, password=pg.password, dbname=database,
                           autocommit=True)


# ----- least privilege and the chain ------------------------------------------------------------------------
def test_a_station_role_can_only_insert_and_read_and_verify_finds_what_the_administrator_did(pg_server, rig_qc):  # noqa: F811
    url = pg_server.records_database("audit")
    records = Records.open(url, password=STATION_PASSWORD, writer=True)     # a station's writer is accepted
    written = chained(records, "line1-A", 4, "pg")
    chained(records, "line1-B", 2, "pgb")
    records.close()
    assert [r.previous_sha256 for r in written[1:]] == [r.record_sha256 for r in written[:-1]]
    assert written[0].previous_sha256 is None
    with station_connection(pg_server, "audit") as conn:
        for statement in ("UPDATE qc_record SET verdict = 'PASS'", "DELETE FROM qc_record",
                          "TRUNCATE qc_record CASCADE", "ALTER TABLE qc_record DISABLE TRIGGER USER",
                          "DELETE FROM qc_characteristic", "UPDATE qc_schema SET version = 9"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                conn.execute(statement)
    r = rig_qc("history", "--db", url, "--verify", env={"PGPASSWORD": STATION_PASSWORD})
    assert r.returncode == 0 and "6 records of 2 stations checked" in r.stdout and r.stdout.endswith(": intact\n")
    # The administrator owns the tables: it can switch the triggers off and rewrite. The chain sees it.
    with admin_connection(pg_server, "audit") as conn:
        conn.execute("ALTER TABLE qc_record DISABLE TRIGGER USER")
        conn.execute("ALTER TABLE qc_characteristic DISABLE TRIGGER USER")
        conn.execute("UPDATE qc_record SET verdict = 'PASS' WHERE uid = 'pg-1'")
        conn.execute("DELETE FROM qc_characteristic WHERE record_id = (SELECT id FROM qc_record WHERE uid = 'pgb-0')")
        conn.execute("DELETE FROM qc_record WHERE uid = 'pgb-0'")
        conn.execute("ALTER TABLE qc_record ENABLE TRIGGER USER")
        conn.execute("ALTER TABLE qc_characteristic ENABLE TRIGGER USER")
    r = rig_qc("history", "--db", url, "--verify", env={"PGPASSWORD": STATION_PASSWORD})
    assert r.returncode == 1, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("record pg-1 (unit SN-0001, station line1-A) changed after it was written")
    assert lines[1].startswith("record pgb-1 (unit SN-0001, station line1-B) does not follow its predecessor")
    assert lines[-1].endswith(": 2 problems")


def test_qc_run_refuses_a_role_that_owns_the_tables_and_station_check_says_why(pg_server, tmp_path, rig_qc):  # noqa: F811
    admin = pg_server.create_database("owned")
    with admin_connection(pg_server, "postgres") as conn:
        conn.execute("CREATE ROLE owner LOGIN PASSWORD 'Own3r-pw'")
        conn.execute("GRANT ALL ON DATABASE owned TO owner")
    with admin_connection(pg_server, "owned") as conn:
        conn.execute("GRANT CREATE ON SCHEMA public TO owner")
    owner = pg_server.url(database="owned", user="owner")
    station = make_station(tmp_path / "station", "line9-Z", owner, "Own3r-pw")
    check = ("station", "check", "--out", str(station), "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9")
    r = rig_qc(*check)                             # no schema yet: a station does not make one
    assert r.returncode == 1
    (line,) = [s for s in r.stdout.splitlines() if "schema version" in s]
    assert line.startswith("FAIL  schema version:") and "an administrator makes it" in line
    init_schema(owner, password="Own3r-pw")       # the first run's way before: the station's user made the tables
    assert admin                                   # (the database made by the administrator, the tables by the owner)
    r = rig_qc("run", "--serial", "SN-0001", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9",
               "--out", str(tmp_path / "bench"), "--db", owner, env={"PGPASSWORD": "Own3r-pw"})
    assert r.returncode == 2, r.stderr
    (line,) = r.stderr.splitlines()
    assert "role owner owns qc_record, qc_characteristic, qc_schema, qc_release" in line
    assert "INSERT and SELECT only" in line and "Own3r-pw" not in line
    with pytest.raises(TooPrivileged, match="is a superuser"):   # the administrator is no station either
        Records.open(pg_server.url(database="owned"), password=pg_server.password, writer=True)
    r = rig_qc(*check)
    assert r.returncode == 1
    assert any(s.startswith("FAIL  database rights: records database") for s in r.stdout.splitlines())


def test_verify_finds_a_changed_a_deleted_and_an_inserted_record_in_sqlite(tmp_path, rig_qc):
    path = tmp_path / "r.sqlite"
    records = Records.open(str(path), create=True)
    chained(records, "s", 5, "sq")
    records.close()
    with sqlite3.connect(path) as conn:     # the file's owner may drop the triggers; the chain remains
        conn.execute("DROP TRIGGER qc_record_no_update")
        conn.execute("DROP TRIGGER qc_record_no_delete")
        conn.execute("UPDATE qc_record SET operator = 'someone else' WHERE uid = 'sq-1'")
        conn.execute("DELETE FROM qc_record WHERE uid = 'sq-3'")
        conn.execute("INSERT INTO qc_record (uid, serial, operator, rig, judged, software, spec_name, spec_version, "
                     "spec_sha256, status, session, data_sha256, files, diagnosis, notes, simulated, station) "
                     "SELECT 'forged', serial, operator, rig, judged, software, spec_name, spec_version, spec_sha256, "
                     "status, session, 'forged', files, diagnosis, notes, simulated, station FROM qc_record "
                     "WHERE uid = 'sq-4'")
    r = rig_qc("history", "--db", str(path), "--verify")
    assert r.returncode == 1
    found = {line.split()[1]: line for line in r.stdout.splitlines() if line.startswith("record ")}
    assert "changed after it was written" in found["sq-1"]
    assert "does not follow its predecessor" in found["sq-4"]        # sq-3 before it is gone
    assert "has no hash although its station's chain had begun" in found["forged"]


# ----- commissioning and the queue ----------------------------------------------------------------------------
def test_a_wrong_database_port_fails_commissioning_and_the_station_then_refuses_to_test(pg_server, tmp_path, rig_qc):  # noqa: F811
    wrong = pg_server.url(database="audit", user="station").replace(f":{pg_server.port}/", ":9/")
    station = make_station(tmp_path / "station", "line1-C", wrong, STATION_PASSWORD)
    r = rig_qc("station", "check", "--out", str(station), "--shaker", "tcp://127.0.0.1:9", "--daq",
               "socket://127.0.0.1:9")
    assert r.returncode == 1
    (db_line,) = [s for s in r.stdout.splitlines() if "database reachable" in s]
    assert db_line.startswith("FAIL  database reachable:") and "Connection refused" in db_line
    assert r.stdout.splitlines()[-1].startswith("station line1-C: commissioning FAILED")
    assert json.loads((station / "commissioning.json").read_text())["passed"] is False
    r = rig_qc("run", "--serial", "SN-0001", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9",
               "--out", str(station))
    assert r.returncode == 2
    (line,) = r.stderr.splitlines()
    assert "its commissioning of" in line and "failed (database reachable, controller, DAQ)" in line
    assert not [p for p in station.iterdir() if p.is_dir()]        # nothing started, nothing queued


def test_a_queue_older_than_its_limit_warns_on_the_next_run_and_keeps_its_database(tmp_path, rig_qc):
    bench = tmp_path / "bench"
    down = "postgresql://station@127.0.0.1:9/qc"
    old = replace(record("SN-0001", "queued-1"),
                  judged=(_dt.datetime.now(_dt.UTC) - _dt.timedelta(hours=30)).isoformat(timespec="seconds"))
    RecordQueue(bench).put(old, safe_url(parse_url(down)))
    warning = queue_warning(bench)                                   # the console's: data
    assert warning is not None and warning.count == 1 and 29.9 < warning.oldest_h < 30.1
    r = rig_qc("run", "--serial", "SN-0002", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9",
               "--out", str(bench), "--db", down)
    assert r.returncode == 3                                          # no rig there: after the warning
    assert "warning: 1 record queued in" in r.stderr and "the oldest 30.0 h (limits: 24 h, 20 records)" in r.stderr
    # Sent to the database it was queued for only: a station now naming another one asks.
    r = rig_qc("sync", "--out", str(bench))
    assert r.returncode == 3 and "not asked (no terminal); --send-to-current sends them" in r.stderr
    assert "records queued for postgresql+psycopg://station@127.0.0.1:9/qc are not sent" in r.stderr
    r = rig_qc("sync", "--out", str(bench), "--send-to-current")
    assert r.returncode == 0 and "1 queued record sent to sqlite:///" in r.stderr
    (sent,) = (bench / "qc-queue" / "sent").iterdir()
    assert json.loads(sent.read_text())["queued_for"].startswith("sqlite:///")   # the copy says where it went
    # qc history of a station whose database is down says so and lists what is queued
    RecordQueue(bench).put(replace(old, uid="queued-2"), safe_url(parse_url(down)))
    make_station(bench, "bench-1", down)
    r = rig_qc("history", "--out", str(bench))
    assert r.returncode == 3 and "cannot be read now; 1 record of station" in r.stderr
    assert "SN-0001  FAIL  record queued-2  for postgresql+psycopg://station@127.0.0.1:9/qc" in r.stdout


# ----- who did what -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def unit(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generated unit's data in a station folder (sessions lie in their station's folder)."""
    station = tmp_path_factory.mktemp("pg-station")
    return generate(station / "SN-0031-x", list(SPEC.plan.experiments), load_truth(None, "2dof", "good", 31),
                    periods=None, seed=31, date="261128", serial="SN-0031")


def test_a_rejudgement_on_a_postgresql_station_records_who_rejudged_and_why(pg_server, unit, rig_qc):  # noqa: F811
    url = pg_server.records_database("rejudged")
    station = make_station(unit.parent, "line2-A", url, STATION_PASSWORD)
    records = Records.open(url, password=STATION_PASSWORD, writer=True)
    first = judged_record(SPEC, trace_session(unit), evaluate(SPEC, unit), "", None, serial="SN-0031",
                          operator="A. Original", rig="rig-1", started=None, finished=None, station="line2-A",
                          identified_by="login")
    assert records.add(first)
    records.close()
    r = rig_qc("release", "SN-0031", "--out", str(station))          # a second person: the login here
    assert r.returncode == 0 and f"released by {getpass.getuser()} (login)" in r.stdout, r.stderr
    r = rig_qc("judge", str(unit), "--reason", "spec 1.2.0 replaced the hand-chosen plan")   # station.toml only
    assert r.returncode == 0, r.stderr
    docs = json.loads(rig_qc("history", "--out", str(station), "--json", "--all").stdout)
    assert [(d["operator"], d["identified_by"], d["rejudges"]) for d in docs] == [
        ("A. Original", "login", None), (getpass.getuser(), "login", first.uid)]
    assert docs[1]["rejudge_reason"] == "spec 1.2.0 replaced the hand-chosen plan"
    assert docs[1]["report_sha256"] and docs[1]["station"] == "line2-A"
    assert docs[0]["released"]["by"] == getpass.getuser() and docs[1]["released"] is None
    report = next(unit.glob(f"qc-report-*-{docs[1]['uid'][:8]}.html")).read_text()
    assert f"Re-judged by <b>{getpass.getuser()} (identified by the station: OS login)</b>" in report
    r = rig_qc("release", "SN-0031", "--out", str(station))          # the one who re-judged cannot release it
    assert r.returncode == 2 and "a release is a second person's" in r.stderr
    r = rig_qc("judge", str(unit), "--operator", "someone")
    assert r.returncode == 2 and "the station identifies its operator" in r.stderr
    r = rig_qc("history", "--out", str(station), "--verify")
    assert r.returncode == 0 and r.stdout.endswith(": intact\n"), r.stdout


def test_a_pin_identifies_a_qualified_operator_and_a_login_must_be_listed(tmp_path, rig_qc):
    folder = make_station(tmp_path / "s", "line3", "sqlite:///x.sqlite", None, 'identify = "pin"',
                          "[[operator]]", 'name = "B. Checker"', f'pin = "{pin_hash("4711")}"')
    config = load_station_config(folder)
    assert identify_operator(config, pin="4711").operator == "B. Checker"
    with pytest.raises(StationConfigError, match="no qualified operator's"):
        identify_operator(config, pin="1234")
    assert "4711" not in (folder / "station.toml").read_text()
    listed = make_station(tmp_path / "t", "line4", "sqlite:///x.sqlite", None, "[[operator]]",
                          'name = "C. Else"', 'login = "c-else"')
    with pytest.raises(StationConfigError, match="is not a qualified operator"):
        identify_operator(load_station_config(listed))
    r = rig_qc("judge", str(tmp_path), "--out", str(listed))
    assert r.returncode == 2


# ----- the report ---------------------------------------------------------------------------------------------
def test_a_flagged_capture_is_in_the_record_and_the_report_with_all_an_auditor_asks(virtual_rig, tmp_path, rig_qc):
    text = re.sub(r'(?m)^version = "[^"]*".*$', 'version = "flagged"\nrelease = true',
                  Path(SPEC.source).read_text().replace("max_cycles = 400", "max_cycles = 3"), count=1)
    spec = tmp_path / "QC-flagged.toml"
    spec.write_text(text)
    sim = virtual_rig(unit="good", speed=50)
    bench = tmp_path / "bench"
    r = rig_qc("run", "--serial", "SN-0044", "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out", str(bench),
               "--spec", str(spec), "--rig-id", "rig-7")
    assert r.returncode in (0, 1, 4), r.stderr[-3000:]
    assert "release required by the spec: a second person runs python -m rig qc release SN-0044" in r.stdout
    (doc,) = json.loads(rig_qc("history", "--out", str(bench), "--json").stdout)
    assert list(doc["flagged"].values()) == [["steady state not reached within 3 cycles"]]
    (session,) = [p for p in bench.iterdir() if p.name.startswith("SN-0044")]
    html = (session / "qc-report.html").read_text()
    assert hashlib.sha256(html.encode()).hexdigest() == doc["report_sha256"]
    software = json.loads((session / "qc-record.json").read_text())["software"]
    for item in ("<h2>Flagged captures</h2>", "steady state not reached within 3 cycles", "<th>station</th>",
                 f"{getpass.getuser()} (identified by the station: OS login)", software, "DAQ calibration file",
                 "not reported by the rig", f"archive id rig-7/{session.name}",
                 "required by the spec: a second", 'counter(page) " of " counter(pages)',
                 "class=watermark"):
        assert item in html, item
    assert str(tmp_path) not in html and "/tmp" not in html           # no machine path


def test_an_older_postgresql_schema_is_upgraded_by_the_administrator_only(pg_server, rig_qc):  # noqa: F811
    url = pg_server.records_database("older")
    with admin_connection(pg_server, "older") as conn:          # back to version 3, as an older program left it
        conn.execute("DROP TABLE qc_release")
        conn.execute("DROP TABLE qc_study")                        # version 5's
        for column in ADDED_IN_4["qc_record"]:
            conn.execute(f"ALTER TABLE qc_record DROP COLUMN {column}")
        conn.execute("ALTER TABLE qc_schema DISABLE TRIGGER USER")
        conn.execute("UPDATE qc_schema SET version = 3")
        conn.execute("ALTER TABLE qc_schema ENABLE TRIGGER USER")
    r = rig_qc("history", "--db", url, env={"PGPASSWORD": STATION_PASSWORD})
    assert r.returncode == 2 and "has schema version 3" in r.stderr and "an administrator upgrades it" in r.stderr
    init_schema(pg_server.url(database="older"), ("station",), password=pg_server.password)
    r = rig_qc("history", "--db", url, "--verify", env={"PGPASSWORD": STATION_PASSWORD})
    assert r.returncode == 0 and r.stdout.endswith(": 0 records of 0 stations checked against their hash chains: "
                                                   "intact\n"), r.stdout
    records = Records.open(url, password=STATION_PASSWORD, writer=True)   # INSERT on the new table granted too
    chained(records, "line1-U", 1, "up")
    records.close()


def test_a_run_with_another_configuration_than_the_one_commissioned_is_refused(tmp_path):
    checked = Configuration("line1-A", "sqlite:////srv/qc.sqlite", "tcp://10.0.0.7:502", "socket://10.0.0.8:5025",
                            "a" * 64, "b" * 64)
    write(tmp_path, Commissioning("2026-11-28T07:00:00+00:00", checked, (Item("controller", True, "answers"),)))
    require_commissioned(tmp_path, checked)                          # the same: accepted
    with pytest.raises(NotCommissioned, match="shaker, spec_sha256 changed since its commissioning"):
        require_commissioned(tmp_path, replace(checked, shaker="tcp://10.0.0.9:502", spec_sha256="c" * 64))
    assert (tmp_path / "commissioning.txt").read_text().splitlines()[0] == "PASS  controller: answers"


def test_a_report_names_no_path_of_the_stations_disk():
    base = replace(record("SN-0001", "paths"), session="/srv/qc/line1-A/SN-0001-20261128-070000", station="line1-A",
                   remedy="python -m rig qc run --serial SN-0001 --out /srv/qc/line1-A --periods 4",
                   notes=("judged in /srv/qc/line1-A/SN-0001-20261128-070000",))
    page = render_report(base, SPEC, None)
    assert "/srv" not in page
    assert "--out STATION_DIR --periods 4" in page and "judged in line1-A/SN-0001-20261128-070000" in page
