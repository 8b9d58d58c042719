"""One session's progress, kept once (no Qt, no sentences): :class:`SessionProgress`,
an inline subscriber of the session's bus, built from the session's context (the
plan, its predicted rig time per experiment, the acquisition's clock and measured
pace).  It holds the experiments' phases, settling reports and capture fractions,
the re-predictions, the links lost, the outcome; and it computes, in one place, the
settling cycles left, the rig time left (per experiment and for the session), the
wall time that is at the measured pace, and the fraction done.

Every view renders it and none recomputes: the terminal's lines and the notebook's bar
(:mod:`rig.session.progress`), ``rig.open()``'s session, the console's plan table
(:mod:`rig.gui.plan_state`) and its QC tab (:mod:`rig.gui.qc`).  The console's plan
preview is one too, from :func:`rig.planning.prediction.predict` before any session.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from identify.plans import ExperimentSpec
from rig.config import RigConfig
from rig.events import Event, Kind, LinkCondition, Phase
from rig.planning.criterion import first_block_sample
from rig.session.outcome import ExitStatus

ACTIVE = ("moving", "settling", "capturing", "stopping")
PENDING = "pending"
RUNNING_SHARE = 0.95     # of its estimate, the most a running experiment counts as done before it is written


def deciding(config: RigConfig) -> dict[str, float]:
    """What decides the capture, as the settling reports carry it: the drift criterion's
    bias bound, or each channel's change threshold."""
    ss = config.steady_state
    if ss.criterion == "drift" and ss.drift is not None:
        return {"bias_sigma": ss.drift.fraction}
    return dict(ss.thresholds)


def predicted_cycles_left(history: Sequence[tuple[int, Mapping[str, float]]], thresholds: Mapping[str, float],
                          min_cycles: int, max_cycles: int) -> int | None:
    """Cycles until every deciding value is below its bound, from the last two settling
    reports (each taken to decay geometrically per cycle).  None while that cannot be
    told (one report, or a value not decaying)."""
    if not history:
        return None
    cycles, change = history[-1]
    floor = max(min_cycles - cycles, 0)
    over = [c for c in thresholds if change.get(c, math.inf) >= thresholds[c]]
    if not over:
        return floor
    if len(history) < 2:
        return None
    cycles0, change0 = history[-2]
    left = 0.0
    for c in over:
        a, b = change0.get(c, math.nan), change[c]
        if not (a > 0 and b > 0 and b < a) or cycles <= cycles0:
            return None
        rate = math.log(b / a) / (cycles - cycles0)          # per cycle, negative
        left = max(left, math.log(thresholds[c] / b) / rate)
    return int(min(max(math.ceil(left), floor), max(max_cycles - cycles, 0)))


@dataclass
class ExperimentProgress:
    """One experiment of the session as far as it has gone."""

    label: str
    estimate_s: float                      # rig time predicted (re-predicted: scaled)
    spec: ExperimentSpec | None = None     # None: only its estimate is known (a terminal given estimates alone)
    status: str = PENDING                  # pending, moving, settling, capturing, stopping, done, skipped, aborted…
    cycles: int = 0
    fraction: float = 0.0
    note: str = ""
    started: float | None = None           # the session's clock, at its first event
    finished: float | None = None
    settling: list[tuple[int, dict[str, float]]] = field(default_factory=list)  # cycles, change (+ bias_sigma)
    reported_left: int | None = None       # the acquisition's own cycles left (drift criterion), at the last report
    has_reported_left: bool = False
    samples: int | None = None             # the DAQ stream's newest sample as last read (settling, capturing)
    lead_samples: int = 0                  # samples after RUN before settling is counted (fade-in and lag)
    settled_at: int | None = None          # settling cycles when the capture began
    running_since: float | None = None     # when settling began (wall clock): older reads are of the last RUN

    def status_text(self) -> str:
        if self.status == "settling":
            return f"settling {self.cycles}" if self.cycles else "settling"
        if self.status == "capturing":
            return f"capturing {100 * self.fraction:.0f} %"
        return self.status + (f" ({self.note})" if self.note else "")


