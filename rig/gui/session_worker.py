"""The session worker (no Qt here): one session at a time on the ``rig-session`` thread,
a plan (what ``rig run`` would run) or a unit's QC test (what ``rig qc run`` would run,
through :func:`rig.qc.run.test_unit`), both through
:func:`rig.session.lifecycle.run_lifecycle`: links → session → safe stop.  The window is one
more subscriber of the session's events (queued: the acquisition never waits on it),
and the status poller reads the session's links while it runs.

Abort, the E-STOP and the window closing reach the session through
:meth:`SessionWorker.request_stop`, which hands the reason to the runner
(:meth:`rig.session.runner.SessionRunner.request_stop`), or keeps it for the runner
about to exist.
"""

from __future__ import annotations

import io
import threading
import traceback
from collections.abc import Callable
from pathlib import Path

from rich.console import Console
from rich.text import Text

from identify.errors import InputError
from identify.exit_codes import EXIT_OK
from rig.drivers.daq import Daq
from rig.drivers.shaker import Shaker
from rig.errors import BadInput, RigError
from rig.events import Event, Kind, LinkCondition, Message, Subscriber
from rig.gui.emergency import EmergencyStop
from rig.gui.manual import Heartbeat, ManualControl
from rig.gui.messages import Notice, SafeStopIncomplete, SessionClosed, SessionOpened
from rig.gui.plan_state import PlanProgress
from rig.gui.qc import QcDone, QcRequest, QcStarted, QcTracker, done_from, ended, refused
from rig.qc.run import Prediction, QcSubscribers, test_unit
from rig.qc.spec import load_spec
from rig.session.lifecycle import SessionContext, run_lifecycle
from rig.session.outcome import RunResult
from rig.session.preparation import Prepared, RunOptions, prepare
from rig.session.runner import SessionRunner


