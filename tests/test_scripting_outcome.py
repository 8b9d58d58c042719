"""Issue 42: a script reads how its session ended as data (the RunResult), and the
virtual rig learns the simulator's endpoints and state from its state file, not its log."""

from __future__ import annotations

import json

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
