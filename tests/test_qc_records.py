"""The records database: the same records in SQLite and in a throwaway PostgreSQL server
read back identically; records cannot be changed or deleted; concurrent writers lose
nothing; a record added twice is there once.  Where a PostgreSQL password may come from
and that it leaks nowhere: tests/test_qc_stations.py."""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from rig.cli import main
from rig.qc.judge import Outcome
from rig.qc.records import CharacteristicRecord, QcRecord, Records, RecordStatus
from rig.qc.spec import load_spec
from simulator.generate import generate
from simulator.truth import load_truth
from tests.pgserver import STATION_PASSWORD, pg_server  # noqa: F401 — the fixture

SPEC = load_spec("default")


@pytest.fixture(scope="module")
def units(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two generated units: a good one and a leaking one."""
    root = tmp_path_factory.mktemp("units")
    return [generate(root / unit, list(SPEC.plan.experiments), load_truth(None, "2dof", unit, seed), periods=None,
                     seed=seed, date="261122", serial=f"SN-{seed:04d}")
            for unit, seed in (("good", 8), ("gas-leak", 9))]


def qc(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``python -m rig qc …`` in this process: exit status and everything it printed."""
    capsys.readouterr()
    code = main(["qc", *args])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def test_the_same_records_read_back_identically_from_sqlite_and_postgresql(units, pg_server, tmp_path, capsys,  # noqa: F811
                                                                          monkeypatch):
    monkeypatch.setenv("PGPASSWORD", STATION_PASSWORD)
    url_pg = pg_server.records_database("judged")     # made by the administrator; a station's role writes
    url_sqlite = f"sqlite:///{tmp_path / 'records.sqlite'}"
    for url in (url_sqlite, url_pg):
        assert [qc(capsys, "judge", str(u), "--db", url, "--create-db", "--operator", "qe")[0] for u in units] == [0, 1]
    docs = []
    for url in (url_sqlite, url_pg):
        code, out = qc(capsys, "history", "--db", url, "--json")
        assert code == 0
        docs.append(json.loads(out))
    def same(doc: dict) -> dict:   # each judgement is a record of its own: its uid and time are its own,
        # and so are the hashes that cover them (the report shows the uid)
        return {k: v for k, v in doc.items()
                if k not in ("uid", "judged_at", "record_sha256", "previous_sha256", "report_sha256")}
    assert [same(d) for d in docs[0]] == [same(d) for d in docs[1]]
    assert [(d["serial"], d["verdict"]) for d in docs[0]] == [("SN-0008", "PASS"), ("SN-0009", "FAIL")]
    assert docs[0][1]["characteristics"]["gas_precharge_bar"]["outcome"] == "FAIL"


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_records_cannot_be_changed_or_deleted(backend, pg_server, tmp_path):  # noqa: F811
    url = f"sqlite:///{tmp_path / 'r.sqlite'}" if backend == "sqlite" else pg_server.url()
    records = Records.open(url, create=True, password=pg_server.password if backend == "postgresql" else None)
    assert records.add(record("SN-0001", f"immutable-{backend}"))
    assert not records.add(record("SN-0001", f"immutable-{backend}"))    # the same uid again: nothing added
    for statement in ("UPDATE qc_record SET verdict = 'PASS'", "DELETE FROM qc_record",
                      "UPDATE qc_characteristic SET value = 0", "DELETE FROM qc_characteristic"):
        with pytest.raises(SQLAlchemyError, match="never changed or deleted"), records.engine.begin() as conn:
            conn.execute(text(statement))
    kept = [r for r in records.find() if r.uid == f"immutable-{backend}"]
    assert [(r.verdict, r.characteristics[0].value) for r in kept] == [(Outcome.FAIL, 5.1)]
    records.close()


def record(serial: str, uid: str) -> QcRecord:
    return QcRecord(uid=uid, serial=serial, operator="op", rig="rig", started="2026-11-23T10:00:00+00:00",
                    finished="2026-11-23T10:05:00+00:00", judged="2026-11-23T10:05:10+00:00", software="test",
                    spec_name="default", spec_version="1.0.0", spec_sha256="0" * 64, calibration_sha256=None,
                    register_map_sha256=None, verdict=Outcome.FAIL, status=RecordStatus.COMPLETE, session="/nowhere",
                    data_sha256=uid, files={},
                    characteristics=(CharacteristicRecord("gas_precharge_bar", "bar", 5.1, 0.02, 1e-4, 0.02, 5.7,
                                                          6.3, 6.0, Outcome.FAIL),))


def _writer(url: str, worker: int, barrier) -> None:  # a child process
    records = Records.open(url)
    barrier.wait(timeout=60)
    for i in range(5):
        records.add(record(f"SN-{worker:02d}{i:02d}", f"w{worker}-{i}"))
    records.close()


def test_concurrent_writers_on_one_sqlite_file_lose_nothing(tmp_path):
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    Records.open(url, create=True).close()
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(4)
    workers = [ctx.Process(target=_writer, args=(url, w, barrier)) for w in range(4)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=120)
    assert [w.exitcode for w in workers] == [0] * 4
    records = Records.open(url)
    assert sorted(r.uid for r in records.find()) == sorted(f"w{w}-{i}" for w in range(4) for i in range(5))
    with records.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
    records.close()


def test_history_prints_capability_and_writes_control_charts(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    records = Records.open(url, create=True)
    for i, value in enumerate((5.95, 6.05, 6.00, 5.98, 6.02)):
        base = record(f"SN-{i:04d}", f"u{i}")
        c = base.characteristics[0]
        records.add(QcRecord(**{**base.__dict__, "verdict": Outcome.PASS, "characteristics": (
            CharacteristicRecord(c.name, c.unit, value, c.std, c.std_fit, c.u_cal, c.low, c.high, c.nominal,
                                 Outcome.PASS),)}))
    records.close()
    code, out = qc(capsys, "history", "--db", url, "--chart", str(tmp_path / "charts"))
    assert code == 0
    row = next(line for line in out.splitlines() if line.startswith("│ gas_precharge_bar"))
    cells = [c.strip() for c in row.strip("│").split("│")]
    # n, mean, σ within = MR̄/1.128 with MR̄ = (0.10 + 0.05 + 0.02 + 0.04) / 4, in the unit and to the σ's
    # two digits; Cp = 0.6 / (6·σ within), in parentheses: not meaningful for fewer than 25 units
    assert cells[1:4] == ["5", "6.000 bar", "0.047 bar"] and cells[5] == f"({0.6 / (6 * 0.0525 / 1.128):.3g})"
    assert "(Cp), (Cpk): not meaningful, fewer than 25 units" in out
    assert cells[-3:] == ["5", "0", "0"]
    (chart,) = (tmp_path / "charts").iterdir()
    assert chart.name == "gas_precharge_bar.png" and chart.read_bytes().startswith(b"\x89PNG")
    code, out = qc(capsys, "history", "--db", url, "--serial", "SN-0003", "--json")
    assert [d["characteristics"]["gas_precharge_bar"]["value"] for d in json.loads(out)] == [5.98]
    assert json.loads(qc(capsys, "history", "--db", url, "--since", "2026-11-24", "--json")[1]) == []
