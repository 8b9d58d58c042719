"""The rig side of the operator's console (no Qt here): the links, the manual commands,
the session runner, the fits and the E-STOP, each on its own thread.  Whatever happens
is *posted* as a small typed record (a :class:`rig.events.Message`, as the session's
events are) into a queue that the window drains on its own timer, so that the GUI
thread never talks to the rig, and the rig never waits on the GUI.

Threads:

``rig-command``   manual commands, connecting, reconnecting after a session (one at a time)
``rig-status``    reads the controller's status and the DAQ's counters, 4 times a second
``rig-session``   prepare → :func:`rig.session.run.run_lifecycle` (links → session → safe stop),
                  as ``rig run``;
                  or QC mode's ``python -m rig qc run`` as a child process (:mod:`rig.gui.qc`)
``fit``           identification and re-fits, one at a time, each in a process of its own
                  (:mod:`rig.gui.fits`: a fit in this process would stall the window)
``e-stop``        :class:`rig.drivers.estop.EStop`: on a press, mode STOP and hydraulics off on a
                  Modbus connection of its own, opened in advance and used for nothing
                  else; its latch then vetoes every motion command of the console's and
                  the session's links until the operator confirms the reset

Outside a session the console holds its own links: the controller with its watchdog
fed (if this program dies, the controller trips and holds), and the DAQ streaming for
the live view.  A session opens its links afresh exactly as ``rig run`` does (its
journal starts with the handshake), so the console lets go of its links first (the DAQ
takes one client at a time) and takes them back after the safe stop.
"""

from __future__ import annotations

import io
import signal
import subprocess
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from identify.errors import IdentifyError, InputError
from identify.model import DEFAULT_ESTIMATE
from rig.config import RigConfig, load_rig_config
from rig.drivers.daq import Calibration, Daq, DaqError
from rig.drivers.estop import EStop
from rig.drivers.peer_identity import Peers
from rig.drivers.peers import wrong_peer_or
from rig.drivers.registers import RegisterMap, load_register_map
from rig.drivers.shaker import Shaker, ShakerLinkError, ShakerStatus, check_waveform
from rig.errors import BadInput, RigError
from rig.events import Event, Kind, LinkCondition, LinkNotice, Message, Subscriber
from rig.gui import fits
from rig.gui.fits import FitRunner, FitSummary
from rig.gui.plan_state import PlanProgress
from rig.gui.qc import ProgressReader, QcDone, QcRequest, outcome, qc_command
from rig.session.run import (
    EXIT_OK,
    Links,
    RunOptions,
    RunResult,
    SessionContext,
    SessionRunner,
    close_links,
    prepare,
    run_lifecycle,
)

STATUS_PERIOD_S = 0.25
CONSOLE_RECONNECT_S = 2.0


# ----- what is posted to the window: each a rig.events.Message, as the session's events are --------------
@dataclass(frozen=True)
class Snapshot(Message):
    """The controller and the DAQ as last read (status None: not connected or unreadable)."""

    status: ShakerStatus | None
    error: str | None
    received: int = 0
    lost: int = 0
    crc_errors: int = 0
    over_range: int = 0
    overflow_flags: int = 0
    heartbeat_ok: bool = True
    samples: int = -1                       # the DAQ stream's samples since START, read with the status (-1: none)
    time: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class Notice(Message):
    text: str
    level: str = "info"                    # info, refused, error


@dataclass(frozen=True)
class LinkState(Message):
    connected: bool
    text: str
    simulated: bool = False     # a peer named itself a simulator (rig.drivers.peer_identity)


@dataclass(frozen=True)
class SessionOpened(Message):
    path: Path
    progress: PlanProgress
    options: RunOptions


@dataclass(frozen=True)
class SessionClosed(Message):
    result: RunResult | None               # None: refused or failed before the session folder existed
    text: str


@dataclass(frozen=True)
class FitProgress(Message):
    title: str
    iteration: int
    objective: float


