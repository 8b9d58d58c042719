"""QC mode's rig side (no Qt here): one unit's test is :func:`rig.qc.run.test_unit`, the
function ``rig qc run`` calls, run by the console's session worker with the window's
subscribers (rig.gui.session_worker): the same checks, session, identification,
judgement, record, report and exit status, through the one session lifecycle.

What the QC panel shows comes from typed data only: its progress from the session's
events and the re-prediction of the time left (:class:`QcTracker`), its verdict and
table from the stored record (:func:`done_from`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from identify.exit_codes import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_INTERNAL
from rig.events import Event, Kind, Message
from rig.qc import DEFAULT_SPEC
from rig.qc.judge import Outcome
from rig.qc.present import shown
from rig.qc.run import EXIT_BY_VERDICT, Prediction, QcOptions, QcOutcome

# What the operator is told to do: an INCONCLUSIVE unit is neither passed nor failed, it is tested again.
SHOWN = {Outcome.PASS: "PASS", Outcome.FAIL: "FAIL", Outcome.INCONCLUSIVE: "RETEST"}
VERDICT_BY_EXIT = {code: outcome for outcome, code in EXIT_BY_VERDICT.items()}
RUNNING_SHARE = 0.95     # of its estimate, the most a running experiment counts as done before it is written


@dataclass(frozen=True)
class QcRequest:
    serial: str
    spec: str = DEFAULT_SPEC
    out: Path = Path("qc")             # the station's folder: a session folder per unit, and the records
    operator: str | None = None
    periods: int | None = None         # a retest's: more than the spec's

    def options(self, shaker: str, daq: str, config_files: dict[str, str | None]) -> QcOptions:
        """What ``rig qc run`` would be given for the same unit on the same rig."""
        return QcOptions(spec=self.spec, serial=self.serial, shaker=shaker, daq=daq, out=Path(self.out),
                         operator=self.operator, periods=self.periods, rig_config=config_files.get("rig_config"),
                         calibration=config_files.get("calibration"), register_map=config_files.get("register_map"))


@dataclass(frozen=True)
class QcStarted(Message):
    request: QcRequest


@dataclass(frozen=True)
class QcRow:
    """One characteristic as the summary prints it (rig.qc.present), each cell with its unit."""

    outcome: str
    title: str
    value: str           # value ± k·σ
    limits: str
    acceptance: str
    sigma: str = ""


@dataclass(frozen=True)
class QcProgress(Message):
    """How far a unit's test is: the fraction of the plan's rig time done and what is left."""

    fraction: float
    rig_left_s: float | None
    text: str                          # what it does now: "experiment 2 of 3 (v): settling"
    predicted_after: str = ""          # the experiments after which the time left was predicted again ("": not yet)


@dataclass(frozen=True)
class QcDone(Message):
    """How one unit's test ended, as the QC panel shows it."""

    serial: str
    exit_code: int
    shown: str                         # PASS, FAIL, RETEST, ABORTED, REFUSED or ERROR
    report: Path | None = None
    rows: list[QcRow] = field(default_factory=list)
    causes: list[str] = field(default_factory=list)     # likely causes, in full
    remedy: str = ""
    simulated: bool = False            # the record says a peer named itself a simulator
    reason: str = ""                   # why there is no verdict (refused, aborted, error)
    retest_periods: int | None = None  # RETEST: the periods of the retest


def done_from(request: QcRequest, outcome: QcOutcome, retest_periods: int) -> QcDone:
    """The panel's verdict, table and causes from the record the test stored."""
    record = outcome.record
    verdict = VERDICT_BY_EXIT.get(outcome.exit_code) if record.verdict is not None else None
    if verdict is None:
        return QcDone(request.serial, outcome.exit_code, "ABORTED", outcome.report, simulated=record.simulated,
                      reason=record.reason or f"exit status {outcome.exit_code}")
    rows = []
    for c in record.characteristics:
        s = shown(record, c, outcome.k)
        rows.append(QcRow(s.outcome, s.title, s.value, s.limits, s.acceptance, f"{s.sigma} {s.basis}".strip()))
    return QcDone(request.serial, outcome.exit_code, SHOWN[verdict], outcome.report, rows=rows,
                  causes=list(record.diagnosis), remedy=record.remedy or "", simulated=record.simulated,
                  retest_periods=retest_periods if verdict is Outcome.INCONCLUSIVE else None)


