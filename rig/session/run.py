"""A whole session, in four steps that can each be read and tested on their own:

``prepare``    every file, address, plan and argument checked; nothing written,
               nothing sent (:class:`~rig.errors.BadInput` → exit 2);
``connect``    both links opened and the controller's state read; a dead link or a
               latched alarm ends here, still with nothing written (exit 3);
``run``        the session folder, then every planned experiment.  From here on the
               actuator may move, so *whatever* ends this step (the plan done, an
               alarm, a lost link, Ctrl-C/SIGTERM/SIGHUP, a bug) goes through
``tear down``  the safe stop (fade if running, STOP, hydraulics off), the session's
               status written as it is, the links closed.

How a session ended is data, :class:`~rig.session.outcome.RunResult` (in the spirit of
Bluesky's ``RunEngineResult``): an :class:`~rig.session.outcome.ExitStatus` (complete,
ended, aborted, failed, interrupted), whether the plan was cut short, the reason and the
exception, and the safe stop's failures (``panicked``: the watchdog is the last guard).
The status sentence of session.json is rendered from them, and stored beside them.

Exit status: 0 every experiment captured (or skipped by ``--on-alarm skip``);
1 identification did not converge; 2 bad input, refused before anything moved or
was written; 3 aborted (alarm, lost link, controller or DAQ fault, a latched alarm
at start) after the safe stop; 130 interrupted by the operator (or SIGTERM/SIGHUP)
after the safe stop; 70 an internal error (a bug: traceback shown) after the safe stop.
"""

from __future__ import annotations

import logging
import shlex
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console

from identify.dataset import Experiment
from identify.exit_codes import EXIT_NOT_CONVERGED, EXIT_OK
from identify.files import atomic_write_bytes
from identify.model import DEFAULT_ESTIMATE
from rig.config import RigConfig, load_rig_config
from rig.drivers.daq import Calibration, Daq, DaqError, check_daq_address
from rig.drivers.peer_identity import Peers
from rig.drivers.peers import wrong_peer_or
from rig.drivers.registers import ControllerState, RegisterMap, load_register_map
from rig.drivers.shaker import AlarmError, MotionInterlock, Shaker, ShakerAddress, ShakerError, ShakerLinkError
from rig.errors import RigError, RigFault
from rig.events import Event, EventBus, Kind, LinkNotice, Subscriber
from rig.planning.plans import ExperimentDuration, Plan, PlanError, check_plan, load_plan
from rig.planning.prediction import LinkTiming, measured, predict, remember
from rig.session.acquisition import Acquisition, ExperimentRecord, Interrupted
from rig.session.outcome import ExitStatus, RunResult, stored_exit_status
from rig.session.progress import ConsoleProgress, describe
from rig.session.storage import Session, SessionError, SessionLog

if TYPE_CHECKING:  # the numerics are imported when a fit runs, not with the command line
    from identify.result import FitResult

INTERRUPTING_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
ORDERING_PROGRESS_S = 1.5    # at most this long between two lines while the plan is ordered


@dataclass
class RunOptions:
    plan: str
    shaker: str | None
    daq: str | None
    out: Path
    experiments: list[str] | None = None
    periods: int | None = None
    resume: bool = False
    reset_alarm: bool = False               # clear an alarm latched before the session (read and logged first)
    identify: bool = False
    on_alarm: str = "abort"                 # or "skip"
    rig_config: str | None = None
    calibration: str | None = None
    register_map: str | None = None
    model: str = "2dof"
    params: str | None = None
    estimate: list[str] = field(default_factory=list)   # empty: the plan's purpose, else the model's default
    date: str | None = None
    unit_serial: str = "unknown"
    order: str | None = None                # thermal or fixed; None: the plan's, and a --experiments list as given


class PlanRefused(PlanError):
    """The plan breaks the rig's limits; every violation is listed."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.problems = problems
        lines = "\n".join(f"  {p}" for p in problems)
        super().__init__(f"plan refused, nothing moved ({len(problems)} violation{'s' if len(problems) > 1 else ''}"
                         f" of the limits in {source}):\n{lines}")


class AlarmLatched(RigFault):
    """The controller holds an alarm from before this session: nothing is moved until
    someone who knows why has cleared it."""


@dataclass
class Prepared:
    """Everything a session needs, checked; nothing has been written or sent yet."""

    options: RunOptions
    shaker_url: str
    daq_url: str
    config: RigConfig
    calibration: Calibration
    register_map: RegisterMap
    plan: Plan                              # as listed until ordered()
    stored: Session | None                  # the session to resume, as read

    def ordered(self, progress: Callable[[int, int], object] | None = None) -> Prepared:
        """With the plan in the order it runs. The lifecycle orders once the links have
        answered, so that a wrong or swapped address is named within seconds, not after
        the standard plan's seconds of ordering (told to ``progress``)."""
        return replace(self, plan=self.plan.ordered(self.config, progress=progress))


