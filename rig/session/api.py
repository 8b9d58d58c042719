"""The scripting API: the lab procedure in Python, on the machinery of ``rig run``.

    import rig

    with rig.open(shaker="tcp://127.0.0.1:5020", daq="socket://127.0.0.1:5021") as r:
        print(r.status())
        session = r.run_plan("standard", experiments=["j", "n"], out="sessions/unit-17")
        result = session.identify()            # the model's default set: theta4, theta6, theta16
        print(result.report())

Nothing here runs a subprocess: a :class:`Rig` holds the same two links as ``rig run``
and a session goes through the same prepare / run / safe stop
(:mod:`rig.session.run`), so a scripted session is on disk what a command-line session is.
Leaving the ``with`` block, whatever the reason, ends in the safe stop.  Errors are
those of :mod:`rig.errors`; a session that did not complete raises
:class:`SessionFailed` after its safe stop, with the session attached for a resume.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from rich.console import Console

from identify.dataset import Experiment
from identify.model import DEFAULT_ESTIMATE
from rig.config import RigConfig, load_rig_config
from rig.drivers.daq import Calibration
from rig.drivers.registers import ControllerState, RegisterMap, load_register_map
from rig.drivers.shaker import ShakerStatus
from rig.errors import BadInput, RigFault
from rig.events import Event, EventBus, LinkNotice, Subscriber
from rig.session.acquisition import Acquisition
from rig.session.outcome import ExitStatus, RunResult
from rig.session.progress import ConsoleProgress, ProgressBar
from rig.session.run import (
    EXIT_OK,
    Links,
    RunOptions,
    SessionContext,
    SessionRunner,
    close_links,
    fit_session,
    open_links,
    prepare,
    run_lifecycle,
)
from rig.session.storage import Session as SessionFolder

if TYPE_CHECKING:
    from identify.result import FitResult

log = logging.getLogger(__name__)
Progress = Literal["auto", "bar", "lines"] | bool


def _in_notebook() -> bool:
    """A Jupyter kernel, where terminal lines would be noise and a bar is what one expects."""
    return "ipykernel" in sys.modules


class SessionFailed(RigFault):
    """A session ended short of complete (aborted, interrupted); the rig was safely stopped
    and what was captured is kept: ``.session`` says how far it got, ``.result`` how it
    ended, as data (its ``exit_status``, ``reason``, ``exception``)."""

    def __init__(self, session: Session) -> None:
        super().__init__(f"session {session.status} ({session.dataset_dir})")
        self.session = session
        self.result: RunResult | None = session.result


class Session:
    """A planned session on a :class:`Rig`: subscribe to its events, run it, identify."""

    def __init__(self, rig: Rig, options: RunOptions, progress: Progress) -> None:
        self._rig, self._options, self._progress = rig, options, progress
        self._prepared = prepare(options)
        self._subscribers: list[Callable[[Event], None]] = []
        self._folder: SessionFolder | None = None
        self._result: RunResult | None = None

    def subscribe(self, callback: Callable[[Event], None]) -> None:
        """``callback(event)`` for every event of the session, from a thread of its own
        (the acquisition never waits on it)."""
        self._subscribers.append(callback)

    def run(self) -> Session:
        """Capture every planned experiment; returns when the session has ended."""
        if self._result is not None:
            raise RuntimeError("this session has run; plan a new one (or resume it with resume=True)")
        rig = self._rig

        def runner_changed(runner: SessionRunner | None) -> None:
            rig._bus = runner.bus if runner is not None else None   # the links' notices go to the session

        def progress(ctx: SessionContext) -> list[Subscriber]:
            self._folder = ctx.session
            if self._progress == "bar" or (self._progress == "auto" and _in_notebook()):
                return [ProgressBar(ctx.progress)]
            if self._progress:
                return [ConsoleProgress(rig._console, ctx.progress, pace_reading=ctx.runner.acquisition.pace_reading)]
            return []

        self._result = result = run_lifecycle(self._prepared, rig._console, links=rig._links,
                                              subscribers=self._subscribers, attach=progress,
                                              on_runner=runner_changed)
        self._folder = result.session
        if result.error is not None:
            raise result.error
        if result.exit_code != EXIT_OK:
            raise SessionFailed(self)
        return self

    @property
    def result(self) -> RunResult | None:
        """How the session ended, as data (None until :meth:`run` has returned or raised):
        read its ``exit_status`` (:class:`~rig.session.outcome.ExitStatus`), ``reason``,
        ``exception``, ``captured``, ``skipped``; :attr:`status` is the sentence for people."""
        return self._result

    @property
    def exit_status(self) -> ExitStatus | None:
        """The session's end state (None while planned): what a script decides on."""
        return self._result.exit_status if self._result is not None else None

    @property
    def status(self) -> str:
        """``planned``, then what ``session.json`` says: complete, ended: …, aborted: …
        (a sentence for people; code reads :attr:`exit_status` or :attr:`result`)"""
        return self._folder.meta["status"] if self._folder is not None else "planned"

    @property
    def dataset_dir(self) -> Path:
        return Path(self._options.out)

    @property
    def experiments(self) -> list[dict[str, Any]]:
        """The captured experiments as ``dataset.json`` lists them (label, file, settle cycles, …)."""
        return list(self._folder.manifest["experiments"]) if self._folder is not None else []

    def identify(self, model: str = "2dof", estimate: Sequence[str] | None = None,
                 params: str | Path | None = None) -> FitResult:
        """Fit the captured experiments (the same :class:`~identify.result.FitResult` as
        ``identify.fit``); RESULT.json and report.txt go into the session folder.
        ``estimate``: by default those the plan was designed for (its purpose, for this
        model), else a built-in model's set (``identify.model.DEFAULT_ESTIMATE``)."""
        from identify.plans import Purpose

        if self._folder is None:
            raise RuntimeError("nothing captured yet: run() the session first")
        captured: list[Experiment] = self._result.captured if self._result is not None else []
        doc = self._folder.manifest.get("purpose")
        purpose = Purpose.from_document(doc, "dataset.json") if doc else None
        if estimate is None and purpose is not None and purpose.model == model:
            estimate = purpose.estimate
        if estimate is None and model not in DEFAULT_ESTIMATE:
            raise BadInput(f"model {model}: name the parameters to estimate (estimate=[...])")
        names = list(estimate) if estimate is not None else list(DEFAULT_ESTIMATE[model])
        return fit_session(self._folder, model, params, names, captured)


class Rig:
    """A connected rig: the controller and the DAQ, as ``rig run`` holds them."""

    def __init__(self, shaker: str, daq: str, *, rig_config: str | None = None, calibration: str | None = None,
                 register_map: str | None = None, reset_alarm: bool = False, console: Console | None = None) -> None:
        self._rig_config, self._calibration, self._register_map = rig_config, calibration, register_map
        self.shaker_url, self.daq_url = shaker, daq
        self.config: RigConfig = load_rig_config(rig_config)
        calibration_table = Calibration.from_file(calibration)
        registers: RegisterMap = load_register_map(register_map)
        self._console = console or Console(stderr=True, soft_wrap=True)
        self._bus: EventBus | None = None   # the running session's, for the links' messages
        self._links: Links = open_links(shaker, daq, self.config, calibration_table, registers,
                                        reset_alarm=reset_alarm, on_event=self._link_event)
        self._idle_bus = EventBus()
        self._stopper = Acquisition(self._links.shaker, self._links.daq, self.config, self._idle_bus)

    def _link_event(self, notice: LinkNotice) -> None:
        bus = self._bus
        if bus is not None:
            bus.publish_link(notice)
        else:
            log.warning("%s", notice.message)

    # ----- the lab procedure ---------------------------------------------------------------------
    def status(self) -> ShakerStatus:
        return self._links.shaker.status()

    def move(self, position_mm: float, wait_s: float = 60.0) -> ShakerStatus:
        """Hydraulics on and move to a static position; returns once there."""
        shaker = self._links.shaker
        shaker.move_to(position_mm * 1e-3, switch_on=True)
        return shaker.wait_for({ControllerState.AT_STATIC}, timeout_s=wait_s)

    def plan(self, plan: str | Path = "standard", *, out: str | Path, experiments: Sequence[str] | None = None,
             periods: int | None = None, on_alarm: str = "abort", date: str | None = None, unit: str = "unknown",
             resume: bool = False, progress: Progress = "auto") -> Session:
        """A session checked and ready to :meth:`Session.run` (nothing written yet).
        ``progress``: "auto" (a bar in notebooks, lines in a terminal), "bar", "lines" or False."""
        options = RunOptions(plan=str(plan), shaker=self.shaker_url, daq=self.daq_url, out=Path(out),
                             experiments=list(experiments) if experiments else None, periods=periods, resume=resume,
                             on_alarm=on_alarm, date=date, unit_serial=unit, rig_config=self._rig_config,
                             calibration=self._calibration, register_map=self._register_map)
        return Session(self, options, progress)

    def run_plan(self, plan: str | Path = "standard", *, out: str | Path, experiments: Sequence[str] | None = None,
                 periods: int | None = None, **options: Any) -> Session:
        """:meth:`plan` and run it: returns once the session is complete."""
        return self.plan(plan, out=out, experiments=experiments, periods=periods, **options).run()

    def stop(self) -> list[str]:
        """The safe stop: fade out if running, STOP, hydraulics off; the steps that failed."""
        return self._stopper.safe_stop("stop requested by the script")

    # ----- lifetime ------------------------------------------------------------------------------
    def close(self) -> None:
        """The safe stop, then both links closed."""
        try:
            failures = self.stop()
            if failures:
                log.error("safe stop incomplete (%s): the controller's watchdog stops the shaker",
                          "; ".join(failures))
        finally:
            close_links(self._links)
            self._idle_bus.close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open(shaker: str, daq: str, **options: Any) -> Rig:  # noqa: A001 — rig.open() reads like the procedure
    """Connect to the rig's controller and DAQ (see :class:`Rig`)."""
    return Rig(shaker, daq, **options)
