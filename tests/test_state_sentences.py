"""Every sentence about the rig's state is derived from a reading (issue 34).

"At rest" is said only after the controller was *read* at rest, and a pace only from a
measurement taken in this session, with its clock named.  Each fault (the controller's
link lost for a while, the controller dead, the DAQ dead, the whole simulator killed)
is injected in each phase of an experiment (moving, settling, capturing, stopping) on
the in-process virtual rig's simulated clock; the session's exit code and status stay
what they were (3, ``aborted: …``), and what the terminal and session.log say of the
rig's state is checked against the simulator's own state at that moment.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable

import pytest
from rich.console import Console

from identify.exit_codes import EXIT_ABORTED, EXIT_OK
from rig.drivers.daq import DaqError
from rig.events import Event, Kind, Phase
from rig.session.acquisition import PaceReading
from rig.session.progress import ConsoleProgress, describe
from rig.session.run import SessionContext, SessionRunner
from rig.session.storage import read_log
from simulator.controller import State
from tests.virtual_rig_inprocess import InProcessRig

LETTERS = ["j", "n"]        # a fault in j's stopping is met by n's first command
FIRST = "261122j"




def _dead(*args: object, **kwargs: object) -> bytes:
    raise OSError(5, "Input/output error (injected: the DAQ is dead)")


def kill_daq(vrig: InProcessRig) -> None:
    """The DAQ stops for good: no sample, no answer, its line gone and not reopened."""
    device = vrig.sim.daq
    with device._lock:
        device.streaming = False
    device._handle = lambda line: None                       # type: ignore[method-assign]
    vrig.line.host.read = _dead                              # type: ignore[method-assign]
    vrig.line.host.write = _dead                             # type: ignore[method-assign,assignment]

    def no_port() -> None:
        raise DaqError(f"cannot open the DAQ at {vrig.daq.url}: nothing answers (injected)")

    vrig.daq._open_port = no_port                            # type: ignore[method-assign,assignment]


def kill_simulator(vrig: InProcessRig) -> None:
    vrig.client.cut(1e9)
    kill_daq(vrig)


FAULTS: dict[str, Callable[[InProcessRig], None]] = {
    # back one second after the session has given it up: the safe stop reaches it
    "link lost": lambda vrig: vrig.client.cut(vrig.config.reconnect_s + 1.0),
    "controller dead": lambda vrig: vrig.client.cut(1e9),
    "DAQ dead": kill_daq,
    "simulator killed": kill_simulator,
}
PHASES = {"moving": 0.2, "settling": 3.0, "capturing": 0.5, "stopping": 0.3}   # seconds into the phase


def controller_at_rest(vrig: InProcessRig) -> bool:
    return vrig.sim.controller.state in (State.OFF, State.IDLE)


@pytest.mark.parametrize("phase", list(PHASES))
@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_fault_in_each_phase_says_only_what_was_read(vrig, tmp_path, fault, phase):
    truth: list[tuple[str, bool, bool]] = []          # (sentence, controller at rest, link up) as it was said
    runners: list[SessionRunner] = []
    terminal = io.StringIO()

    def said(e: Event) -> None:
        if e.kind == Kind.PHASE and e.data["phase"] == Phase.IDLE:
            truth.append((describe(e), controller_at_rest(vrig), vrig.client.link_up))

    def attach(ctx: SessionContext) -> list:
        return [ConsoleProgress(Console(file=terminal, width=300), ctx.estimates_s, ctx.current_pace, ctx.rig_clock,
                                ctx.runner.acquisition.pace_reading)]

    def keep(runner: SessionRunner | None) -> None:
        if runner is not None:
            runners.append(runner)

    vrig.bus.subscribe(said, inline=True)
    vrig.when(phase, PHASES[phase], lambda: FAULTS[fault](vrig), experiment=FIRST)
    result = vrig.run_session(tmp_path / "s", LETTERS, attach=attach, on_runner=keep)
    vrig.bus.close()                                      # the terminal has said everything
    meta = json.loads((tmp_path / "s" / "session.json").read_text())

    # exit code and status as before
    assert result.exit_code == EXIT_ABORTED and meta["status"] == result.status
    assert result.status.startswith("aborted: ")
    # "At rest" only where the controller was read, and then it was true
    assert truth, "no sentence about the rig's state after a stop"
    for sentence, at_rest, link_up in truth:
        if sentence.startswith("At rest"):
            assert at_rest and link_up, sentence
    last, _, link_up = truth[-1]
    if fault in ("controller dead", "simulator killed"):
        assert last.startswith("Not known to be at rest: the controller could not be read"), last
        assert "safe stop incomplete" in meta["status"]
    else:   # the controller answers after the fault: the last sentence is what it read
        assert not last.startswith("Not known"), last
        state = vrig.sim.controller.state
        assert last.startswith("At rest" if state in (State.OFF, State.IDLE) else "Stopped by the controller's alarm")
    # the terminal and session.log say the same sentences, never "At rest" after an unread stop
    log_sentences = [describe(e) for e in read_log(tmp_path / "s" / "session.log")
                     if e.kind == Kind.PHASE and e.data["phase"] == Phase.IDLE]
    assert log_sentences == [s for s, _, _ in truth]
    lines = terminal.getvalue().splitlines()
    assert [line.split("  ", 1)[-1].strip() for line in lines if "rest" in line] == \
        [s for s, _, _ in truth if "rest" in s]
    # the pace: only streams that ended as planned measure it, and the sentence names its clock
    pace = runners[0].acquisition.pace_reading()
    if phase in ("settling", "capturing") and fault != "link lost":
        assert pace.over.startswith("the pace probe's"), pace     # the cut stream is not a measurement
    assert "this computer's clock" in str(pace) and "the DAQ's sample count" in str(pace)


def test_a_session_that_completes_reads_the_controller_at_rest(vrig, tmp_path):
    result = vrig.run_session(tmp_path / "s", ["j"])
    assert result.exit_code == EXIT_OK
    idle = [e for _, e in vrig.events if e.kind == Kind.PHASE and e.data["phase"] == Phase.IDLE]
    assert [e.data["controller"] for e in idle] == ["IDLE", "OFF"]     # after STOP; after hydraulics off
    assert [describe(e) for e in idle] == ["At rest: the controller reads IDLE.",
                                           "At rest: the controller reads OFF, hydraulics off."]


def test_the_pace_in_the_last_line_says_what_measured_it():
    out = io.StringIO()
    clock = iter([0.0, 165.0])
    progress = ConsoleProgress(Console(file=out, width=300), {"261126j": 1600.0}, 10.0, lambda: next(clock),
                               lambda: PaceReading(10.02, "150 s of this session's streams that ended as planned"))
    progress(Event(Kind.SESSION_END, None, {"message": "complete", "exit_code": 0}))
    last = out.getvalue().splitlines()[-1]
    assert last == ("session took 2:45 min:s of this computer's clock; at 10 rig seconds per second of this "
                    "computer's clock (the DAQ's sample count over 150 s of this session's streams that ended as "
                    "planned), about 27:33 min:s of rig time; announced 26:40")


def test_an_old_log_without_a_reading_does_not_say_at_rest():
    assert describe(Event(Kind.PHASE, None, {"phase": "idle"})) == \
        "Stopped (the controller's state after the stop is not on record)."


def test_settling_says_the_cycles_left_not_a_bias_of_hundreds_of_sigma():
    """'could bias the fit by up to 560 σ' every 5 cycles: alarming and not actionable.
    The criterion is said once per experiment, each line then counts the cycles left."""
    from rig.config import load_rig_config
    from rig.session.acquisition import drift_cycles_left

    ss = load_rig_config(None).steady_state
    assert ss.drift is not None
    limit = ss.drift.fraction
    # 560 σ decaying ×0.8 per cycle reaches the limit in log(limit/560)/log(0.8) cycles
    import math
    expected = math.ceil(math.log(limit / 560.0) / math.log(0.8))
    assert drift_cycles_left(ss, ss.min_cycles + 10, 560.0, 0.8) == expected
    assert drift_cycles_left(ss, ss.min_cycles + 10, 560.0, 1.02) is None           # not decaying
    assert drift_cycles_left(ss, 1, limit / 2, 0.8) == ss.min_cycles - 1             # the minimum still to wait

    out = io.StringIO()
    progress = ConsoleProgress(Console(file=out, width=300), {"261126c": 600.0})
    for cycles, left in ((10, 40), (15, 35)):
        progress(Event(Kind.PROGRESS, "261126c", {"phase": "settling", "cycles": cycles, "ratio": 0.9,
                                                  "bias_sigma": 560.0, "bias_limit_sigma": limit,
                                                  "cycles_left": left, "change": {"force_N": 0.4}}))
    lines = out.getvalue().splitlines()[1:]
    assert len(lines) == 3 and "σ" not in out.getvalue()
    assert lines[0] == (f"[1/1] 261126c  Settling: the capture waits until the transient left by the move could shift "
                        f"the fitted parameters by less than {limit:g} of their standard deviation; the lines below "
                        "count the cycles left until then.")
    assert lines[1] == ("[1/1] 261126c  Cycle 10: the block means moved by force 0.4 N; about 40 more cycles to settle "
                        "(it decays ×0.900 per cycle).")
    assert lines[2].startswith("[1/1] 261126c  Cycle 15:") and "about 35 more cycles" in lines[2]


def test_no_rig_time_is_said_for_a_session_whose_link_was_lost():
    """The killed simulator's session said 'about 2:39 min:s of rig time': the wall time
    at a pace measured before, through the seconds the link was being waited for."""
    out = io.StringIO()
    clock = iter([0.0, 16.0])
    progress = ConsoleProgress(Console(file=out, width=400), {"261126j": 105.0}, 9.91, lambda: next(clock),
                               lambda: PaceReading(9.91, "5 s of this session's streams that ended as planned"))
    progress(Event(Kind.LINK, None, {"link": "controller", "state": "lost", "message": "Modbus link lost"}))
    progress(Event(Kind.SESSION_END, None, {"message": "aborted: …", "exit_code": 3}))
    last = out.getvalue().splitlines()[-1]
    assert last.startswith("session took 0:16 min:s of this computer's clock; its rig time is not known: the "
                           "controller link was lost") and "about" not in last
    # a link lost and back again measures on
    out, clock = io.StringIO(), iter([0.0, 16.0])
    progress = ConsoleProgress(Console(file=out, width=400), {"261126j": 105.0}, 9.91, lambda: next(clock),
                               lambda: PaceReading(9.91, "5 s of this session's streams that ended as planned"))
    for state in ("lost", "back"):
        progress(Event(Kind.LINK, None, {"link": "controller", "state": state, "message": state}))
    progress(Event(Kind.SESSION_END, None, {"message": "complete", "exit_code": 0}))
    assert "about 2:38 min:s of rig time" in out.getvalue().splitlines()[-1]
