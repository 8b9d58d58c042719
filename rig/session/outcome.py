"""How a session ended, as data (in the spirit of Bluesky's ``RunEngineResult``): an
:class:`ExitStatus`, whether the plan was cut short, the reason and the exception.  The
status sentence that session.json, the terminal and the console show is rendered from
these fields (:attr:`RunResult.status`), never parsed back: code reads the fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from identify.dataset import Experiment
from identify.exit_codes import EXIT_ABORTED, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK
from rig.session.storage import Session


class ExitStatus(StrEnum):
    """The end state of a session (session.json's ``exit_status``)."""

    RUNNING = "running"            # not ended (on disk: the process died without a word)
    COMPLETE = "complete"          # every planned experiment captured
    ENDED = "ended"                # ended by the plan's owner: decided early, or experiments skipped after alarms
    ABORTED = "aborted"            # an alarm, a lost link, a controller or DAQ fault, a failed safe stop at the end
    FAILED = "failed"              # an internal error (a bug), or the safe stop itself raised
    INTERRUPTED = "interrupted"    # a stop request: the operator, SIGINT/SIGTERM/SIGHUP


EXIT_CODES = {ExitStatus.COMPLETE: EXIT_OK, ExitStatus.ENDED: EXIT_OK, ExitStatus.ABORTED: EXIT_ABORTED,
              ExitStatus.FAILED: EXIT_INTERNAL, ExitStatus.INTERRUPTED: EXIT_INTERRUPTED,
              ExitStatus.RUNNING: EXIT_INTERNAL}


def stored_exit_status(meta: dict[str, Any]) -> ExitStatus | None:
    """How a stored session ended, from its session.json's ``outcome``.  A session written
    before the outcome was has only the sentence: its status where the sentence is the
    bare word (``complete``, ``running``), otherwise None (the sentence is not parsed)."""
    outcome = meta.get("outcome")
    word = outcome.get("exit_status") if isinstance(outcome, dict) else meta.get("status")
    return ExitStatus(word) if word in set(ExitStatus) else None


@dataclass
class RunResult:
    """How a session ended (the record of it is ``session.json``).

    ``reason``: what ended it, as said to the operator: the alarm or fault
    (``aborted``), ``internal error: …`` (``failed``), the stop request's reason, e.g. the
    signal's name (``interrupted``), why the plan's owner ended it early or which
    experiments were skipped (``ended``); empty for ``complete``.  ``exception``: what
    was raised to end it (None for a stop request or an ending on purpose)."""

    session: Session
    exit_status: ExitStatus = ExitStatus.RUNNING
    reason: str = ""
    exception: BaseException | None = None
    interrupted: bool = False                # the plan did not run to its end (a stop, an alarm, a fault, a bug)
    before_motion: bool = False              # ended between the session folder and the first command
    planned: int = 0                         # experiments this run set out to do
    captured: list[Experiment] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    safe_stop_failures: list[str] = field(default_factory=list)
    unwritten: str | None = None             # an experiment captured at the end but not written, and why
    decided: str | None = None               # why the session ended before its plan did (SessionRunner.decide)

    @property
    def exit_code(self) -> int:
        return EXIT_CODES[self.exit_status]

    @property
    def error(self) -> BaseException | None:
        """A bug, re-raised by the caller once the record is written (None otherwise)."""
        return self.exception if self.exit_status is ExitStatus.FAILED else None

    @property
    def panicked(self) -> bool:
        """The safe stop did not complete: the controller's watchdog is the last guard."""
        return bool(self.safe_stop_failures)

    def end(self, status: ExitStatus, reason: str = "", exception: BaseException | None = None) -> None:
        self.exit_status, self.reason, self.exception = status, reason, exception
        self.interrupted = status not in (ExitStatus.COMPLETE, ExitStatus.ENDED) or self.decided is not None

    @property
    def status(self) -> str:
        """The status sentence (session.json's ``status``, the terminal's last line),
        rendered from the fields."""
        s = self.exit_status
        if s is ExitStatus.COMPLETE:
            text = "complete"
        elif s is ExitStatus.ENDED:
            text = f"ended: {len(self.captured)} of {self.planned} experiments captured, {self.reason}"
        elif s is ExitStatus.INTERRUPTED:
            text = f"interrupted ({self.reason})" + (" before anything moved" if self.before_motion else "")
        elif s is ExitStatus.RUNNING:
            text = "running"
        else:
            text = f"aborted: {self.reason}" + (" (before anything moved)" if self.before_motion else "")
        if self.unwritten:
            text += f"; {self.unwritten}"
        if self.safe_stop_failures:
            text += ("; safe stop incomplete (" + "; ".join(self.safe_stop_failures)
                     + "): the controller's watchdog stops the shaker once this program has let go")
        return text

    def to_json(self) -> dict[str, Any]:
        """The structured outcome beside the sentence in session.json."""
        return {"exit_status": self.exit_status.value, "exit_code": self.exit_code, "interrupted": self.interrupted,
                "reason": self.reason, "exception": (f"{type(self.exception).__name__}: {self.exception}"
                                                     if self.exception is not None else None),
                "before_motion": self.before_motion, "skipped": list(self.skipped),
                "safe_stop_failures": list(self.safe_stop_failures)}
