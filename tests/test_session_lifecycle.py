"""The one session lifecycle (rig.session.run.run_lifecycle) with a failure injected at each of
its steps, on the in-process virtual rig's simulated clock: whatever fails, once the
session folder exists its status is not ``running`` (nor ``complete``), the exit code
says why, the safe stop was taken where motion may have started, and nothing is left
behind (threads, open files)."""

from __future__ import annotations

import io
import json
import os
import threading
from pathlib import Path

import pytest
from rich.console import Console

from identify.exit_codes import EXIT_ABORTED, EXIT_INTERNAL, EXIT_OK
from rig.cli import main
from rig.drivers.daq import DaqError
from rig.drivers.shaker import ShakerLinkError
from rig.errors import RigFault
from rig.events import Event, Kind
from rig.session.outcome import ExitStatus
from rig.session.progress import ConsoleProgress, describe
from rig.session.run import RunOptions, RunResult, SessionRunner, prepare
from rig.session.storage import Session, SessionError, SessionLog, SessionWriteError, read_log
from rig.session.timing import log_times
from simulator.controller import State
from tests.virtual_rig_inprocess import InProcessRig


def open_files() -> set[str]:
    """What this process has open (files, sockets, pipes), by target."""
    fds = Path("/proc/self/fd")
    out = set()
    for fd in os.listdir(fds):
        try:
            out.add(os.readlink(fds / fd))
        except OSError:
            pass  # the listing's own descriptor, closed by now
    return out


class Leaks:
    """Threads and open files that appeared during a session and were still there after it."""

    def __init__(self) -> None:
        self.threads = set(threading.enumerate())
        self.files = open_files()

    def after(self) -> tuple[list[str], list[str]]:
        threads = [t.name for t in threading.enumerate() if t not in self.threads and t.is_alive()]
        return threads, sorted(f for f in open_files() - self.files if "session" in f or "socket" in f)


def run(vrig: InProcessRig, out: Path, letters: list[str] = ["j"], **hooks) -> tuple[RunResult, dict]:  # noqa: B006
    leaks = Leaks()
    result = vrig.run_session(out, letters, **hooks)
    assert leaks.after() == ([], []), "left behind"
    return result, json.loads((out / "session.json").read_text())


def phases(vrig: InProcessRig) -> list[str]:
    return [p for _, _, p in vrig.phases()]


def assert_at_rest(vrig: InProcessRig) -> None:
    c = vrig.sim.controller
    assert (c.state, c.hydraulics_on, vrig.sim.daq.streaming) == (State.OFF, False, False)


def test_a_session_that_completes_leaves_nothing_behind(vrig, tmp_path):
    result, meta = run(vrig, tmp_path / "s", ["j", "n"])
    assert (result.status, result.exit_code, meta["status"]) == ("complete", EXIT_OK, "complete")
    assert meta["estimated_rig_time_s"] > 0
    assert_at_rest(vrig)
    # session.log: one JSON object per event, as published; read back, each says itself in a sentence
    lines = [json.loads(line) for line in (tmp_path / "s" / "session.log").read_text().splitlines()]
    assert all(list(line)[:3] == ["time", "kind", "experiment"] for line in lines)
    assert [line["kind"] for line in lines].count("experiment-done") == 2 and lines[-1]["kind"] == "session-end"
    assert [e.kind for e in read_log(tmp_path / "s" / "session.log")] == [line["kind"] for line in lines]
    assert all(describe(e)[0].isupper() and describe(e).endswith(".") for e in read_log(tmp_path / "s" / "session.log"))
    assert (result.exit_status, result.interrupted, result.reason, result.exception) == \
        (ExitStatus.COMPLETE, False, "", None)
    assert meta["outcome"] == {"exit_status": "complete", "exit_code": EXIT_OK, "interrupted": False, "reason": "",
                               "exception": None, "before_motion": False, "skipped": [], "safe_stop_failures": []}
    # a complete session is not resumed: read from its outcome, or from the bare word of an older session.json
    resume = RunOptions(plan="standard", shaker=None, daq=None, out=tmp_path / "s", resume=True)
    with pytest.raises(SessionError, match="the session is complete; nothing to resume"):
        prepare(resume)
    older = {k: v for k, v in meta.items() if k != "outcome"}
    (tmp_path / "s" / "session.json").write_text(json.dumps(older))
    with pytest.raises(SessionError, match="the session is complete; nothing to resume"):
        prepare(resume)