@dataclass(frozen=True)
class FitDone(Message):
    title: str
    result: FitSummary
    folder: Path


@dataclass(frozen=True)
class ComparisonDone(Message):
    results: dict[str, FitSummary]
    folder: Path


@dataclass(frozen=True)
class QcStarted(Message):
    request: QcRequest


@dataclass(frozen=True)
class IdentifySettings:
    model: str = "2dof"
    params: str | None = None
    estimate: list[str] = field(default_factory=lambda: list(DEFAULT_ESTIMATE["2dof"]))


class Station:
    def __init__(self, shaker_url: str | None, daq_url: str | None, post: Callable[[Message], None], *,
                 rig_config: str | None = None, calibration: str | None = None, register_map: str | None = None,
                 speed: float = 1.0) -> None:
        self.shaker_url, self.daq_url, self.post, self.speed = shaker_url, daq_url, post, speed
        self.config_files = {"rig_config": rig_config, "calibration": calibration, "register_map": register_map}
        self.config: RigConfig = load_rig_config(rig_config)
        self.calibration = Calibration.from_file(calibration)
        self.register_map: RegisterMap = load_register_map(register_map)
        self.shaker: Shaker | None = None           # the console's links (outside sessions)
        self.daq: Daq | None = None
        self.runner: SessionRunner | None = None    # the session's, while one runs
        self.manual_frequency_hz: float | None = None
        self.manual_runs = 0                         # manual sines sent: each new one is a new excitation
        self.heartbeat_ok = True
        self.closing = False                         # the window is closing: no links taken back
        self._was_connected = False
        self._abort = threading.Event()
        self._closed = threading.Event()
        self._commands = ThreadPoolExecutor(1, "rig-command")
        self._fits = FitRunner(lambda title, it, objective: post(FitProgress(title, it, objective)),
                               lambda title, text: post(Notice(f"{title} failed: {text}", "error")))
        self._session: threading.Thread | None = None
        self._qc: subprocess.Popen | None = None
        # Posts EstopDone, and LatchChanged on every trip and reset (the window's motion controls follow it).
        self.emergency = EStop(self.config.limits, self.register_map, fallback=self.active_shaker, on_done=post)
        self.emergency.subscribe(post)
        self._poller = threading.Thread(target=self._poll, name="rig-status", daemon=True)
        self._poller.start()

    # ----- state ----------------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self.shaker is not None or self.runner is not None

    @property
    def session_running(self) -> bool:
        return self._session is not None and self._session.is_alive()

    def active_shaker(self) -> Shaker | None:
        runner = self.runner
        return runner.links.shaker if runner is not None else self.shaker

    def live_daq(self) -> Daq | None:
        runner = self.runner
        return runner.links.daq if runner is not None else self.daq

    # ----- links ----------------------------------------------------------------------------------------
    def connect(self, shaker_url: str | None = None, daq_url: str | None = None) -> Future:
        self.shaker_url, self.daq_url = shaker_url or self.shaker_url, daq_url or self.daq_url
        return self._commands.submit(self._job, "connect", self._connect)

    def _connect(self) -> None:
        if self.shaker is not None:
            return
        if not self.shaker_url or not self.daq_url:
            raise BadInput("give the controller's and the DAQ's addresses (--shaker, --daq) or --simulate")
        shaker = Shaker(self.shaker_url, self.config.limits, self.register_map, reconnect_s=CONSOLE_RECONNECT_S,
                        on_event=self._link_event, interlock=self.emergency.latch)
        daq = Daq(self.daq_url, self.calibration, rate_hz=self.config.daq_rate_hz, reconnect_s=CONSOLE_RECONNECT_S,
                  on_event=self._link_event)
        try:
            self._open_estop_line(self.shaker_url)
            shaker.connect()        # limits written, watchdog on and fed: if this program dies, the rig holds
            identity = daq.open()
            peers = Peers(shaker.identify(), identity)
            daq.start()             # the live view streams whenever no session does
        except (ShakerLinkError, DaqError) as exc:
            close_links(Links(shaker, daq, "", None))
            raise wrong_peer_or(exc, self.shaker_url, self.daq_url, self.register_map) from None
        except BaseException:
            close_links(Links(shaker, daq, "", None))
            raise
        self.shaker, self.daq = shaker, daq
        self.post(LinkState(True, f"controller {self.shaker_url}, DAQ {self.daq_url} ({identity})", peers.simulated))

    def _release(self) -> None:
        shaker, daq = self.shaker, self.daq
        self.shaker = self.daq = None
        if shaker is not None and daq is not None:
            close_links(Links(shaker, daq, "", None))

    def disconnect(self) -> Future:
        def job() -> None:
            self._release()
            self.post(LinkState(False, "disconnected"))
        return self._commands.submit(self._job, "disconnect", job)

    def _link_event(self, notice: LinkNotice) -> None:
        """The console's own links (outside sessions)."""
        self._heartbeat(notice.state)
        self.post(Notice(notice.message))

    def _session_event(self, event: Event) -> None:
        """A session's events, for the window (queued: the acquisition never waits on it)."""
        if event.kind == Kind.LINK:
            self._heartbeat(LinkCondition(event.data["state"]))
        self.post(event)

    def _heartbeat(self, state: LinkCondition) -> None:
        if state is LinkCondition.HEARTBEAT_FAILING:
            self.heartbeat_ok = False
        elif state is LinkCondition.HEARTBEAT_BACK:
            self.heartbeat_ok = True

    # ----- manual commands: checked here, sent on the command thread ------------------------------------
    def _refuse_manual(self, status: ShakerStatus | None, need_hydraulics: bool, motion: bool = True) -> list[str]:
        if self.session_running:
            return ["a session is running: abort it first"]
        if motion and self.emergency.latched:
            return [f"{self.emergency.latch.reason}: confirm the reset first"]
        if self.shaker is None:
            return ["not connected"]
        if status is not None and status.state == "ALARM":
            return [f"alarm latched ({status.alarm}): reset it first"]
        if need_hydraulics and status is not None and status.state == "OFF":
            return ["the hydraulics are off: switch them on first"]
        return []

    def _manual(self, what: str, problems: list[str], action: Callable[[Shaker], None]) -> list[str]:
        """Send ``action`` unless ``problems``; the refusal is returned and posted, nothing sent."""
        if problems:
            self.post(Notice(f"{what} refused, nothing sent: {'; '.join(problems)}", "refused"))
            return problems
        shaker = self.shaker
        assert shaker is not None  # _refuse_manual checked it

        def job() -> None:
            action(shaker)
            self.post(Notice(f"{what}: sent"))
        self._commands.submit(self._job, what, job)
        return []

    def hydraulics(self, on: bool, status: ShakerStatus | None) -> list[str]:
        problems = self._refuse_manual(status, need_hydraulics=False, motion=on)
        return self._manual(f"hydraulics {'on' if on else 'off'}", problems, lambda s: s.hydraulics(on))

    def move(self, static_m: float, status: ShakerStatus | None) -> list[str]:
        lim = self.config.limits
        problems = self._refuse_manual(status, need_hydraulics=True)
        if not lim.stroke_low_m <= static_m <= lim.stroke_high_m:
            problems.append(f"static position {static_m * 1e3:.2f} mm outside the stroke limits "
                            f"{lim.stroke_low_m * 1e3:.1f}…{lim.stroke_high_m * 1e3:.1f} mm")
        return self._manual(f"move to {static_m * 1e3:.2f} mm", problems, lambda s: s.move_to(static_m))

    def sine(self, static_m: float, amplitude_m: float, frequency_hz: float, status: ShakerStatus | None) -> list[str]:
        problems = self._refuse_manual(status, need_hydraulics=True)
        problems += check_waveform(self.config.limits, static_m, amplitude_m, frequency_hz)
        ramp = self.config.steady_state.ramp_time_s

        def run(s: Shaker) -> None:
            s.run(static_m, amplitude_m, frequency_hz, "sine", ramp)
            self.manual_frequency_hz = frequency_hz
            self.manual_runs += 1
        return self._manual(f"sine {amplitude_m * 1e3:.2f} mm at {frequency_hz:g} Hz around {static_m * 1e3:.2f} mm",
                            problems, run)

    def fade_stop(self, status: ShakerStatus | None) -> list[str]:
        """Stop: fade a running waveform out (then hold), else hold at once."""
        problems = self._refuse_manual(None, need_hydraulics=False, motion=False)
        # A fade is a move to the static position: after an E-STOP only STOP holds.
        running = status is not None and status.state == "RUNNING" and not self.emergency.latched

        def stop(s: Shaker) -> None:
            s.fade_out() if running else s.stop()
        return self._manual("fade out" if running else "stop", problems, stop)

    def reset_alarm(self) -> list[str]:
        problems = ["a session is running: abort it first"] if self.session_running else []
        if self.shaker is None and not problems:
            problems = ["not connected"]
        return self._manual("alarm reset", problems, lambda s: s.reset_alarm())

    # ----- E-STOP -----------------------------------------------------------------------------------------
    def estop(self) -> None:
        """STOP and hydraulics off at once, no fade, on the E-STOP's thread and line; a
        session (or a QC run) is told to stop too (its safe stop then finds the rig at rest)."""
        self.emergency.press()
        self._abort.set()
        runner = self.runner
        if runner is not None:
            runner.acquisition.stop_requested.set()
            runner.bus.publish(Kind.LOG, message="E-STOP pressed by the operator: STOP and hydraulics off")
        self._interrupt_qc()

    def _refuse_latched(self, what: str) -> bool:
        if not self.emergency.latched:
            return False
        self.post(Notice(f"{what} refused, nothing sent: {self.emergency.latch.reason}: confirm the reset first",
                         "refused"))
        return True

    def _open_estop_line(self, url: str | None) -> None:
        """The E-STOP's own line to ``url``; where none can be opened, the operator is told
        (the E-STOP then uses the session's or the console's link)."""
        if not url:
            return
        try:
            self.emergency.open(url)
        except RigError as exc:
            self.post(Notice(f"E-STOP line to {url} not opened ({exc}); the E-STOP will use the session's link"))

    # ----- sessions ---------------------------------------------------------------------------------------
    def run_plan(self, opt: RunOptions, identify: IdentifySettings | None) -> bool:
        """Start a session (False if one is running or an E-STOP is latched).  ``opt`` is
        what ``rig run`` would get."""
        if self.session_running or self._refuse_latched("session"):
            return False
        self._abort.clear()
        self._session = threading.Thread(target=self._run_session, args=(opt, identify), name="rig-session",
                                         daemon=True)
        self._session.start()
        return True

    def abort(self, why: str = "Abort pressed by the operator") -> None:
        """The safe stop: the session fades out, stops, switches the hydraulics off."""
        self._abort.set()
        runner = self.runner
        if runner is not None:
            runner.bus.publish(Kind.LOG, message=f"{why}: safe stop")
            runner.acquisition.stop_requested.set()
        self._interrupt_qc()

    # ----- QC mode ----------------------------------------------------------------------------------------
    def run_qc(self, request: QcRequest) -> bool:
        """Test one unit with ``python -m rig qc run`` (False if a session or a QC run is
        going, or an E-STOP is latched)."""
        if self.session_running or self._refuse_latched(f"QC of unit {request.serial}"):
            return False
        self._abort.clear()
        self._session = threading.Thread(target=self._run_qc, args=(request,), name="rig-session", daemon=True)
        self._session.start()
        return True

    def _run_qc(self, request: QcRequest) -> None:
        done: QcDone | None = None
        try:
            if not self.shaker_url or not self.daq_url:
                raise BadInput("give the controller's and the DAQ's addresses (--shaker, --daq) or --simulate")
            self._open_estop_line(self.shaker_url)
            self._was_connected = self.shaker is not None
            self._commands.submit(self._release).result()      # the DAQ takes one client: the child's
            cmd = qc_command(request, self.shaker_url, self.daq_url, self.config_files)
            self.post(QcStarted(request))
            if self._abort.is_set():
                raise RigError("aborted before the QC run started")
            # Its own process group: Ctrl-C in the console's terminal reaches the console,
            # whose safe stop then interrupts the child once.
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
            self._qc = proc
            if self._abort.is_set():
                self._interrupt_qc()
            stdout: list[str] = []
            reader = threading.Thread(target=lambda: stdout.extend(proc.stdout or ()), name="qc-stdout", daemon=True)
            reader.start()
            tail: deque[str] = deque(maxlen=20)
            progress = ProgressReader()
            for line in proc.stderr or ():
                line = line.rstrip()
                tail.append(line)
                if line:
                    self.post(Notice(f"QC {request.serial}: {line}"))
                if (step := progress.feed(line)) is not None:
                    self.post(step)
            proc.wait()
            reader.join()
            done = outcome(request, proc.returncode, "".join(stdout), list(tail))
        except (BadInput, RigError) as exc:
            done = QcDone(request.serial, -1, "REFUSED", reason=str(exc))
        except Exception as exc:  # noqa: BLE001 — a bug: shown with its traceback, the console goes on
            done = QcDone(request.serial, -1, "ERROR", reason=f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        finally:
            self._qc = None
            if done is not None:
                self.post(done)
            if self._was_connected and not self.closing:
                self._commands.submit(self._job, "reconnect", self._connect)

    def _interrupt_qc(self) -> None:
        """A QC run's safe stop: SIGINT, as Ctrl-C in its terminal (recorded ABORTED, no verdict)."""
        proc = self._qc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)

    def _run_session(self, opt: RunOptions, identify: IdentifySettings | None) -> None:
        result: RunResult | None = None
        try:
            result = self._session_steps(opt)
        except (BadInput, InputError, RigError) as exc:
            self.post(SessionClosed(None, f"session not started: {exc}"))
        except Exception as exc:  # noqa: BLE001 — a bug: shown with its traceback, the console goes on
            self.post(SessionClosed(None, f"internal error: {type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
        finally:
            if self._was_connected and not self.closing:
                self._commands.submit(self._job, "reconnect", self._connect)
        if result is None:
            return
        self.post(SessionClosed(result, f"session {result.status}: {result.session.path}"))
        if result.exit_code == EXIT_OK and identify is not None and result.captured:
            self.identify(result, opt)

    def _session_steps(self, opt: RunOptions) -> RunResult | None:
        prep = prepare(opt)                      # refused here: nothing written, nothing sent
        self._open_estop_line(prep.shaker_url)
        self._was_connected = self.shaker is not None
        self._commands.submit(self._release).result()

        def runner_changed(runner: SessionRunner | None) -> None:
            if runner is not None:
                runner.links.shaker.interlock = self.emergency.latch   # before the session's first motion command
            self.runner = runner
            if runner is not None and self._abort.is_set():   # Abort or E-STOP while the links were opened
                runner.acquisition.stop_requested.set()

        def opened(ctx: SessionContext) -> list[Subscriber]:
            progress = PlanProgress(ctx.runner.prep.plan, prep.config, ctx.session.meta["date"], self.speed,
                                    ctx.session.completed())
            self.post(SessionOpened(ctx.session.path, progress, opt))
            return []

        # The window's queue: the acquisition never waits on it.
        result = run_lifecycle(prep, Console(file=io.StringIO()), subscribers=[self._session_event], attach=opened,
                               on_runner=runner_changed)
        if result.error is not None:
            self.post(Notice(f"internal error in the session: {result.error!r}", "error"))
        return result

    @property
    def fitting(self) -> bool:
        return self._fits.busy

    def wait_session(self, timeout_s: float | None = None) -> bool:
        """True once no session runs (for closing the window and for tests)."""
        thread = self._session
        if thread is not None:
            thread.join(timeout_s)
        return not self.session_running

    # ----- fits -------------------------------------------------------------------------------------------
    def identify(self, result: RunResult, opt: RunOptions) -> None:
        title = f"identification {opt.model} of {result.session.path.name}"
        folder = result.session.path
        self._fits.submit(title, fits.session_fit, (result.session, opt, result.captured),
                          lambda summary: self.post(FitDone(title, summary, folder)))

    def refit(self, folder: Path, settings: IdentifySettings) -> None:
        title = f"re-fit {settings.model} of {folder.name}"
        self._fits.submit(title, fits.refit, (folder, settings.model, settings.params, list(settings.estimate)),
                          lambda summary: self.post(FitDone(title, summary, folder)))

    def compare(self, folder: Path, settings: IdentifySettings) -> None:
        title = f"1-dof vs 2-dof on {folder.name}"
        self._fits.submit(title, fits.compare_models, (folder, list(settings.estimate), settings.params),
                          lambda results: self.post(ComparisonDone(results, folder)))

    # ----- plumbing ---------------------------------------------------------------------------------------
    def _job(self, what: str, fn: Callable[[], None]) -> None:
        """Run one job; its failure is posted in one line (bugs with their traceback)."""
        try:
            fn()
        except (BadInput, InputError, RigError, IdentifyError) as exc:
            self.post(Notice(f"{what} failed: {exc}", "error"))
        except Exception as exc:  # noqa: BLE001 — a bug: shown, the console goes on
            self.post(Notice(f"{what}: internal error {type(exc).__name__}: {exc}\n{traceback.format_exc()}",
                             "error"))

    def _poll(self) -> None:
        while not self._closed.wait(STATUS_PERIOD_S):
            shaker, daq = self.active_shaker(), self.live_daq()
            if shaker is None:
                continue
            status, error = None, None
            try:
                status = shaker.status()
            except Exception as exc:  # noqa: BLE001 — shown as the link's state
                error = str(exc)
            kw = {}
            if daq is not None:
                c = daq.counters
                # the parser's index restarts at START itself; the ring holds the last stream's samples
                # until the first frames of the new one arrive
                kw = dict(received=daq.parser.received, lost=c.lost_samples, crc_errors=c.crc_errors,
                          over_range=c.over_range, overflow_flags=c.overflow_flags, samples=daq.parser.next_index)
            self.post(Snapshot(status, error, heartbeat_ok=self.heartbeat_ok, **kw))

    def close(self, timeout_s: float = 60.0) -> None:
        """Safe stop of a running session, then every link closed and every thread ended."""
        self.closing = True
        self.abort("the console is closing")
        self.wait_session(timeout_s)
        self._closed.set()
        self.emergency.close()
        self._commands.submit(self._release)
        self._commands.shutdown(wait=True)
        self._fits.close()
        self._poller.join(timeout=2)


def session_options(plan: str, shaker: str | None, daq: str | None, out: Path, experiments: list[str] | None,
                    station: Station, identify: IdentifySettings | None, resume: bool = False) -> RunOptions:
    """The options ``rig run`` would be given for the same session."""
    files = station.config_files
    opt = RunOptions(plan=plan, shaker=shaker, daq=daq, out=out, experiments=experiments, resume=resume,
                     identify=identify is not None, rig_config=files["rig_config"],
                     calibration=files["calibration"], register_map=files["register_map"])
    if identify is not None:
        opt.model, opt.params, opt.estimate = identify.model, identify.params, list(identify.estimate)
    return opt