@dataclass
class Links:
    shaker: Shaker
    daq: Daq
    identity: str
    latched_alarm: str | None                # an alarm cleared by --reset-alarm, for the record
    start_position_m: float = 0.0            # where the actuator stood when the session connected
    peers: Peers | None = None               # who answered on both links (session.json, QC records)


# ----- prepare: check everything, write nothing ----------------------------------------------------
def prepare(opt: RunOptions) -> Prepared:
    config = load_rig_config(opt.rig_config)
    calibration = Calibration.from_file(opt.calibration)
    register_map = load_register_map(opt.register_map)
    stored = None
    if opt.resume:
        stored = Session.load(opt.out)
        if stored_exit_status(stored.meta) is ExitStatus.COMPLETE:
            raise SessionError(f"{opt.out}: the session is complete; nothing to resume")
        meta = stored.meta
        if "identify" in meta and not opt.identify:   # asked for when the session began
            wanted = meta["identify"]
            opt = replace(opt, identify=True, model=wanted["model"], estimate=wanted["estimate"],
                          params=wanted["params"])
        plan = load_plan(meta["plan"]).select(meta["experiments"]).with_periods(meta["periods"])
        shaker_url = opt.shaker or meta.get("endpoints", {}).get("shaker")
        daq_url = opt.daq or meta.get("endpoints", {}).get("daq")
    else:
        Session.check_new(opt.out)
        plan = load_plan(opt.plan).select(opt.experiments).with_periods(opt.periods)
        shaker_url, daq_url = opt.shaker, opt.daq
    if not shaker_url or not daq_url:
        raise SessionError("--shaker and --daq are needed (a resumed session takes them from its session.json)")
    ShakerAddress.parse(shaker_url)
    check_daq_address(daq_url)
    problems = check_plan(plan, config)
    if problems:
        raise PlanRefused(config.source, problems)
    if stored is None:
        # Settling is most of a session and depends on the experiment before: on request
        # the order of least predicted rig time (a resumed session keeps the order it began
        # with; a list of experiments the operator typed runs as typed unless --order thermal).
        order = opt.order or ("fixed" if opt.experiments else plan.order)
        plan = replace(plan, order=order)
    opt = replace(opt, estimate=opt.estimate or designed_estimate(plan, opt.model))
    if opt.identify:
        _check_identification(opt)
    return Prepared(opt, shaker_url, daq_url, config, calibration, register_map, plan, stored)


def designed_estimate(plan: Plan, model: str) -> list[str]:
    """The parameters a fit of this plan's data estimates when none are named: those the
    plan was designed for (its purpose, for the same model), else the model's default."""
    if plan.purpose is not None and plan.purpose.model == model:
        return list(plan.purpose.estimate)
    return list(DEFAULT_ESTIMATE.get(model, ()))


def _check_identification(opt: RunOptions) -> None:
    """Model, start file and estimated names, before the rig spends an hour on data they would refuse."""
    from identify.model import load_model
    from identify.parameters import Parameters

    if not opt.estimate:
        raise PlanError("--estimate names no parameter")
    model = load_model(opt.model)
    params = Parameters.from_file(model, opt.params) if opt.params else Parameters(model)
    params.set_estimated(opt.estimate)


# ----- connect: both links, and the controller's state ------------------------------------------------
def connect(prep: Prepared, on_event: Callable[[LinkNotice], object],
            interlock: MotionInterlock | None = None) -> Links:
    """Open both links for a prepared session.  The caller closes them (:func:`close_links`).
    ``interlock`` (an E-STOP's latch) vetoes every motion command from the first one on."""
    return open_links(prep.shaker_url, prep.daq_url, prep.config, prep.calibration, prep.register_map,
                      reset_alarm=prep.options.reset_alarm, on_event=on_event, interlock=interlock)