def test_predicted_and_real_rig_time_per_phase_come_from_the_logs_fields(vrig, tmp_path, capsys):
    """rig log-times on a simulated session: every phase of each experiment, predicted
    against taken, from the prediction, phase and pace-probe events (no sentence read)."""
    run(vrig, tmp_path / "s", ["j", "n"])
    rows = log_times(tmp_path / "s")
    by = {(r.experiment, r.phase): r for r in rows}
    assert sorted(by) == sorted((x, p) for x in ("261122j", "261122n")
                                for p in ("moving", "settling", "capturing", "stopping", "total"))
    predicted = {e.experiment: e.data for e in read_log(tmp_path / "s" / "session.log") if e.kind == Kind.PHASE_PLAN}
    for label, p in predicted.items():
        # the capture is whole periods of samples: taken as predicted, but for the polls that see its end
        capturing = by[label, "capturing"]
        assert capturing.predicted_s == p["capture_s"]
        assert 0 <= capturing.taken_s - capturing.predicted_s <= 0.3, capturing
        assert by[label, "stopping"].taken_s >= p["fade_s"]          # the fade-out, then the wait for AT_STATIC
        total = by[label, "total"]
        assert total.taken_s == pytest.approx(sum(by[label, x].taken_s for x in
                                                  ("moving", "settling", "capturing", "stopping")))
    assert main(["log-times", str(tmp_path / "s")]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split() == ["experiment", "phase", "predicted", "s", "taken", "s", "error"]
    assert len(table) == 1 + len(rows) and table[1].split()[:2] == ["261122j", "moving"]


def test_the_terminal_says_each_line_under_the_experiment_it_belongs_to():
    """An experiment's file is written while the next one moves: its line keeps its own number."""
    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=200), {"261126l": 60.0, "261126v": 60.0, "261126j": 60.0})
    progress(Event(Kind.PHASE, "261126v", {"phase": "moving", "target_mm": 133.04}))
    progress(Event(Kind.EXPERIMENT_DONE, "261126l", {"file": "261126l.csv", "samples": 12000, "lost": 0,
                                                     "flags": []}))
    progress(Event(Kind.PROGRESS, "261126v", {"phase": "settling", "cycles": 12, "ratio": 0.81234,
                                              "bias_sigma": 2601.66, "change": {"stroke_mm": 1.2e-5, "force_N": 5.63}}))
    lines = out.getvalue().splitlines()[1:]
    assert lines[0] == "[2/3] 261126v  Moving to the static position 133.0 mm."
    assert lines[1].startswith("[1/3] 261126l  Written to 261126l.csv: 12000 samples, none lost in the window.")
    assert lines[2] == ("[2/3] 261126v  Cycle 12: the block means moved by stroke 0.000 mm, force 5.6 N; the "
                        "transient decays ×0.812 per cycle.")


