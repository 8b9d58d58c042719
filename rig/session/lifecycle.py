"""The one session lifecycle, :func:`run_lifecycle`: every entry (``rig run``, ``rig qc
run``, the console, ``rig.open(...).run_plan()``) runs a session through it, and
hands its subscribers a :class:`SessionContext` (with the session's one
:class:`~rig.session.session_progress.SessionProgress`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from rich.console import Console

from rig.drivers.shaker import MotionInterlock
from rig.errors import RigError
from rig.events import EventBus, Kind, Subscriber
from rig.session.acquisition import Interrupted
from rig.session.links import Links, close_links, connect
from rig.session.outcome import ExitStatus, RunResult
from rig.session.preparation import Prepared
from rig.session.runner import SessionRunner, interrupt_on_signals
from rig.session.session_progress import SessionProgress, session_progress
from rig.session.storage import Session, SessionLog

ORDERING_PROGRESS_S = 1.5    # at most this long between two lines while the plan is ordered


# ----- the one lifecycle ------------------------------------------------------------------------------
@dataclass
class SessionContext:
    """What a caller's subscribers are built from, once the session's rig time is predicted."""

    runner: SessionRunner
    session: Session
    estimates_s: dict[str, float]            # rig time per experiment still to do, by label
    pace: float                              # the links' rig seconds per second (1 on a rig)
    progress: SessionProgress                # the session's one progress, current before any subscriber hears an event

    @property
    def rig_clock(self) -> Callable[[], float]:
        return self.runner.acquisition.clock.monotonic

    @property
    def current_pace(self) -> Callable[[], float]:
        """The pace as the session corrects it from its own streams (for the time left)."""
        return self.runner.acquisition.current_pace


def run_lifecycle(prep: Prepared, console: Console | None = None, *, links: Links | None = None,
                  bus: EventBus | None = None, interlock: MotionInterlock | None = None,
                  subscribers: Sequence[Subscriber] = (),
                  attach: Callable[[SessionContext], Sequence[Subscriber]] | None = None,
                  on_runner: Callable[[SessionRunner | None], object] | None = None) -> RunResult:
    """A prepared session from its links to its teardown, the one way every entry runs one
    (``rig run``, ``rig qc run``, the console, ``rig.open(...).run_plan()``):

    links (opened here unless the caller holds them) → the session folder → its journal
    and session.log → the pace probe → the predicted durations (on record) → the
    caller's ``attach`` subscribers, built from them → every experiment → the safe stop
    → the honest status → the links (if opened here), the bus (if made here) and the
    log closed.

    ``interlock`` (an E-STOP's latch) vetoes the session's motion commands from the first
    one on.  ``console``: where a failure to close something at the end is said (the
    logging module's ``rig.session.run`` logger without one).

    ``subscribers`` get every event from the first (queued: the acquisition never waits
    on them); ``on_runner`` is told the runner once it exists and None once it is gone
    (the console's Abort and E-STOP reach the session through it).  A failure before the
    session folder exists is raised: nothing written, nothing moved.  From the moment it
    exists, whatever happens ends in a status that is not ``running``: ``aborted: …``
    (exit 3; 70 for a bug, which comes back in ``result.error`` for the caller to raise
    once the record is written), ``interrupted (…)`` (130) or ``ended: …``, with the
    safe stop wherever motion may have started (:meth:`SessionRunner.run`)."""
    own_bus, own_links = bus is None, links is None
    bus = bus if bus is not None else EventBus()
    for fn in subscribers:
        bus.subscribe(fn)
    runner: SessionRunner | None = None
    log: SessionLog | None = None
    moved = False
    try:
        if links is None:
            links = connect(prep, on_event=bus.publish_link, interlock=interlock)
        else:
            # Links held across sessions (a script's rig): the actuator may have moved since they connected.
            links.start_position_m = links.shaker.status().position_m
            if interlock is not None:
                links.shaker.interlock = interlock
        prep = _ordered(prep, bus)
        runner = SessionRunner(prep, links, bus)
        if on_runner is not None:
            on_runner(runner)
        session = runner.create_session()      # from here on, session.json says how the session ended
        with interrupt_on_signals(runner):
            try:
                links.daq.attach_journal(session.journal_path)
                log = SessionLog(session.path / "session.log")
                bus.subscribe(log, inline=True)
                estimates = runner.estimates_s(session, links.start_position_m)   # the pace probe, then durations
                runner.announce_prediction(session)
                # On record, so that the estimate can be checked against what the session took.
                session.meta["estimated_rig_time_s"] = round(sum(estimates.values()), 1)
                acq = runner.acquisition
                progress = session_progress(prep.plan.experiments, session.label, estimates, prep.config,
                                            acq.current_pace, acq.clock.monotonic,
                                            earlier=[session.label(letter) for letter in session.completed()])
                bus.subscribe(progress, inline=True)
                context = SessionContext(runner, session, estimates, runner.pace or 1.0, progress)
                for fn in attach(context) if attach else ():
                    bus.subscribe(fn)
            except BaseException as exc:  # noqa: BLE001 — nothing has moved yet: on record, no safe stop needed
                return _ended_before_motion(runner, session, exc)
            moved = True
            return runner.run(session)
    finally:
        if on_runner is not None:
            on_runner(None)
        _teardown(runner, links, own_links, bus if own_bus else None, log, disarm=not moved, console=console)


def _ordered(prep: Prepared, bus: EventBus) -> Prepared:
    """The plan in the order it runs, its progress said on the bus: the standard plan's
    thermal ordering takes seconds of CPU (15 to 25 on a busy host), which no terminal
    or console may spend in silence."""
    n = len(prep.plan.experiments)
    if prep.plan.order != "thermal" or n < 2:
        return prep.ordered()
    bus.publish(Kind.LOG, message=f"ordering the {n} experiments for the least predicted rig time: the damper "
                                  "model predicts each one's settling after every other one", ordering=True)
    started = last = time.monotonic()

    def told(done: int, total: int) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= ORDERING_PROGRESS_S and done < total:
            last = now
            bus.publish(Kind.LOG, message=f"ordering: {done} of {total} experiments' successors predicted "
                                          f"({now - started:.0f} s)", ordering=True)

    prep = prep.ordered(told)
    bus.publish(Kind.LOG, message=f"ordered in {time.monotonic() - started:.1f} s: "
                                  f"{', '.join(e.letter for e in prep.plan.experiments)}", ordering=True)
    return prep


def _ended_before_motion(runner: SessionRunner, session: Session, exc: BaseException) -> RunResult:
    """The outcome of a session that failed between its folder and its first command
    (journal, log, pace probe, durations): the rig was not moved, so no safe stop."""
    result = RunResult(session, before_motion=True)
    if isinstance(exc, (Interrupted, KeyboardInterrupt)):
        result.end(ExitStatus.INTERRUPTED, runner.stop_reason or "SIGINT")
    elif isinstance(exc, RigError):
        result.end(ExitStatus.ABORTED, str(exc), exc)
    else:
        result.end(ExitStatus.FAILED, f"internal error: {type(exc).__name__}: {exc}", exc)
    runner.bus.publish(Kind.LOG, message=f"session {result.status}")
    session.finish(result.status, result.to_json())
    runner.bus.publish(Kind.SESSION_END, message=result.status, exit_code=result.exit_code,
                       exit_status=result.exit_status.value)
    return result


def _teardown(runner: SessionRunner | None, links: Links | None, own_links: bool, bus: EventBus | None,
              log: SessionLog | None, *, disarm: bool, console: Console | None) -> None:
    """The writer's thread, then the links (their threads publish to the log; a caller's
    links are kept open, their stream stopped and the session's journal let go), then
    the bus, then the log.  A failure here is said but changes nothing of the record
    already written."""
    said_on = runner.bus if runner is not None else bus     # open until its own step below

    def say(text: str, *, on_record: bool = False) -> None:
        if console is not None:
            console.print(f"[yellow]{text}[/yellow]", highlight=False)
        else:
            logging.getLogger(__name__).error("%s", text)
        if on_record and said_on is not None:   # the bus and session.log are still open
            said_on.publish(Kind.LOG, message=text)

    def links_closed() -> None:
        assert links is not None
        for failure in close_links(links, disarm=disarm):   # a watchdog left armed trips the rig later: said
            say(f"closing the links: {failure}", on_record=True)

    steps: list[tuple[str, Callable[[], object]]] = []
    if runner is not None:
        steps.append(("session writer", runner.close))
    if links is not None and own_links:
        steps.append(("links", links_closed))
    elif links is not None:
        steps += [("DAQ stream", links.daq.stop), ("DAQ journal", links.daq.detach_journal)]
    if bus is not None:
        steps.append(("event bus", bus.close))
    if log is not None:
        steps.append(("session log", log.close))
    for what, close in steps:
        try:
            close()
        except Exception as exc:  # noqa: BLE001 — the session's status is on record already
            say(f"closing the {what} failed: {exc}")
