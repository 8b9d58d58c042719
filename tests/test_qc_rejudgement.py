"""A re-judgement says so (issue 34): its report's title and header, a box and a note
naming the record it judges again, the terminal's first line; and its measurement
times are the original record's, not the session files' (14:19:08 in one record,
14:19:09 in the other, for the same measurement)."""

from __future__ import annotations

import re
from dataclasses import replace

from rig.qc.records import Records
from rig.qc.trace import trace_session
from tests.test_qc_units import judge, unit_dataset


def test_a_rejudgement_names_the_record_and_keeps_its_times(tmp_path, capsys):
    session = unit_dataset(tmp_path / "unit", "good", 3)
    db = tmp_path / "records.sqlite"
    code, out = judge(capsys, session, db)
    assert code == 0 and "RE-JUDGEMENT" not in out
    records = Records.open(str(db))
    (first,) = records.find()
    records.close()
    (original,) = sorted(session.glob("qc-report-*.html"))
    assert "<h1>QC report — unit SN-0003</h1>" in original.read_text()

    # the first record as qc run writes it: its times are the run's, a second before the session files'
    trace = trace_session(session)
    assert first.started == trace.started
    db2 = tmp_path / "run.sqlite"
    records = Records.open(str(db2), create=True)
    measured = replace(first, uid="run-record", started="2026-11-23T14:19:08+00:00",
                       finished="2026-11-23T14:20:01+00:00")
    records.add(measured)
    records.close()

    code, out = judge(capsys, session, db2)
    first_line = out.splitlines()[0]
    assert first_line.startswith("SN-0003: PASS") and first_line.endswith("RE-JUDGEMENT of record run-record")
    records = Records.open(str(db2))
    _, again = records.find()
    records.close()
    assert again.rejudges == "run-record"
    assert (again.started, again.finished) == (measured.started, measured.finished)
    assert again.notes[0].startswith("re-judgement of record run-record (spec default")
    report = max(session.glob("qc-report-*.html"), key=lambda p: p.stat().st_mtime_ns).read_text()
    assert re.search(r"<title>QC re-judgement SN-0003: PASS.* of record run-reco</title>", report, re.S)
    assert "<h1>QC re-judgement — unit SN-0003 (re-judges record run-record)</h1>" in report
    assert "<h2>Re-judgement</h2><p>This report judges again the measurement of record <code>run-record</code> " \
           "(2026-11-23T14:19:08+00:00 … 2026-11-23T14:20:01+00:00)" in report
    assert "<h2>Notes</h2>" in report and "re-judgement of record run-record" in report
