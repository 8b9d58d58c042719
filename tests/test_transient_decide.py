"""Stop-when-decided within one transient capture (issue 36): the record is judged as it
grows and the capture ends at the first judgement that decides, every sample delivered
by then kept (in-process rig, simulated clock)."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from rich.console import Console

from rig.config import DEFAULT_RIG_CONFIG
from rig.qc.spec import load_spec
from rig.session.acquisition import JUDGED_AT_S
from rig.session.run import Links, RunOptions, SessionRunner, prepare, run_lifecycle
from tests.virtual_rig_inprocess import DAQ_URL, SHAKER_URL, InProcessRig


def _run(tmp_path, judge):
    spec = load_spec("transient")
    rig = InProcessRig(DEFAULT_RIG_CONFIG)
    try:
        rig.connect()
        prep = prepare(RunOptions(plan=spec.source, shaker=SHAKER_URL, daq=DAQ_URL, out=tmp_path / "s",
                                  date="261126", unit_serial="SN-0001"))
        prep = replace(prep, config=replace(prep.config, steady_state=spec.steady_state))
        def configure(runner: SessionRunner | None) -> None:
            if runner is not None:
                runner.acquisition.judge_partial = judge(rig) if getattr(judge, "needs_rig", False) else judge

        t0 = rig.sim.t
        result = run_lifecycle(prep, Console(file=io.StringIO()), links=Links(rig.shaker, rig.daq, rig.identity, None),
                               bus=rig.bus, on_runner=configure)
        return result, rig.sim.t - t0, pd.read_csv(tmp_path / "s" / "261126a.csv")
    finally:
        rig.close()


def test_an_undecided_record_is_judged_at_each_point_and_captured_whole(tmp_path):
    seen: list[float] = []

    def judge(record):
        seen.append(len(record.index) / record.rate_hz)
        return None

    result, rig_s, data = _run(tmp_path, judge)
    assert result.status == "complete" and result.decided is None
    assert seen == pytest.approx(list(JUDGED_AT_S), abs=1e-9)
    assert data["time_s"].iloc[-1] == pytest.approx(3.0, abs=2e-3)   # the 1 s ramp and 8 periods at 4 Hz


def test_a_decided_record_ends_the_capture_and_the_session_keeping_every_sample(tmp_path):
    calls: list[np.ndarray] = []

    def judge(record):
        calls.append(record.time_s)
        return "every characteristic decided (PASS)"

    whole = _run(tmp_path / "whole", lambda record: None)[1]
    result, rig_s, data = _run(tmp_path / "early", judge)
    assert len(calls) == 1 and calls[0][-1] == pytest.approx(JUDGED_AT_S[0], abs=1e-3)
    assert result.exit_code == 0 and result.status.startswith("ended: 1 of 1 experiments captured")
    assert "after 1.5 s of the record" in (result.decided or "")
    # what was judged is in the file, from RUN on, no sample missing
    t = data["time_s"].to_numpy()
    assert t[0] == 0.0 and JUDGED_AT_S[0] - (t[1] - t[0]) - 1e-9 <= t[-1] < 3.0
    assert np.allclose(np.diff(t), t[1] - t[0])
    assert rig_s < whole - 1.0


def test_a_judgement_slower_than_the_rest_of_the_record_is_not_repeated(tmp_path):
    """The rig runs on while a fit runs: once the record is whole, nothing more is judged."""
    seen: list[float] = []

    def slow(rig):
        def judge(record):
            seen.append(len(record.index) / record.rate_hz)
            rig.clock.spend(2.0)   # a fit that takes 2 s of the rig's time
            return None
        return judge

    slow.needs_rig = True
    result, rig_s, data = _run(tmp_path, slow)
    assert seen == pytest.approx([JUDGED_AT_S[0]], abs=1e-9) and result.status == "complete"
    assert data["time_s"].iloc[-1] == pytest.approx(3.0, abs=2e-3)