def open_links(shaker_url: str, daq_url: str, config: RigConfig, calibration: Calibration,
               register_map: RegisterMap, *, reset_alarm: bool, on_event: Callable[[LinkNotice], object],
               interlock: MotionInterlock | None = None) -> Links:
    """Open the controller and the DAQ and read the controller's state; a latched alarm
    is refused unless ``reset_alarm``.  On any failure both links are closed again."""
    shaker = Shaker(shaker_url, config.limits, register_map, reconnect_s=config.reconnect_s, on_event=on_event,
                    interlock=interlock)
    daq = Daq(daq_url, calibration, rate_hz=config.daq_rate_hz, reconnect_s=config.reconnect_s, on_event=on_event)
    links = Links(shaker, daq, "", None)
    try:
        shaker.connect()
        links.identity = daq.open()
        links.peers = Peers(shaker.identify(), links.identity)
        status = shaker.status()
        links.start_position_m = status.position_m
        if status.state is ControllerState.ALARM:
            if not reset_alarm:
                raise AlarmLatched(
                    f"the controller at {shaker_url} holds a latched alarm: {status.alarm} (stroke "
                    f"{status.position_m * 1e3:.2f} mm). Find out why, then clear it with "
                    f"'python -m rig stop --reset --shaker {shaker_url}' or run again with --reset-alarm")
            links.latched_alarm = status.alarm
            shaker.reset_alarm()
            if shaker.status().state is ControllerState.ALARM:
                raise AlarmLatched(f"the controller at {shaker_url} still holds the alarm {status.alarm} "
                                   "after a reset: the cause is still there")
    except (ShakerLinkError, DaqError) as exc:
        close_links(links)
        raise wrong_peer_or(exc, shaker_url, daq_url, register_map) from None   # the other box may have answered
    except BaseException:
        close_links(links)
        raise
    return links


def probe_timing(shaker_url: str, daq_url: str, config: RigConfig) -> LinkTiming:
    """The links' pace and latencies measured now (the session's pace probe: the DAQ
    streams, the controller's state is read; nothing moves), for a prediction made
    before a session (``rig design --shaker … --daq …``); kept as the last measured."""
    bus = EventBus()
    links = open_links(shaker_url, daq_url, config, Calibration.from_file(), load_register_map(), reset_alarm=False,
                       on_event=bus.publish_link)
    try:
        # As in a session: the DAQ's bytes journalled to disk as they come (the DAQ's stop,
        # part of every latency measured, waits for that journal's flush).
        with tempfile.TemporaryDirectory(prefix="rig-pace-probe-") as scratch:
            links.daq.attach_journal(Path(scratch) / "daq-raw.bin")
            try:
                acq = Acquisition(links.shaker, links.daq, config, bus, links.shaker.clock)
                pace = acq.measure_pace()
            finally:
                links.daq.detach_journal()
    finally:
        close_links(links, disarm=True)
        bus.close()
    timing = measured(pace, acq.answer_s, acq.overhead_s, f"{shaker_url} and {daq_url}", "a pace probe just now")
    remember(timing)
    return timing


def close_links(links: Links, *, disarm: bool = False) -> None:
    """Close both links; with ``disarm``, first hand the controller back with its watchdog
    off, as the manual commands leave it: a session that ends before it ran took nothing
    over, and an armed watchdog would trip a rig left with its hydraulics on."""
    steps = ([links.shaker.disable_watchdog] if disarm else []) + [links.shaker.close, links.daq.close]
    for close in steps:
        try:
            close()
        except Exception:  # noqa: BLE001 — closing must not hide why the session ended
            pass


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
            with _interrupt_on_signals(self):
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
def _interrupt_on_signals(runner: SessionRunner) -> Iterator[None]:
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
        return [ConsoleProgress(console, ctx.estimates_s, ctx.current_pace, ctx.rig_clock,
                                ctx.runner.acquisition.pace_reading)]

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