def refused(request: QcRequest, reason: str) -> QcDone:
    return QcDone(request.serial, EXIT_BAD_INPUT, "REFUSED", reason=reason)


def ended(request: QcRequest, reason: str, report: Path | None, bug: bool) -> QcDone:
    """A test that ended on an error after its checks: the rig not reached or failing
    (ABORTED, exit 3), or a bug (ERROR, exit 70); the report where the run wrote one."""
    if bug:
        return QcDone(request.serial, EXIT_INTERNAL, "ERROR", report, reason=reason)
    return QcDone(request.serial, EXIT_ABORTED, "ABORTED", report, reason=reason)


class QcTracker:
    """A queued subscriber of the unit's session: its progress as :class:`QcProgress`,
    from the rig time predicted per experiment (the session's own estimates, on record
    in session.json), the events and the rig time the running experiment has taken so
    far (the session's clock at its measured pace, at most 95 % of its estimate until it
    is written); after each captured experiment the time left is predicted again from the
    parameters identified so far (:meth:`predicted`)."""

    def __init__(self, estimates_s: dict[str, float], post: Callable[[Message], None],
                 clock: Callable[[], float], pace: Callable[[], float]) -> None:
        self.estimates = dict(estimates_s)
        self.order = list(estimates_s)
        self.post, self.clock, self.pace = post, clock, pace
        self.done: set[str] = set()
        self.current: str | None = None
        self.started: dict[str, float] = {}    # each experiment's first event, on the session's clock
        self.phase = ""
        self.after = ""
        self._lock = threading.Lock()  # the bus's thread and the session's (predicted) both call in
        self._emit("session started: the first experiment")

    def __call__(self, e: Event) -> None:
        with self._lock:
            if e.experiment is not None and e.experiment in self.estimates:
                if e.kind in (Kind.PHASE, Kind.PROGRESS):
                    self.started.setdefault(e.experiment, self.clock())
                    self.current, self.phase = e.experiment, str(e.data["phase"])
                elif e.kind in (Kind.EXPERIMENT_DONE, Kind.EXPERIMENT_FAILED):
                    self.done.add(e.experiment)
                else:
                    return
            elif e.kind != Kind.SESSION_END:
                return
            if e.kind == Kind.SESSION_END:
                judging = "; identifying and judging the unit" if e.data["exit_code"] == 0 else ""
                self._emit(f"session {e.data['message']}{judging}")
            else:
                self._emit(self._doing())

    def predicted(self, prediction: Prediction) -> None:
        """The rest of the plan re-predicted (rig.qc.run.decider): its estimates scaled to it."""
        with self._lock:
            rest = [label for label in self.order if label not in prediction.after]
            total = sum(self.estimates[label] for label in rest)
            if total > 0:
                for label in rest:
                    self.estimates[label] *= prediction.rig_left_s / total
            self.after = ", ".join(prediction.after)
            self._emit(self._doing())

    def _doing(self) -> str:
        if self.current is None:
            return "session started: the first experiment"
        number = self.order.index(self.current) + 1
        return f"experiment {number} of {len(self.order)} ({self.current}): {self.phase}"

    def _emit(self, text: str) -> None:
        total = sum(self.estimates.values())
        done = sum(self.estimates[label] for label in self.done)
        # begun, not yet written (an experiment's file is written while the next one moves)
        now, pace = self.clock(), self.pace()
        running = sum(min((now - t0) * pace, RUNNING_SHARE * self.estimates[label])
                      for label, t0 in self.started.items() if label not in self.done)
        fraction = min((done + running) / total, 1.0) if total > 0 else 0.0
        self.post(QcProgress(fraction, max(total - done - running, 0.0), text, self.after))
