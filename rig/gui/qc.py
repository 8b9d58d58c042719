"""QC mode's rig side (no Qt here): one unit's test is :func:`rig.qc.run.test_unit`, the
function ``rig qc run`` calls, run by the console's session worker with the window's
subscribers (rig.gui.session_worker): the same checks, session, identification,
judgement, record, report and exit status, through the one session lifecycle.

What the QC panel shows comes from typed data only: its progress from the session's one
progress (:class:`QcTracker` renders it), its verdict and table from the stored record
(:func:`done_from`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from identify.exit_codes import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_INTERNAL
from rig.events import Event, Kind, Message
from rig.gui.units import GAS_PRESSURE_UNIT
from rig.qc import DEFAULT_SPEC
from rig.qc.judge import Outcome
from rig.qc.present import shown
from rig.qc.records import QcRecord
from rig.qc.run import EXIT_BY_VERDICT, Prediction, QcOptions, QcOutcome
from rig.qc.spec import Spec
from rig.session.session_progress import SessionProgress

# What the operator is told to do: an INCONCLUSIVE unit is neither passed nor failed, it is tested again.
SHOWN = {Outcome.PASS: "PASS", Outcome.FAIL: "FAIL", Outcome.INCONCLUSIVE: "RETEST"}
VERDICT_BY_EXIT = {code: outcome for outcome, code in EXIT_BY_VERDICT.items()}


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
    origin: str = ""     # measured, identified or predicted (a key of ORIGINS)


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
    trace: str = ""                    # who, by which rules (spec, its revision and hash), at which k


ORIGINS = {"measured": "on the experiment's own samples",
           "identified": "from the model fitted to the measured experiments",
           "predicted": "a test the plan does not run (a drop, an excitation of its own) simulated with the "
                        "identified model, not measured"}


def origin(spec: Spec, name: str) -> str:
    """Where a characteristic's value comes from, as its kind says (a key of ORIGINS)."""
    c = next((c for c in spec.characteristics if c.name == name), None)
    if c is None:
        return ""
    if c.kind == "loop_energy":     # measured where the plan runs its experiment, else simulated
        return "measured" if c.args.get("experiment") in {e.letter for e in spec.plan.experiments} else "predicted"
    return "predicted" if c.kind == "drop_peak_force" else "identified"


def trace(record: QcRecord, k: float, typed: bool = True) -> str:
    """Who judged by which rules, at which coverage factor: the verdict's traceability line
    (``typed``: the operator's name was typed, not taken from the login)."""
    k_used = record.k if record.k is not None else k
    who = record.operator if typed else f"{record.operator} (the login name: no operator typed)"
    return (f"Operator {who} · spec {record.spec_name} revision {record.spec_version} (sha256 "
            f"{record.spec_sha256[:12]}…) · values ± kσ with k = {k_used:g}")


def done_from(request: QcRequest, outcome: QcOutcome, spec: Spec) -> QcDone:
    """The panel's verdict, table and causes from the record the test stored."""
    record = outcome.record
    verdict = VERDICT_BY_EXIT.get(outcome.exit_code) if record.verdict is not None else None
    if verdict is None:
        return QcDone(request.serial, outcome.exit_code, "ABORTED", outcome.report, simulated=record.simulated,
                      reason=record.reason or f"exit status {outcome.exit_code}",
                      trace=trace(record, outcome.k, request.operator is not None))
    rows = []
    kinds = {c.name: c.kind for c in spec.characteristics}
    for c in record.characteristics:
        # the spec's "bar" of a gas pressure is absolute: named as every other screen names it
        named = replace(c, unit=GAS_PRESSURE_UNIT) if kinds.get(c.name) == "gas_pressure" and c.unit == "bar" else c
        s = shown(record, named, outcome.k)
        rows.append(QcRow(s.outcome, s.title, s.value, s.limits, s.acceptance, f"{s.sigma} {s.basis}".strip(),
                          origin(spec, c.name)))
    return QcDone(request.serial, outcome.exit_code, SHOWN[verdict], outcome.report, rows=rows,
                  causes=list(record.diagnosis), remedy=record.remedy or "", simulated=record.simulated,
                  retest_periods=spec.retest_periods() if verdict is Outcome.INCONCLUSIVE else None,
                  trace=trace(record, outcome.k, request.operator is not None))


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
    rendered from the session's one :class:`~rig.session.session_progress.SessionProgress`
    (its fraction done and rig time left, which the re-prediction after each captured
    experiment updates through the bus: :meth:`predicted` only names the experiments it
    followed)."""

    def __init__(self, progress: SessionProgress, post: Callable[[Message], None]) -> None:
        self.progress, self.post = progress, post
        self.order = [label for label, r in progress.experiments.items() if r.note != "earlier"]
        self.after = ""
        self._lock = threading.Lock()  # the bus's thread and the session's (predicted) both call in
        self._emit("session started: the first experiment")

    def __call__(self, e: Event) -> None:
        with self._lock:
            if e.kind == Kind.SESSION_END:
                judging = "; identifying and judging the unit" if e.data["exit_code"] == 0 else ""
                self._emit(f"session {e.data['message']}{judging}")
            elif e.kind in (Kind.PHASE, Kind.PROGRESS, Kind.EXPERIMENT_DONE, Kind.EXPERIMENT_FAILED, Kind.LINK,
                            Kind.PREDICTION):
                self._emit(self._doing())

    def predicted(self, prediction: Prediction) -> None:
        """The rest of the plan re-predicted (rig.qc.run.decider): after which experiments."""
        with self._lock:
            self.after = ", ".join(prediction.after)
            self._emit(self._doing())

    def _doing(self) -> str:
        current = self.progress.current
        if current is None:
            return "between experiments" if self.progress.rig_done_s() else "session started: the first experiment"
        number = self.order.index(current.label) + 1
        return f"experiment {number} of {len(self.order)} ({current.label}): {current.status}"

    def _emit(self, text: str) -> None:
        self.post(QcProgress(self.progress.fraction_done(), self.progress.rig_left_s(), text, self.after))