# ----- the one lifecycle ------------------------------------------------------------------------------
@dataclass
class SessionContext:
    """What a caller's subscribers are built from, once the session's rig time is predicted."""

    runner: SessionRunner
    session: Session
    estimates_s: dict[str, float]            # rig time per experiment still to do, by label
    pace: float                              # the links' rig seconds per second (1 on a rig)

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
        with _interrupt_on_signals(runner):
            try:
                links.daq.attach_journal(session.journal_path)
                log = SessionLog(session.path / "session.log")
                bus.subscribe(log, inline=True)
                estimates = runner.estimates_s(session, links.start_position_m)   # the pace probe, then durations
                runner.announce_prediction(session)
                # On record, so that the estimate can be checked against what the session took.
                session.meta["estimated_rig_time_s"] = round(sum(estimates.values()), 1)
                for fn in attach(SessionContext(runner, session, estimates, runner.pace or 1.0)) if attach else ():
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
    steps: list[tuple[str, Callable[[], object]]] = []
    if runner is not None:
        steps.append(("session writer", runner.close))
    if links is not None and own_links:
        steps.append(("links", lambda: close_links(links, disarm=disarm)))
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
            if console is not None:
                console.print(f"[yellow]closing the {what} failed:[/yellow] {exc}", highlight=False)
            else:
                logging.getLogger(__name__).error("closing the %s failed: %s", what, exc)


def resume_command(session: Session, opt: RunOptions) -> str:
    """What the operator types to go on (``--reset-alarm`` only where the watchdog or an
    alarm will be latched: the operator is told, not surprised)."""
    args = ["python", "-m", "rig", "run", "--resume", "--out", str(session.path)]
    if opt.identify:
        args += ["--identify", "--model", opt.model, "--estimate", ",".join(opt.estimate)]
        if opt.params:
            args += ["--params", opt.params]
    return shlex.join(args) + "  (add --reset-alarm if the controller reports a latched alarm)"


def fit_session(session: Session, model_name: str, params_file: str | Path | None, estimate: list[str],
                captured: list[Experiment],
                progress: Callable[[int, float, np.ndarray], None] | None = None) -> FitResult:
    """Fit the session's periodic experiments: those captured in this run from memory,
    earlier ones (a resumed session) from their files; RESULT.json and report.txt are
    written into the session.  The numbers equal ``python -m identify fit`` on the folder;
    ``progress`` follows the estimator's iterations (the GUI's fit view)."""
    from identify.dataset import read_dataset
    from identify.fit import fit_experiments
    from identify.model import load_model
    from identify.parameters import Parameters
    from identify.preparation import model_columns, resolve_outputs

    model = load_model(model_name)
    params = Parameters.from_file(model, params_file) if params_file else Parameters(model)
    by_label = {e.label: e for e in captured}
    earlier = [e["label"] for e in session.manifest["experiments"] if e["label"] not in by_label]
    if earlier:
        stored = read_dataset(session.path, model_columns(model, resolve_outputs(model, None)), earlier)
        by_label.update((label, stored.experiment(label)) for label in earlier)
    experiments = [by_label[e["label"]] for e in session.manifest["experiments"] if e.get("kind") == "periodic"]
    result = fit_experiments(model, experiments, params, estimate, progress=progress)
    result.write_json(session.path / "RESULT.json")
    atomic_write_bytes(session.path / "report.txt", (result.fit_report() + "\n").encode())
    return result


def purpose_departure(manifest: dict[str, Any], estimate: list[str]) -> str | None:
    """The warning a fit's first line carries where it holds a parameter the session's plan
    was designed for at its prior (None without a purpose, or where it fits them all)."""
    from identify.plans import Purpose

    if "purpose" not in manifest:
        return None
    return Purpose.from_document(manifest["purpose"], "dataset.json").departure(estimate)


def identify_session(session: Session, opt: RunOptions, console: Console, captured: list[Experiment]) -> int:
    """``rig run --identify``: fit in memory right after the capture, print the report."""
    from identify.errors import IdentifyError

    command = (f"python -m identify fit {session.path} --model {opt.model} --estimate {','.join(opt.estimate)}"
               + (f" --params {opt.params}" if opt.params else "") + " --output RESULT.json")
    departure = purpose_departure(session.manifest, opt.estimate)
    if departure:
        console.print(departure, highlight=False)
    console.print(f"identifying {', '.join(opt.estimate)} ({opt.model}) on the session's periodic experiments; "
                  f"same as: {command}", highlight=False)
    try:
        result = fit_session(session, opt.model, opt.params, opt.estimate, captured)
    except IdentifyError as exc:
        console.print(f"[red]identification failed:[/red] {exc} (the captured session is complete and kept)",
                      highlight=False)
        return EXIT_NOT_CONVERGED
    print(result.fit_report())
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED
