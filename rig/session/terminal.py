"""``rig run`` in a terminal: prepare, the lifecycle with the terminal's progress lines,
the last line (and how to resume), the identification asked for."""

from __future__ import annotations

import shlex
import time
from collections.abc import Callable

from rich.console import Console

from identify.exit_codes import EXIT_OK
from rig.events import Event, Kind, Subscriber
from rig.session.fitting import identify_session
from rig.session.lifecycle import SessionContext, run_lifecycle
from rig.session.outcome import RunResult
from rig.session.preparation import Prepared, RunOptions, prepare
from rig.session.progress import ConsoleProgress, describe
from rig.session.storage import Session


def run_session(opt: RunOptions, console: Console | None = None) -> int:
    """``rig run``: prepare, connect, run, tear down; identification after a complete session."""
    console = console or Console(stderr=True, soft_wrap=True)  # log lines stay whole when piped
    prep = prepare(opt)
    opt = prep.options                      # a resumed session brings its identification back
    result = execute(prep, console)
    session = result.session
    if result.error is not None:
        raise result.error
    if result.exit_code != EXIT_OK:   # one line: what happened, where the data is, how to go on
        console.print(f"[red]session {result.status}[/red]; what was captured is kept in {session.path}; to finish "
                      f"the session: {resume_command(session, opt)}", highlight=False)
        return result.exit_code
    console.print(f"session {result.status}: {session.path}", highlight=False)
    if opt.identify:
        return identify_session(session, opt, console, result.captured)
    return EXIT_OK


def execute(prep: Prepared, console: Console) -> RunResult:
    """``rig run``: the lifecycle with the terminal's progress lines, the first of them at
    once (nothing else is said before the links answer, the plan is ordered and the
    pace is probed: seconds), and the ordering's while it runs."""
    plan, n = prep.plan, len(prep.plan.experiments)
    order = "in the order of least predicted rig time" if plan.order == "thermal" and n > 1 else "as listed"
    kept = f" ({len(prep.stored.completed())} captured before, kept)" if prep.stored else ""
    console.print(f"plan {plan.name}: {n} experiment{'s' if n != 1 else ''}{kept} {order}; connecting to the "
                  f"controller at {prep.shaker_url} and the DAQ at {prep.daq_url}", highlight=False)
    early = _EarlyLines(console)
    return run_lifecycle(prep, console, subscribers=[early], attach=terminal_progress(console, early))


def terminal_progress(console: Console, early: _EarlyLines | None = None
                      ) -> Callable[[SessionContext], list[Subscriber]]:
    """The terminal's subscribers of a session (``rig run``, ``rig qc run``): the pace
    where the links run faster than the rig, then a line per phase and the ETA (and
    the ``early`` lines end there)."""
    def progress(ctx: SessionContext) -> list[Subscriber]:
        if early is not None:
            early.until = time.time()
        config = ctx.runner.prep.config
        if ctx.pace > 1.0:   # a simulator faster than the rig's own time
            console.print(f"the links run {ctx.runner.acquisition.pace_reading()}: conditioning holds shorter "
                          f"than {config.min_hold_s * ctx.pace:.0f} s are not planned (session.log has "
                          "the pace probe)", style="dim", highlight=False)
        return [ConsoleProgress(console, ctx.progress, pace_reading=ctx.runner.acquisition.pace_reading)]

    return progress


class _EarlyLines:
    """The terminal's lines before its :class:`ConsoleProgress` exists: the ordering's
    (log events marked ``ordering``) published until ``until`` (wall clock).  How a
    session ended before it began is the caller's last line, not said twice."""

    def __init__(self, console: Console) -> None:
        self.console, self.until = console, float("inf")

    def __call__(self, e: Event) -> None:
        if e.kind == Kind.LOG and e.data.get("ordering") and e.time < self.until:
            self.console.print(f"{'[session]':<8} {describe(e)}", style="dim", highlight=False, markup=False)


def resume_command(session: Session, opt: RunOptions) -> str:
    """What the operator types to go on (``--reset-alarm`` only where the watchdog or an
    alarm will be latched: the operator is told, not surprised)."""
    args = ["python", "-m", "rig", "run", "--resume", "--out", str(session.path)]
    if opt.identify:
        args += ["--identify", "--model", opt.model, "--estimate", ",".join(opt.estimate)]
        if opt.params:
            args += ["--params", opt.params]
    return shlex.join(args) + "  (add --reset-alarm if the controller reports a latched alarm)"