def test_a_folder_that_cannot_be_made_is_raised_and_nothing_is_written(vrig, tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise SessionError(f"--out {tmp_path / 's'}: cannot create the session folder (injected)")

    monkeypatch.setattr(Session, "create", refuse)
    with pytest.raises(SessionError, match="injected"):
        vrig.run_session(tmp_path / "s", ["j"])
    assert not (tmp_path / "s").exists() and phases(vrig) == []


def test_a_log_that_cannot_be_written_aborts_before_anything_moves(vrig, tmp_path, monkeypatch):
    def refuse(self, path):
        raise SessionWriteError(f"{path}: the session log cannot be written (injected)")

    monkeypatch.setattr(SessionLog, "__init__", refuse)
    result, meta = run(vrig, tmp_path / "s")
    assert result.exit_code == EXIT_ABORTED and meta["status"] == result.status
    assert result.status.startswith("aborted: ") and result.status.endswith("(before anything moved)")
    assert phases(vrig) == [] and not vrig.sim.controller.hydraulics_on


def test_a_daq_cut_at_the_pace_probes_start_is_on_record(vrig, tmp_path, monkeypatch):
    """The DAQ line cut at the first START (the pace probe's, before any motion)."""
    def cut():
        raise DaqError("DAQ at socket://virtual-rig:4001: link lost during 'START' and not back (injected)")

    monkeypatch.setattr(vrig.daq, "start", cut)
    result, meta = run(vrig, tmp_path / "s")
    assert (result.exit_code, meta["status"]) == (EXIT_ABORTED, result.status)
    assert "link lost during 'START'" in meta["status"] and meta["status"].endswith("(before anything moved)")
    assert phases(vrig) == []
    assert vrig.messages("session-end") == [meta["status"]]


def test_a_bug_in_the_durations_is_an_internal_error_on_record(vrig, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise ZeroDivisionError("injected bug")

    monkeypatch.setattr("rig.session.runner.predict", broken)
    result, meta = run(vrig, tmp_path / "s")
    assert (result.exit_code, type(result.error)) == (EXIT_INTERNAL, ZeroDivisionError)
    assert meta["status"] == "aborted: internal error: ZeroDivisionError: injected bug (before anything moved)"


def test_a_first_command_that_fails_ends_in_the_safe_stop(vrig, tmp_path, monkeypatch):
    def lost(*args, **kwargs):
        raise ShakerLinkError("Modbus link to tcp://virtual-rig:502 lost and not back within 3 s (injected)")

    monkeypatch.setattr(vrig.shaker, "hydraulics", lost)    # the first write of the session: hydraulics on
    result, meta = run(vrig, tmp_path / "s")
    assert result.exit_code == EXIT_ABORTED and meta["status"].startswith("aborted: Modbus link")
    assert phases(vrig) == ["moving", "stopping", "idle"]   # the safe stop was taken
    assert "safe stop incomplete (hydraulics off:" in meta["status"]


@pytest.mark.parametrize("failing", ["261122j", "261122n"])
def test_a_failure_in_each_experiment_ends_in_the_safe_stop(vrig, tmp_path, failing):
    def fail():
        raise RigFault(f"injected fault in {failing}")

    vrig.when("settling", 2.0, fail, experiment=failing)
    result, meta = run(vrig, tmp_path / "s", ["j", "n"])
    assert (result.exit_code, meta["status"]) == (EXIT_ABORTED, f"aborted: injected fault in {failing}")
    captured = json.loads((tmp_path / "s" / "dataset.json").read_text())["experiments"]
    assert [e["label"] for e in captured] == ([] if failing == "261122j" else ["261122j"])
    assert phases(vrig)[-2:] == ["stopping", "idle"]
    assert_at_rest(vrig)


def test_a_writer_that_fails_aborts_after_the_safe_stop(vrig, tmp_path, monkeypatch):
    def full(self, record):
        raise SessionWriteError(f"{self.path}: experiment {record.label} was captured but could not be written "
                                "(No space left on device)")

    monkeypatch.setattr(Session, "write_experiment", full)
    result, meta = run(vrig, tmp_path / "s", ["j", "n"])
    assert result.exit_code == EXIT_ABORTED
    assert meta["status"].startswith("aborted: ") and "261122j was captured but could not be written" in meta["status"]
    assert_at_rest(vrig)


def test_a_teardown_that_fails_keeps_the_record(vrig, tmp_path, monkeypatch, caplog):
    real_close = SessionRunner.close

    def close_then_fail(self):
        real_close(self)
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(SessionRunner, "close", close_then_fail)
    result, meta = run(vrig, tmp_path / "s")
    assert (result.status, result.exit_code, meta["status"]) == ("complete", EXIT_OK, "complete")
    assert "closing the session writer failed: [Errno 5] Input/output error" in caplog.text
    assert (tmp_path / "s" / "session.log").read_text().count("session-end") == 1


def test_the_last_experiment_is_written_with_the_rig_at_rest_and_a_failed_write_aborts(vrig, tmp_path, monkeypatch):
    """The rig is brought to rest before the session waits for its last data (at 10x the
    seconds a CSV takes were tens of seconds of rig time with the hydraulics on); a
    last write that fails still makes the session aborted, not complete."""
    at_rest = threading.Event()
    seen: list[bool] = []

    def rest(e: Event) -> None:
        if e.kind == Kind.PHASE and e.data["phase"] == "idle" and e.experiment is None:
            at_rest.set()

    def write_after_rest(self, record):
        seen.append(at_rest.wait(30.0))   # a guard: the safe stop comes at once, or never (before the fix)
        raise SessionWriteError(f"{self.path}: experiment {record.label} was captured but could not be written "
                                "(No space left on device)")

    vrig.bus.subscribe(rest, inline=True)
    monkeypatch.setattr(Session, "write_experiment", write_after_rest)
    result, meta = run(vrig, tmp_path / "s", ["j"])
    assert seen == [True] and not vrig.sim.controller.hydraulics_on
    assert result.exit_code == EXIT_ABORTED and meta["status"] == result.status
    assert meta["status"].startswith("aborted: ") and "261122j was captured but could not be written" in meta["status"]
