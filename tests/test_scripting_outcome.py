"""Issue 42: a script reads how its session ended as data (the RunResult), and the
virtual rig learns the simulator's endpoints and state from its state file, not its log."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import rig
from rig.session.api import SessionFailed
from rig.session.outcome import ExitStatus
from rig.virtual import VirtualRig


def test_a_script_reads_the_outcome_of_an_aborted_session_as_data(virtual_rig, tmp_path):
    sim = virtual_rig(faults=["estop@run+3"])
    with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
        session = r.plan("standard", experiments=["j"], out=tmp_path / "s", progress=False)
        assert (session.result, session.exit_status) == (None, None)
        with pytest.raises(SessionFailed) as failed:
            session.run()
    result = failed.value.result
    assert result is not None and result is session.result
    assert session.exit_status is ExitStatus.ABORTED and result.exit_code == 3
    assert result.reason.startswith("shaker alarm: emergency stop") and result.captured == []
    assert session.status == result.status   # the sentence on disk is the one rendered from the fields


def test_the_virtual_rig_takes_its_endpoints_and_state_from_the_state_file(tmp_path):
    with VirtualRig(speed=20) as sim:
        state = sim.state()
        assert state["state"] == "serving" and (state["modbus"], state["daq"]) == (sim.modbus_url, sim.daq_url)
        assert "--state" in sim.command and state["hydraulics"] == []
        with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
            r.move(1.0)
        said = sim.stop()
    state = sim.state()
    assert state["state"] == "stopped" and state["lost_frames"] == 0
    assert [on for _, on in state["hydraulics"]] == [True, False]
    assert sim.rig_time_s() == pytest.approx(state["hydraulics"][1][0] - state["hydraulics"][0][0])
    # The log stays the people's: the facts agree with it, and a reworded log changes nothing.
    assert "hydraulics on" in said and "DAQ frames lost by faults: 0" in said
    sim._lines[:] = ["reworded\n"]
    assert sim.lost_frames() == 0 and sim.rig_time_s() > 0


def test_the_state_file_is_written_whole_and_says_stopped_at_exit(tmp_path):
    from simulator.cli import StateFile

    path = tmp_path / "state.json"
    state = StateFile(path)
    state.update(state="serving", modbus="tcp://127.0.0.1:1", daq="socket://127.0.0.1:2")
    state.update(hydraulics=[[1.5, True]])
    doc = json.loads(path.read_text())
    assert (doc["state"], doc["modbus"], doc["hydraulics"]) == ("serving", "tcp://127.0.0.1:1", [[1.5, True]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def _entry(session: Path) -> dict[str, object]:
    return {"uid": "0b4c0ffe-0000-4000-8000-000000000042", "session": str(session), "pid": 4242, "host": "station-1",
            "station": "S1", "spec": {"name": "default", "version": "1", "sha256": "ab" * 32, "k": 2.0},
            "serial": "SN-0666", "operator": "op", "rig": "rig-1", "started": "2026-11-28T06:00:00+00:00"}


def test_a_run_left_running_is_ended_with_an_outcome_that_reads_aborted(tmp_path):
    from rig.qc.queue import KILLED, abandoned_record
    from rig.qc.records import RecordStatus
    from rig.session.outcome import stored_exit_status
    from rig.session.storage import Session

    folder = tmp_path / "session"
    Session.create(folder, plan_source="standard", letters=["j"], periods=None, date="261128", snapshot={},
                   unit={"serial": "SN-0666"}, endpoints={})
    assert stored_exit_status(json.loads((folder / "session.json").read_text())) is ExitStatus.RUNNING
    record = abandoned_record(_entry(folder))
    assert record is not None and record.status is RecordStatus.ABORTED
    meta = json.loads((folder / "session.json").read_text())
    assert stored_exit_status(meta) is ExitStatus.ABORTED          # no longer None: the outcome is stored
    assert meta["status"] == f"aborted: {KILLED}"                   # the sentence as it was, rendered
    assert (meta["outcome"]["reason"], meta["outcome"]["exit_code"]) == (KILLED, 3)
    assert record.details["session_status"] == "running"           # what was found
    assert record.details["session_outcome"]["exit_status"] == "aborted"


def test_a_run_that_had_ended_keeps_its_own_outcome(tmp_path):
    from rig.qc.queue import abandoned_record
    from rig.session.outcome import RunResult
    from rig.session.storage import Session

    folder = tmp_path / "session"
    session = Session.create(folder, plan_source="standard", letters=["j"], periods=None, date="261128",
                             snapshot={}, unit={"serial": "SN-0666"}, endpoints={})
    ended = RunResult(session, planned=1)
    ended.end(ExitStatus.COMPLETE)
    session.finish(ended.status, ended.to_json())
    # A reworded sentence changes nothing: the decision reads the stored outcome.
    meta = json.loads((folder / "session.json").read_text())
    (folder / "session.json").write_text(json.dumps({**meta, "status": "running"}))
    record = abandoned_record(_entry(folder))
    assert record is not None and record.reason.startswith("process ended while judging")
    assert json.loads((folder / "session.json").read_text())["outcome"]["exit_status"] == "complete"