class SessionWorker:
    def __init__(self, post: Callable[[Message], None], manual: ManualControl, emergency: EmergencyStop,
                 heartbeat: Heartbeat, config_files: dict[str, str | None],
                 captured: Callable[[RunResult, RunOptions], None]) -> None:
        self.post, self.manual, self.emergency, self.heartbeat = post, manual, emergency, heartbeat
        self.config_files, self.captured = config_files, captured
        self.runner: SessionRunner | None = None      # the session's, while one runs
        self.closing = False                          # the window is closing: no links taken back
        self._stop_reason: str | None = None          # a stop asked for before the runner existed
        self._thread: threading.Thread | None = None
        self._tracker: QcTracker | None = None

    # ----- state ----------------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def links(self) -> tuple[Shaker | None, Daq | None]:
        runner = self.runner
        return (runner.links.shaker, runner.links.daq) if runner is not None else (None, None)

    def wait(self, timeout_s: float | None = None) -> bool:
        """True once no session runs (for closing the window and for tests)."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        return not self.running

    # ----- starting and stopping ---------------------------------------------------------------------------
    def run_plan(self, opt: RunOptions, identify: bool) -> bool:
        """Start a session (False if one is running or an E-STOP is latched)."""
        return self._start("session", self._run_plan, (opt, identify))

    def run_qc(self, request: QcRequest) -> bool:
        """Test one unit (False if a session runs or an E-STOP is latched)."""
        return self._start(f"QC of unit {request.serial}", self._run_qc, (request,))

    def _start(self, what: str, target: Callable[..., None], args: tuple) -> bool:
        if self.running or self.emergency.refuse(what):
            return False
        self._stop_reason = None
        self._thread = threading.Thread(target=target, args=args, name="rig-session", daemon=True)
        self._thread.start()
        return True

    def request_stop(self, reason: str) -> None:
        """The safe stop of the running session (fade out, STOP, hydraulics off)."""
        self._stop_reason = reason
        runner = self.runner
        if runner is not None:
            _stop(runner, reason)

    def _runner_changed(self, runner: SessionRunner | None) -> None:
        self.runner = runner
        if runner is not None and self._stop_reason is not None:   # Abort or E-STOP while the links were opened
            _stop(runner, self._stop_reason)

    def _event(self, event: Event) -> None:
        """A session's events, for the window (queued: the acquisition never waits on it)."""
        if event.kind == Kind.LINK:
            self.heartbeat.follow(LinkCondition(event.data["state"]))
        self.post(event)

    def _take_rig(self, prep: Prepared) -> None:
        """The checks passed: the E-STOP's line, and the console's links let go for the session's."""
        self.emergency.open_line(prep.shaker_url)
        self.manual.release()

    def _opened(self, ctx: SessionContext, opt: RunOptions, qc: bool) -> None:
        self.post(SessionOpened(ctx.session.path, PlanProgress(ctx.progress), opt, qc))

    # ----- a plan ---------------------------------------------------------------------------------------------
    def _run_plan(self, opt: RunOptions, identify: bool) -> None:
        result: RunResult | None = None
        try:
            prep = prepare(opt)                      # refused here: nothing written, nothing sent
            opt = prep.options                       # the parameters to fit: the plan's purpose where not named
            self._take_rig(prep)

            def attach(ctx: SessionContext) -> list[Subscriber]:
                self._opened(ctx, opt, qc=False)
                return []

            result = run_lifecycle(prep, Console(file=io.StringIO()), subscribers=[self._event], attach=attach,
                                   on_runner=self._runner_changed, interlock=self.emergency.latch)
            if result.error is not None:
                self.post(Notice(f"internal error in the session: {result.error!r}", "error"))
        except (BadInput, InputError, RigError) as exc:
            self.post(SessionClosed(None, f"session not started: {exc}"))
        except Exception as exc:  # noqa: BLE001 — a bug: shown with its traceback, the console goes on
            self.post(SessionClosed(None, f"internal error: {type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
        finally:
            if not self.closing:
                self.manual.take_back()
        if result is None:
            return
        self._stopped(result)
        self.post(SessionClosed(result, f"session {result.status}: {result.session.path}"))
        if result.exit_code == EXIT_OK and identify and result.captured:
            self.captured(result, opt)

    # ----- a unit's QC test -----------------------------------------------------------------------------------
    def _run_qc(self, request: QcRequest) -> None:
        folder: list[Path] = []

        def before(prep: Prepared) -> None:
            self._take_rig(prep)
            self.post(QcStarted(request))
            if self._stop_reason is not None:
                raise RigError(f"{self._stop_reason} before the QC run started")

        def attach(ctx: SessionContext) -> list[Subscriber]:
            folder.append(ctx.session.path)
            self._opened(ctx, ctx.runner.prep.options, qc=True)
            self._tracker = QcTracker(ctx.progress, self.post)
            return [self._tracker]

        def predicted(prediction: Prediction) -> None:
            if self._tracker is not None:
                self._tracker.predicted(prediction)

        def report() -> Path | None:
            path = folder[0] / "qc-report.html" if folder else None
            return path if path is not None and path.is_file() else None

        # The session's links are closed once it ends: the console's are taken back before
        # the identification and judging, so that the rig is read while they run.
        to = QcSubscribers(say=lambda text: self.post(Notice(f"QC {request.serial}: {_plain(text)}")), attach=attach,
                           subscribers=[self._event], on_runner=self._runner_changed, interlock=self.emergency.latch,
                           before_session=before,
                           predicted=predicted, after_session=self._qc_session_ended)
        done: QcDone
        try:
            shaker_url, daq_url = self.manual.urls
            if not shaker_url or not daq_url:
                raise BadInput("give the controller's and the DAQ's addresses (--shaker, --daq) or --simulate")
            outcome = test_unit(request.options(shaker_url, daq_url, self.config_files), to)
            done = done_from(request, outcome, load_spec(request.spec))
        except (BadInput, InputError) as exc:
            done = refused(request, str(exc))
        except RigError as exc:
            done = ended(request, str(exc), report(), bug=False)
        except Exception as exc:  # noqa: BLE001 — a bug: shown with its traceback, the console goes on
            done = ended(request, f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}", report(), bug=True)
        finally:
            self._tracker = None
            self._links_back()
        self.post(done)

    def _stopped(self, result: RunResult) -> None:
        if result.safe_stop_failures:
            self.post(SafeStopIncomplete(tuple(result.safe_stop_failures)))

    def _qc_session_ended(self, result: RunResult) -> None:
        self._stopped(result)
        self._links_back()

    def _links_back(self) -> None:
        if not self.closing:
            self.manual.take_back()


def _stop(runner: SessionRunner, reason: str) -> None:
    """The operator's stop, said in session.log at the moment it is asked for."""
    runner.bus.publish(Kind.LOG, message=f"{reason}: safe stop")
    runner.request_stop(reason)


def _plain(text: str) -> str:
    """A terminal line without its rich markup (the log pane has colours of its own)."""
    return Text.from_markup(text).plain
