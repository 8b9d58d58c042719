"""The runner of a prepared plan on connected links: every experiment, then the safe
stop (fade if running, STOP, hydraulics off) and an honest record, whatever ends it
(the plan done, an alarm, a lost link, a stop request or signal, a bug)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

from identify.exit_codes import EXIT_OK
from rig.drivers.shaker import AlarmError, ShakerError
from rig.errors import RigError, RigFault
from rig.events import EventBus, Kind
from rig.planning.plans import ExperimentDuration
from rig.planning.prediction import LinkTiming, measured, predict, remember
from rig.session.acquisition import Acquisition, ExperimentRecord, Interrupted
from rig.session.links import Links
from rig.session.outcome import ExitStatus, RunResult
from rig.session.preparation import Prepared
from rig.session.storage import Session

INTERRUPTING_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


# ----- run and tear down ------------------------------------------------------------------------------
class SessionRunner:
    """Runs a prepared plan on connected links; :meth:`run` always ends in the safe stop
    and an honest status."""

    def __init__(self, prep: Prepared, links: Links, bus: EventBus) -> None:
        self.prep, self.links, self.bus = prep, links, bus
        self.pace: float | None = None     # rig seconds per second of the links (probe_pace)
        self._durations: list[ExperimentDuration] | None = None   # the plan's prediction (durations)
        self._timing: LinkTiming | None = None                     # the links', measured (timing)
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="session-writer")
        self._writing: tuple[str, Future[None]] | None = None
        self.stop_reason: str | None = None   # the first request_stop's reason
        # One time line for the rig: the acquisition waits on the shaker's clock (the wall
        # clock, or a simulated one when a test drives an in-process simulator).
        self.acquisition = Acquisition(links.shaker, links.daq, prep.config, bus, links.shaker.clock)
        # Asked after each captured experiment but the last, its data written: a reason to
        # end the session there (qc run: every characteristic is decided), or None; it
        # may publish a re-prediction of the rest (Kind.PREDICTION) on the runner's bus.
        self.decide: Callable[[RunResult], str | None] | None = None

    def create_session(self) -> Session:
        """The new session's folder (its ``session.json`` says ``running``), or the stored
        one reopened for a resume."""
        prep, opt = self.prep, self.prep.options
        if prep.stored is not None:
            session = prep.stored
            session.reopen(peers=self._peers())
        else:
            plan = prep.plan
            snapshot = {"rig.toml": prep.config.text, "daq-calibration.toml": prep.calibration.text,
                        "register-map.toml": prep.register_map.text,
                        "plan.toml" if plan.text != "standard" else "plan.txt": plan.text + "\n"}
            session = Session.create(opt.out, plan_source=opt.plan if opt.plan == "standard" else
                                     str(Path(opt.plan).resolve()),
                                     letters=[e.letter for e in plan.experiments], periods=opt.periods,
                                     date=opt.date, snapshot=snapshot, unit={"serial": opt.unit_serial},
                                     endpoints={"shaker": prep.shaker_url, "daq": prep.daq_url},
                                     peers=self._peers(),
                                     identify={"model": opt.model, "estimate": opt.estimate,
                                               "params": str(Path(opt.params).resolve()) if opt.params else None}
                                     if opt.identify else None,
                                     purpose=plan.purpose.to_document() if plan.purpose else None)
        return session

    def _peers(self) -> dict[str, Any] | None:
        return self.links.peers.to_json() if self.links.peers is not None else None

    def durations(self, session: Session, start_position_m: float) -> list[ExperimentDuration]:
        """Rig time per experiment still to do, in plan order, with its conditioning hold:
        each starts where the one before it leaves the actuator and the gas (rig.planning.settling),
        which is what makes the standard session's settling, most of its time, predictable
        and, with the holds, short.  The damper is taken as nominal: an identification's
        start file is a guess meant to be off.  Computed once, so that the ETA announced
        and the holds run are the same prediction."""
        if self._durations is None:
            todo = tuple(e for e in self.prep.plan.experiments if e.letter not in session.completed())
            self._durations = predict(replace(self.prep.plan, experiments=todo), self.prep.config, self.timing(),
                                      start_position_m)
        return self._durations

    def timing(self) -> LinkTiming:
        """The links' pace and latencies as this session's probe measured them (probed
        once; kept for the predictions made before the next session, ``rig design``'s)."""
        if self._timing is None:
            acq = self.acquisition
            self._timing = measured(self.probe_pace(), acq.answer_s, acq.overhead_s,
                                    f"{self.prep.shaker_url} and {self.prep.daq_url}", "this session's pace probe")
            remember(self._timing)
        return self._timing

    def estimates_s(self, session: Session, start_position_m: float) -> dict[str, float]:
        """Rig time per experiment still to do, by label (see :meth:`durations`)."""
        return {session.label(d.letter): d.total_s for d in self.durations(session, start_position_m)}

    def announce_prediction(self, session: Session) -> None:
        """The predicted rig time of each experiment, phase by phase, into the session's
        events (session.log: what :func:`rig.session.timing.log_times` compares with the
        rig time each phase took)."""
        for d in self.durations(session, self.links.start_position_m):
            self.bus.publish(Kind.PHASE_PLAN, session.label(d.letter), move_s=d.move_s,
                             hold_s=d.hold.duration_s if d.hold else 0.0, lead_in_s=d.lead_in_s,
                             settle_cycles=d.settle_cycles, settle_s=d.settle_s, capture_s=d.capture_s,
                             fade_s=d.fade_s, links_s=d.links_s, total_s=d.total_s)

    def probe_pace(self) -> float:
        """The links' rig seconds per second (measured once, with the session's log on)."""
        if self.pace is None:
            self.pace = self.acquisition.measure_pace()
        return self.pace

    def request_stop(self, reason: str) -> None:
        """Ask the session to stop, the one way to do it (the console's Abort and E-STOP,
        SIGINT/SIGTERM/SIGHUP): the acquisition sees it at its next poll, the safe stop
        follows, and the session ends ``interrupted (reason)``.  The first reason asked
        is the one on record.  Safe from a signal handler: no lock is taken."""
        if self.stop_reason is None:
            self.stop_reason = reason
        self.acquisition.stop_requested.set()

    def run(self, session: Session) -> RunResult:
        """Every experiment still to do, then the safe stop and the record, whatever ends it."""
        todo = [e for e in self.prep.plan.experiments if e.letter not in session.completed()]
        result = RunResult(session, planned=len(todo))
        try:
            self._announce(session, todo)
            with interrupt_on_signals(self):
                self._capture(session, todo, result)
                self._stop_safely(result)
        finally:
            self._record(session, result)
        return result

    def _announce(self, session: Session, todo: list[Any]) -> None:
        prep, bus = self.prep, self.bus
        bus.publish(Kind.SESSION_START, shaker=prep.shaker_url, daq=prep.daq_url, identity=self.links.identity)
        if self.links.latched_alarm:
            bus.publish(Kind.LOG, message=f"alarm latched before the session: {self.links.latched_alarm}; "
                                          "cleared by --reset-alarm")
        if prep.stored is not None:
            kept = sorted(session.completed())
            plural = "s" if len(kept) != 1 else ""
            bus.publish(Kind.LOG, message=f"resuming: {len(kept)} experiment{plural} kept as captured "
                                          f"({', '.join(kept) or 'none'}), {len(todo)} to do")

    def _capture(self, session: Session, todo: list[Any], result: RunResult) -> None:
        """Every experiment; what ended the capture goes into ``result`` (nothing escapes:
        the safe stop comes next in any case)."""
        try:
            self._experiments(session, todo, result)
        except Interrupted:
            result.end(ExitStatus.INTERRUPTED, self.stop_reason or "SIGINT")
        except RigError as exc:
            self.bus.publish(Kind.LOG, message=f"aborting: {exc}")
            result.end(ExitStatus.ABORTED, str(exc), exc)
        except BaseException as exc:  # a bug: the rig is stopped all the same, then it is shown
            self.bus.publish(Kind.LOG, message=f"aborting on an internal error: {type(exc).__name__}: {exc}")
            result.end(ExitStatus.FAILED, f"internal error: {type(exc).__name__}: {exc}", exc)
        else:
            if result.decided:
                result.end(ExitStatus.ENDED, result.decided)
            elif result.skipped:
                result.end(ExitStatus.ENDED, f"skipped after alarms: {', '.join(result.skipped)}")
            else:
                result.end(ExitStatus.COMPLETE)

    def _experiments(self, session: Session, todo: list[Any], result: RunResult) -> None:
        planned = {d.letter: d for d in self.durations(session, self.links.start_position_m)}
        previous = ""
        for k, spec in enumerate(todo):
            # A hold is planned from the periodic state the experiment before leaves:
            # after one skipped on an alarm, the gas is elsewhere.
            after_skip = bool(result.skipped) and result.skipped[-1] == previous
            self._experiment(spec, session, result, planned[spec.letter], after_skip)
            previous = session.label(spec.letter)
            if self.acquisition.decided_within:   # judged as the transient record grew (qc run)
                result.decided = self.acquisition.decided_within
                self.bus.publish(Kind.LOG, message=f"ending the session before its plan: {result.decided}")
                break
            if self.decide is not None and k < len(todo) - 1:
                self._written(result)
                result.decided = self.decide(result)
                if result.decided:
                    self.bus.publish(Kind.LOG, message=f"ending the session before its plan: {result.decided}")
                    break
        # The last experiment's data are waited for after the safe stop: the rig is at
        # rest, hydraulics off, while they are written (at 10x, the seconds a CSV takes
        # were tens of seconds of the rig's time, with the hydraulics on and not in any
        # prediction).

    def _stop_safely(self, result: RunResult) -> None:
        """The safe stop, then the experiment still being written (if any) waited for."""
        result.safe_stop_failures = self.acquisition.safe_stop(_safe_stop_reason(result))
        if self._writing is not None:     # an experiment captured before the session ended
            label = self._writing[0]
            try:
                self._written(result)
            except Exception as exc:  # noqa: BLE001 — the status says what was lost
                if result.exit_code == EXIT_OK and isinstance(exc, RigError):   # not on disk
                    self.bus.publish(Kind.LOG, message=f"aborting: {exc}")
                    result.end(ExitStatus.ABORTED, str(exc), exc)
                elif result.exit_code == EXIT_OK:   # a bug in the writer: shown by the caller
                    result.end(ExitStatus.FAILED, f"internal error: {type(exc).__name__}: {exc}", exc)
                else:
                    result.unwritten = f"{label} was captured but could not be written ({exc})"

    def _record(self, session: Session, result: RunResult) -> None:
        """The outcome on record (session.json) and announced (``session-end``)."""
        if result.exit_status is ExitStatus.RUNNING:   # the announcement or the safe stop itself raised
            result.end(ExitStatus.FAILED, "the safe stop failed")
        if result.panicked and result.exit_status is ExitStatus.COMPLETE:
            result.end(ExitStatus.ABORTED, "the safe stop at the end failed")
        session.finish(result.status, result.to_json())
        self.bus.publish(Kind.SESSION_END, message=result.status, exit_code=result.exit_code,
                         exit_status=result.exit_status.value)

    def _experiment(self, spec: Any, session: Session, result: RunResult, planned: ExperimentDuration,
                    after_skip: bool) -> None:
        label = session.label(spec.letter)
        try:
            record: ExperimentRecord = self.acquisition.run_experiment(
                spec, label, None if after_skip else planned.hold, planned.time_constant_s)
        except AlarmError as exc:
            self.bus.publish(Kind.ALARM, label, message=str(exc))
            if self.prep.options.on_alarm != "skip":
                raise
            failures = self.acquisition.safe_stop(str(exc))
            if failures:
                raise RigFault(f"{exc}; the safe stop after it failed ({'; '.join(failures)})") from None
            try:
                self.links.shaker.reset_alarm()
            except ShakerError as reset_exc:
                raise RigFault(f"{exc}; the alarm could not be reset ({reset_exc})") from None
            result.skipped.append(label)
            self.bus.publish(Kind.EXPERIMENT_FAILED, label, message=f"{label} skipped after the alarm ({exc})")
            return
        # Written while the next experiment moves and settles: at rest between
        # experiments the gas cools (on a simulator at 50x, the second a CSV takes to
        # write is 50 s of the rig's time).  One write at a time, each on disk before the
        # next is handed over and before the session ends.
        self._written(result)
        self._writing = (label, self._writer.submit(self._write, session, record, result))

    def close(self) -> None:
        """The writer's thread ended (after the write it holds, which :meth:`run` waited for)."""
        self._writer.shutdown(wait=True)

    def _write(self, session: Session, record: ExperimentRecord, result: RunResult) -> None:
        """On the writer's thread: the experiment on disk, then captured, then announced."""
        experiment = session.write_experiment(record)
        result.captured.append(experiment)
        self.bus.publish(Kind.EXPERIMENT_DONE, record.label, file=experiment.file, samples=len(record.index),
                         lost=record.lost_samples, flags=record.flags)

    def _written(self, result: RunResult) -> None:
        """Wait for the experiment being written (raises what the write raised)."""
        if self._writing is None:
            return
        try:
            self._writing[1].result()
        finally:
            self._writing = None


def _safe_stop_reason(result: RunResult) -> str:
    """What the safe stop's log line says it was for."""
    if result.exit_status is ExitStatus.INTERRUPTED:
        return f"interrupted by the operator ({result.reason})"
    if result.exit_status in (ExitStatus.ABORTED, ExitStatus.FAILED) or result.decided:
        return result.reason
    return "end of session"


@contextmanager
def interrupt_on_signals(runner: SessionRunner) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP are :meth:`SessionRunner.request_stop` with the
    signal's name.  Outside the main thread (a GUI's worker) the owner of the thread
    asks for the stop itself."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: Any) -> None:
        runner.request_stop(signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in INTERRUPTING_SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
