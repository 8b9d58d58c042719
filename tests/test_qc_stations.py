"""A plant's QC stations (issue 35), against served simulators and a throwaway PostgreSQL
server:

- the password is in no argv (``ps -eo args`` while a run is going), output, file, record
  or error; a URL that carries one is refused in one line, and so is a station.toml
  with a password that others may read;
- a database stopped between the capture and the record: the run ends with its verdict's
  exit status, the record is queued, ``qc history`` warns, and it reaches the database
  exactly once when it is back;
- ``rig qc run`` killed with SIGKILL in each phase: the controller's watchdog stops the
  motion and switches the hydraulics off within its stated time, and the station's next
  start records the run as ABORTED before anything moves;
- four stations at once on one database: every record once, by station.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rig.qc.queue import Outbox, RecordQueue
from rig.qc.records import QcRecord, Records
from rig.qc.spec import load_spec
from tests.pgserver import STATION_PASSWORD, pg_server  # noqa: F401 — the fixture
from tests.stations import (
    Lines,
    StationLoop,
    commission,
    make_station,
    read_controller,
    run_stations,
    wait_controller,
)
from tests.test_qc_run import qc_cmd, short_spec

# How late after the stated watchdog time the controller may be seen at rest: the
# simulator checks its watchdog at each engine step (milliseconds) and this test polls
# every 20 ms; a busy host delays both.  A watchdog that did not trip would take forever.
WATCHDOG_SLACK_S = 1.0


def rig_qc(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", "qc", *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})})


def history_json(out: Path, *args: str, env: dict[str, str] | None = None) -> list[dict]:
    r = rig_qc("history", "--out", str(out), "--json", "--all", *args, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_a_record_reads_back_from_the_station_journal_as_it_was_written(tmp_path):
    from tests.test_qc_records import record

    written = record("SN-0001", "journal-1")
    path = RecordQueue(tmp_path).put(written, "sqlite:////somewhere/qc-records.sqlite")
    assert path.parent.name == "pending" and not list(path.parent.glob(".*"))   # no temporary left
    assert QcRecord.from_journal(json.loads(path.read_text())) == written


def test_only_a_run_whose_process_is_gone_is_taken_for_abandoned(tmp_path):
    said: list[str] = []
    identity = {"serial": "SN-0001", "operator": "op", "rig": "r", "started": "2026-11-26T10:00:00+00:00"}
    alive = Outbox.open(tmp_path, None, said.append)
    alive.begin(tmp_path / "SN-0001-x", load_spec("default"), identity)
    other = Outbox.open(tmp_path, None, said.append)       # a second process of the station: the run is locked
    assert other.recover() == [] and len(list(alive.queue.running_dir.glob("*.json"))) == 1
    assert alive._run is not None
    alive._run._handle.close()                          # as the kernel does when its process dies
    assert other.recover() == []                        # its session never began: nothing to record …
    assert not list(alive.queue.running_dir.glob("*.json"))   # … and it is not found again
    assert "ended before its session began" in said[-1]
    other.close()
    alive.records.close()


def test_a_url_with_a_password_is_refused_in_one_line_that_says_what_to_do(tmp_path):
    secret = "Pg-s3cret-url"
    for command in (["run", "--serial", "SN-0001", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9",
                     "--out", str(tmp_path / "s")], ["history"], ["sync", "--out", str(tmp_path / "s")]):
        for url in (f"postgresql://qc:{secret}@127.0.0.1:5432/qc", f"postgresql://qc@127.0.0.1/qc?password={secret}"):
            r = rig_qc(*command, "--db", url)
            assert r.returncode == 2, (command, r.stderr)
            (line,) = r.stderr.splitlines()
            assert line.startswith("error: --db postgresql") and "must not carry the password" in line
            assert ".pgpass" in line and "station.toml" in line and secret not in line + r.stdout
    assert not (tmp_path / "s").exists()     # refused before anything was written


def test_a_password_with_an_at_sign_and_a_port_that_is_no_number_are_refused_without_leaking():
    # An unescaped '@' makes a parser split at the first one: the password's tail read as the host.
    r = rig_qc("history", "--db", "postgresql://qc:s3c@ret@127.0.0.1:5999/qc")
    (line,) = r.stderr.splitlines()
    assert r.returncode == 2 and "must not carry the password" in line and "s3c" not in line and "ret@" not in line
    r = rig_qc("history", "--db", "postgresql://qc@127.0.0.1:notaport/qc")
    (line,) = r.stderr.splitlines()
    assert r.returncode == 2 and "not a database URL" in line and "notaport" in line, r.stderr


def test_a_station_file_with_a_password_that_others_can_read_is_refused(tmp_path):
    station = make_station(tmp_path / "s", "A", "postgresql://qc@127.0.0.1:9/qc", "Pg-s3cret-file")
    (station / "station.toml").chmod(0o640)
    r = rig_qc("sync", "--out", str(station))
    assert r.returncode == 2
    (line,) = r.stderr.splitlines()
    assert "holds a password but its group or others may read it (-rw-r-----)" in line and "chmod 600" in line
    assert "Pg-s3cret-file" not in r.stderr + r.stdout


def test_the_password_is_in_no_argv_output_file_or_record(pg_server, virtual_rig, tmp_path):  # noqa: F811
    secret = STATION_PASSWORD
    url = pg_server.records_database("argv")      # the station's role, not the administrator's
    station = make_station(tmp_path / "station", "line1-A", url, secret)
    sim = virtual_rig(unit="good")
    spec = str(short_spec(tmp_path))
    checked = commission(station, sim.modbus_url, sim.daq_url, spec)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    proc = subprocess.Popen(qc_cmd(sim, station, "SN-0077", "--spec", spec),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = Lines(proc)
    lines.wait_for("Now capturing")            # the run is going: the database is open, the rig moving
    ps = subprocess.run(["ps", "-eo", "args", "-ww"], capture_output=True, text=True, check=True).stdout  # whole lines
    assert f"SN-0077 --shaker {sim.modbus_url}" in ps     # the run is in the list …
    assert secret not in ps                               # … and the password is not
    out = lines.stdout()
    err = lines.rest()
    assert proc.returncode in (0, 1, 4), err[-3000:]
    seen = [out, err, checked.stdout, checked.stderr]
    # the other places libpq takes it from: PGPASSWORD, a pgpass file
    plain = tmp_path / "plain"
    plain.mkdir()
    r = rig_qc("history", "--db", url, "--json", env={"PGPASSWORD": secret})
    assert r.returncode == 0 and [d["station"] for d in json.loads(r.stdout)] == ["line1-A"]
    seen += [r.stdout, r.stderr]
    passfile = tmp_path / "pgpass"
    passfile.write_text(f"127.0.0.1:{pg_server.port}:*:station:{secret}\n")
    passfile.chmod(0o600)
    r = rig_qc("history", "--db", url, env={"PGPASSFILE": str(passfile)})
    assert r.returncode == 0 and "SN-0077" in r.stdout
    seen += [r.stdout, r.stderr]
    # errors name the database without it: a wrong password, a server that is not there
    wrong = make_station(tmp_path / "wrong", "B", url, "wrong-" + secret)
    r = rig_qc("history", "--out", str(wrong))
    assert r.returncode == 2 and r.stderr.startswith("error: records database postgresql+psycopg://station@127.0.0.1:")
    assert "password authentication failed" in r.stderr and "wrong-" not in r.stderr
    seen += [r.stdout, r.stderr]
    gone = make_station(tmp_path / "gone", "C", "postgresql://qc@127.0.0.1:9/qc", secret)
    r = rig_qc("history", "--out", str(gone))     # said, with the station's queue (empty here)
    assert r.returncode == 3 and "Connection refused" in r.stderr and "0 records of station" in r.stderr
    seen += [r.stdout, r.stderr]

    for text in seen:
        assert secret not in text
    for p in station.rglob("*"):
        if p.is_file() and p.name != "station.toml":
            assert secret.encode() not in p.read_bytes(), p
    records = Records.open(url, password=secret)
    dumped = json.dumps([r.to_journal() for r in records.find()], default=str)
    records.close()
    assert secret not in dumped and "SN-0077" in dumped


def test_a_record_made_while_the_database_is_down_reaches_it_once_when_it_is_back(pg_server, virtual_rig,  # noqa: F811
                                                                                   tmp_path):
    url = pg_server.records_database("queued")
    station = make_station(tmp_path / "station", "line1-B", url, STATION_PASSWORD)
    sim = virtual_rig(unit="gas-leak")
    spec = str(short_spec(tmp_path))
    assert commission(station, sim.modbus_url, sim.daq_url, spec).returncode == 0
    proc = subprocess.Popen(qc_cmd(sim, station, "SN-0101", "--spec", spec),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = Lines(proc)
    try:
        lines.wait_for("Now capturing")
        pg_server.stop()                         # the network drops between the capture and the record
        out = lines.stdout()
        err = lines.rest()
        verdict = {0: "PASS", 1: "FAIL", 4: "INCONCLUSIVE"}.get(proc.returncode)
        assert verdict is not None, err[-3000:]
        assert out.startswith(f"SN-0101: {verdict}")          # the verdict, on screen and in the exit status
        (queued,) = [line for line in err.splitlines() if line.startswith("record queued")]   # the last word
        assert err.rstrip().endswith("sends it")
        assert queued.startswith("record queued (database unreachable: ") and "qc sync --out" in queued
        (pending,) = (station / "qc-queue" / "pending").iterdir()
        assert json.loads(pending.read_text())["verdict"] == verdict
    finally:
        pg_server.resume()
    r = rig_qc("history", "--out", str(station))
    assert r.returncode == 0 and "warning: 1 record of station" in r.stderr and "qc sync" in r.stderr
    assert "SN-0101" not in r.stdout
    r = rig_qc("sync", "--out", str(station))
    named = url.replace("postgresql", "postgresql+psycopg", 1)
    assert (r.returncode, r.stderr.strip()) == (0, f"1 queued record sent to {named}"), r.stderr
    # a second send of the same record (the queue not told, as after a crash) adds nothing
    (sent,) = (station / "qc-queue" / "sent").iterdir()
    os.replace(sent, station / "qc-queue" / "pending" / sent.name)
    r = rig_qc("sync", "--out", str(station))
    assert r.returncode == 0 and "0 queued records sent" in r.stderr and "(1 were there already)" in r.stderr
    r = rig_qc("history", "--out", str(station))
    assert r.returncode == 0 and "warning" not in r.stderr
    (doc,) = history_json(station, "--station", "line1-B")     # the server holds other tests' stations too
    assert (doc["serial"], doc["verdict"], doc["status"], doc["station"]) == ("SN-0101", verdict, "COMPLETE", "line1-B")


PHASES = {   # the run's own line that says the phase has begun
    "moving": "Moving to the static position",
    "settling": "Excitation running, settling.",
    "capturing": "Now capturing",
    "judging": "session took",       # the session has ended in its safe stop; judging begins
}


@pytest.mark.parametrize("phase", list(PHASES))
def test_a_run_killed_in_each_phase_is_stopped_by_the_watchdog_and_recorded_aborted(phase, virtual_rig, tmp_path):
    sim = virtual_rig(unit="worn-seal")
    station = tmp_path / "station"
    spec = str(short_spec(tmp_path))
    proc = subprocess.Popen(qc_cmd(sim, station, "SN-0666", "--spec", spec), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lines = Lines(proc)
    lines.wait_for(PHASES[phase])
    # The moving phase is said before the hydraulics are switched on: the kill waits for the
    # controller to read them on, so that there is motion to stop.
    before = (read_controller(sim.host, sim.port) if phase == "judging" else
              wait_controller(sim.host, sim.port, lambda c: c.hydraulics_on))
    os.kill(proc.pid, signal.SIGKILL)
    killed = time.monotonic()
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    if phase == "judging":      # the session had ended in its safe stop: nothing moves, nothing to trip
        assert (before.state, before.hydraulics_on) == ("OFF", False)
        after = read_controller(sim.host, sim.port)
        assert (after.state, after.alarm, after.hydraulics_on) == ("OFF", "none", False)
    else:
        assert before.hydraulics_on and before.watchdog_s > 0, before
        after = wait_controller(sim.host, sim.port, lambda c: c.alarm == "watchdog" and not c.hydraulics_on)
        seen_s = time.monotonic() - killed
        assert seen_s <= before.watchdog_s + WATCHDOG_SLACK_S, (seen_s, before.watchdog_s)
        assert (after.state, after.supply_bar) == ("ALARM", 0.0)
        assert read_controller(sim.host, sim.port).position_mm == after.position_mm      # at rest
        assert "trip watchdog" in sim.log() and "hydraulics off" in sim.log().split("trip watchdog")[1]

    (session,) = [p for p in station.iterdir() if p.is_dir() and p.name != "qc-queue"]
    assert not (station / "qc-records.sqlite").exists()           # nothing recorded by the killed run
    # The next start, on a rig that does not answer: the ABORTED record comes first, before any link.
    r = subprocess.run(qc_cmd(sim, station, "SN-0667", "--spec", spec) + ["--shaker", "tcp://127.0.0.1:9"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 3, r.stderr[-3000:]
    told = r.stderr.index("unit SN-0666: the run started")
    assert told < r.stderr.index("QC default") and "recorded as ABORTED" in r.stderr[told:told + 600]
    (doc,) = history_json(station)
    assert (doc["serial"], doc["status"], doc["verdict"]) == ("SN-0666", "ABORTED", None)
    assert doc["session"] == str(session.resolve())
    meta = json.loads((session / "session.json").read_text())
    if phase == "judging":
        assert doc["reason"].startswith("process ended while judging") and meta["status"] == "complete"
    else:
        assert doc["reason"].startswith("process ended without a safe stop")
        assert meta["status"] == "aborted: process ended without a safe stop"
    assert not list((station / "qc-queue" / "running").iterdir())
    # and once only: a third start finds nothing left to record
    r = rig_qc("sync", "--out", str(station))
    assert r.returncode == 0 and "ABORTED" not in r.stderr
    assert len(history_json(station)) == 1


@pytest.mark.slow
def test_four_stations_write_to_one_postgresql_at_once(pg_server, virtual_rig, tmp_path):  # noqa: F811
    """The small one: four stations, three units each, at once (≥ 100 units:
    benchmarks/bench_stations.py)."""
    spec = str(short_spec(tmp_path))
    url = pg_server.records_database("four_stations")   # none of the module's other tests' records in it
    loops = []
    for i, unit in enumerate(("good", "gas-leak", "worn-seal", "good")):
        sim = virtual_rig(unit=unit, unit_seed=i, speed=50)
        folder = make_station(tmp_path / f"station-{i}", f"line1-{'ABCD'[i]}", url, STATION_PASSWORD)
        assert commission(folder, sim.modbus_url, sim.daq_url, spec).returncode == 0
        loops.append(StationLoop(folder, f"S{'ABCD'[i]}", sim.modbus_url, sim.daq_url, 3, spec))
    run_stations(loops)
    assert not [e for loop in loops for e in loop.errors]
    docs = history_json(loops[0].folder)
    serials = sorted(d["serial"] for d in docs)
    assert serials == sorted(loop.serial(i) for loop in loops for i in range(loop.units))   # each once
    assert len({d["uid"] for d in docs}) == len(docs) == 12
    for i, loop in enumerate(loops):
        mine = history_json(loop.folder, "--station", f"line1-{'ABCD'[i]}")
        assert sorted(d["serial"] for d in mine) == [loop.serial(j) for j in range(loop.units)]
        r = rig_qc("history", "--out", str(loop.folder), "--station", f"line1-{'ABCD'[i]}", "--include-simulated",
                   "--chart", str(tmp_path / f"charts-{i}"))
        assert r.returncode == 0 and "warning" not in r.stderr
        assert sorted(p.name for p in (tmp_path / f"charts-{i}").iterdir())