class SessionProgress:
    """The one projection of a session's progress (see the module's text).  Fed by the
    bus (inline: it is current before any queued view hears the event) and, in the
    console, by the status poll's sample counts (:meth:`observe`); read from any thread."""

    def __init__(self, estimates_s: Mapping[str, float], pace: float | Callable[[], float] = 1.0,
                 rig_clock: Callable[[], float] = time.monotonic, *, specs: Mapping[str, ExperimentSpec] | None = None,
                 config: RigConfig | None = None, earlier: Iterable[str] = (),
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        # pace: the links' rig seconds per second, or where to read it as the session
        # corrects it from its own streams (Acquisition.current_pace); rig_clock: the
        # acquisition's (an in-process simulator runs on its own).
        self._pace = pace if callable(pace) else (lambda: pace)
        self.rig_clock, self.wall_clock, self.config = rig_clock, wall_clock, config
        specs = specs or {}
        lead = first_block_sample(config.steady_state, config.daq_rate_hz) if config is not None else 0
        self.experiments: dict[str, ExperimentProgress] = {}
        done_before = set(earlier)
        for label in list(specs) + [x for x in estimates_s if x not in specs]:   # the plan's order
            if label in estimates_s:
                self.experiments[label] = ExperimentProgress(label, float(estimates_s[label]), specs.get(label),
                                                             lead_samples=lead)
            elif label in done_before:
                self.experiments[label] = ExperimentProgress(label, 0.0, specs.get(label), "done", note="earlier")
        self.announced_s = sum(float(x) for x in estimates_s.values())
        self.rig_started = rig_clock()
        self.predicted = False        # the rest re-predicted (Kind.PREDICTION): no correction by the done ones
        self.gone: dict[str, None] = {}   # links lost and not back ("controller", "DAQ")
        self.ended: str | None = None     # the session's status sentence, once it ended
        self.exit_status: ExitStatus | None = None
        self._lock = threading.RLock()

    # ----- fed ----------------------------------------------------------------------------------------
    def __call__(self, e: Event) -> None:
        with self._lock:
            self._apply(e)

    def apply(self, e: Event) -> ExperimentProgress | None:
        """Take one event; returns the experiment it changed."""
        with self._lock:
            return self._apply(e)

    def _apply(self, e: Event) -> ExperimentProgress | None:
        d = e.data
        if e.kind == Kind.LINK:
            if d.get("state") in (LinkCondition.LOST, LinkCondition.GONE):
                self.gone[str(d["link"])] = None
            elif d.get("state") == LinkCondition.BACK:
                self.gone.pop(str(d["link"]), None)
            return None
        if e.kind == Kind.SESSION_END:
            self.ended = str(d.get("message", ""))
            self.exit_status = ExitStatus(d["exit_status"]) if d.get("exit_status") else None
            # an experiment the session's end cut short ends as the session did (aborted beside "Session aborted")
            cut = {ExitStatus.INTERRUPTED: "interrupted", ExitStatus.ABORTED: "aborted"}.get(
                self.exit_status, "failed") if self.exit_status is not None else "failed"
            for r in self.experiments.values():
                if r.status in ACTIVE:
                    r.status = cut
                    r.finished = self.rig_clock()
            return None
        if e.kind == Kind.PREDICTION:
            self._repredicted(float(d["rig_time_left_s"]))
            return None
        found = self.experiments.get(e.experiment or "")
        if found is None:
            return None
        r = found
        if e.kind == Kind.PHASE:
            phase = str(d["phase"])
            if phase in ACTIVE:
                if r.started is None:
                    r.started = self.rig_clock()
                r.status = phase
                if phase == Phase.SETTLING:
                    r.running_since = self.wall_clock()
                if phase == Phase.CAPTURING:
                    # the acquisition's count at its decision: the log's, the record's
                    r.settled_at = r.cycles = int(d.get("cycles", r.cycles))
                    r.fraction = 0.0
        elif e.kind == Kind.PROGRESS and d.get("phase") == Phase.SETTLING:
            if r.started is None:
                r.started = self.rig_clock()
            r.status = "settling"
            if r.samples is None:   # once the stream is read (observe), the count comes from it alone
                r.cycles = int(d["cycles"])
            bound = {"bias_sigma": float(d["bias_sigma"])} if "bias_sigma" in d else {}
            r.settling.append((int(d["cycles"]), dict(d["change"]) | bound))
            r.has_reported_left = "cycles_left" in d
            r.reported_left = d.get("cycles_left")
        elif e.kind == Kind.PROGRESS and d.get("phase") == Phase.CAPTURING:
            r.status = "capturing"
            if r.samples is None:
                r.fraction = float(d["fraction"])
        elif e.kind == Kind.EXPERIMENT_DONE:
            r.status, r.finished = "done", self.rig_clock()
            if d.get("flags"):
                r.note = "flagged"
        elif e.kind == Kind.EXPERIMENT_FAILED:
            r.status, r.finished, r.note = "skipped", self.rig_clock(), "after an alarm"
        elif e.kind == Kind.ALARM:
            r.note = "alarm"
        else:
            return None
        return r

    def _repredicted(self, rig_left_s: float) -> None:
        """The rest of the plan predicted again (qc run, from the unit's own parameters):
        the estimates of what is not done scaled to it; it replaces the correction by
        the experiments done, which it has taken in."""
        rest = [r for r in self.experiments.values() if r.status not in ("done", "skipped")]
        total = sum(r.estimate_s for r in rest)
        if total > 0:
            for r in rest:
                r.estimate_s *= rig_left_s / total
        self.predicted = True

    def observe(self, samples: int, read_at: float) -> ExperimentProgress | None:
        """The DAQ stream's newest sample (it restarts at RUN), read with the controller's
        status at ``read_at`` (wall clock): the settling count and the capture's progress
        of the running experiment follow from it as the acquisition counts them."""
        with self._lock:
            r = self.current
            if (r is None or r.spec is None or self.config is None or r.status not in ("settling", "capturing")
                    or r.running_since is None or read_at < r.running_since or samples < 0):
                return r
            r.samples = samples
            spp = self.config.daq_rate_hz / r.spec.frequency_hz
            counted = samples - r.lead_samples
            if r.status == "settling":
                r.cycles = max(int(counted // spp), 0)
            elif r.settled_at is not None:
                captured = counted - round(r.settled_at * spp)
                r.fraction = min(max(captured / math.ceil(r.spec.periods * spp), 0.0), 1.0)
            return r

    # ----- read ---------------------------------------------------------------------------------------
    @property
    def current(self) -> ExperimentProgress | None:
        return next((r for r in self.experiments.values() if r.status in ACTIVE), None)

    @property
    def order(self) -> list[str]:
        return list(self.experiments)

    def pace(self) -> float:
        return self._pace()

    @property
    def time_known(self) -> bool:
        """False while a link is lost (the count and the clock stand still) or once ended."""
        return not self.gone

    def cycles_left(self, r: ExperimentProgress) -> int | None:
        """Settling cycles still to go from the count shown: the acquisition's own figure
        where it reports one (the drift criterion), else from the last reports' decay."""
        with self._lock:
            if not r.settling:
                return None
            if r.has_reported_left:
                left = r.reported_left
            elif self.config is None:
                return None
            else:
                ss = self.config.steady_state
                left = predicted_cycles_left(r.settling, deciding(self.config), ss.min_cycles, ss.max_cycles)
            if left is None:
                return None
            return max(left - max(r.cycles - r.settling[-1][0], 0), 0)

    def _scale(self) -> float:
        """How much longer than predicted the rest is taken to be, from the experiments
        done: they took ``ratio`` times their estimate, trusted as far as they are the
        session (their share of the estimate): one experiment's settling is tens of per
        cent off either way, the whole plan's much less."""
        if self.predicted:
            return 1.0
        done_s = sum(r.estimate_s for r in self.experiments.values() if r.status in ("done", "skipped")
                     and r.note != "earlier")
        if not done_s:
            return 1.0
        ratio = (self.rig_clock() - self.rig_started) * self.pace() / done_s
        return 1 + (ratio - 1) * done_s / self.announced_s

    def _running_left(self, r: ExperimentProgress, scale: float) -> float:
        """Rig time left of the experiment running now: the settling prediction (or the
        capture's fraction), the capture, the fade out; else its estimate less the rig
        time it has taken (at most RUNNING_SHARE of it counted done until written)."""
        if r.spec is not None and self.config is not None:
            ss, f, periods = self.config.steady_state, r.spec.frequency_hz, r.spec.periods
            if r.status == "capturing":
                return (1 - r.fraction) * periods / f + ss.ramp_time_s
            if r.status == "settling" and r.settling:
                left = self.cycles_left(r)
                if left is not None:
                    return (left + periods) / f + ss.ramp_time_s
        estimate = r.estimate_s * scale
        taken = (self.rig_clock() - r.started) * self.pace() if r.started is not None else 0.0
        return max(estimate - taken, (1 - RUNNING_SHARE) * estimate)

    def experiment_rig_left_s(self, r: ExperimentProgress) -> float:
        """Rig seconds left of one experiment (0 when done, nan when it ended otherwise)."""
        with self._lock:
            return self._experiment_left(r, self._scale())

    def _experiment_left(self, r: ExperimentProgress, scale: float) -> float:
        if r.status == PENDING:
            return r.estimate_s * scale
        if r.status in ACTIVE:
            return self._running_left(r, scale)
        return 0.0 if r.status == "done" else math.nan

    def rig_left_s(self) -> float | None:
        """Rig seconds left of the session; None while a link is lost (nothing measures
        the rig's time then), 0 once it ended."""
        with self._lock:
            if self.ended is not None:
                return 0.0
            if not self.time_known:
                return None
            scale = self._scale()
            left = (self._experiment_left(r, scale) for r in self.experiments.values()
                    if r.status == PENDING or r.status in ACTIVE)
            return sum(x for x in left if not math.isnan(x))

    def wall_left_s(self) -> float | None:
        """:meth:`rig_left_s` in seconds of this computer's clock, at the measured pace."""
        left = self.rig_left_s()
        return None if left is None else left / self.pace()

    def fraction_done(self) -> float:
        """The share of the session's rig time done (written, plus the running one's part)."""
        with self._lock:
            if self.exit_status is ExitStatus.COMPLETE:
                return 1.0
            scale = self._scale()
            done = sum(r.estimate_s for r in self.experiments.values() if r.status == "done" and r.note != "earlier")
            for r in self.experiments.values():
                if r.status in ACTIVE:
                    done += max(r.estimate_s * scale - self._running_left(r, scale), 0.0)
            left = self.rig_left_s() if self.time_known else None
            if left is None:   # the rest as planned, the running part as it stood
                left = sum(r.estimate_s for r in self.experiments.values() if r.status == PENDING)
            return min(done / (done + left), 1.0) if done + left > 0 else 0.0

    def rig_done_s(self) -> float:
        """Rig seconds of the plan's estimate done (for a bar over the rig time)."""
        with self._lock:
            return sum(r.estimate_s for r in self.experiments.values() if r.status in ("done", "skipped")
                       and r.note != "earlier")


def session_progress(plan_experiments: Sequence[ExperimentSpec], label: Callable[[str], str],
                     estimates_s: Mapping[str, float], config: RigConfig, pace: Callable[[], float] | float,
                     rig_clock: Callable[[], float], earlier: Iterable[str] = ()) -> SessionProgress:
    """The progress of a session of these experiments (the plan's, in the order run),
    each labelled by ``label(letter)``, with the rig time predicted for those to do."""
    specs = {label(e.letter): e for e in plan_experiments}
    return SessionProgress(estimates_s, pace, rig_clock, specs=specs, config=config, earlier=earlier)
