"""A session's experiments as the plan table shows them, kept from the bus's events
(no Qt here): pending, moving, settling n, capturing %, done, failed/skipped, and the
time left per experiment and for the session.

Times left come from :func:`rig.planning.plans.estimate_duration_s` (rig time), turned into
wall time by the simulator's speed at first and, once experiments are done, by how
long they actually took against their estimates (as the terminal's progress does).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from identify.exit_codes import EXIT_INTERRUPTED
from identify.plans import ExperimentSpec
from rig.config import RigConfig
from rig.events import Event
from rig.gui.analysis import predicted_cycles_left
from rig.planning.criterion import first_block_sample
from rig.planning.plans import Plan, estimate_duration_s

ACTIVE = ("moving", "settling", "capturing", "stopping")


def deciding(config: RigConfig) -> dict[str, float]:
    """What decides the capture, as the settling reports carry it: the drift criterion's
    bias bound, or each channel's change threshold (the settling view's cycles left and
    the table's time left come from the same)."""
    ss = config.steady_state
    if ss.criterion == "drift" and ss.drift is not None:
        return {"bias_sigma": ss.drift.fraction}
    return dict(ss.thresholds)


@dataclass
class ExperimentRow:
    spec: ExperimentSpec
    label: str
    estimate_s: float                      # rig time
    status: str = "pending"                # pending, moving, settling, capturing, stopping, done, failed, skipped
    cycles: int = 0
    fraction: float = 0.0
    note: str = ""
    started: float | None = None           # wall clock (monotonic)
    finished: float | None = None
    settling: list[tuple[int, dict[str, float]]] = field(default_factory=list)  # cycles, change (+ bias_sigma)
    samples: int | None = None             # the DAQ stream's newest sample as last read (settling, capturing)
    lead_samples: int = 0                  # samples after RUN before settling is counted (fade-in and lag)
    settled_at: int | None = None          # settling cycles when the capture began
    running_since: float | None = None     # when settling began (clock): older reads are of the last RUN

    def observe(self, samples: int, read_at: float, rate_hz: float) -> None:
        """The DAQ stream's newest sample (it restarts at RUN), read with the controller's
        status at ``read_at``: the settling count and the capture's progress follow from
        it as the acquisition counts them, so every number shown moves together."""
        if (self.status not in ("settling", "capturing") or self.running_since is None
                or read_at < self.running_since or samples < 0):
            return
        self.samples = samples
        spp = rate_hz / self.spec.frequency_hz
        counted = samples - self.lead_samples
        if self.status == "settling":
            self.cycles = max(int(counted // spp), 0)
        elif self.settled_at is not None:
            captured = counted - round(self.settled_at * spp)
            self.fraction = min(max(captured / math.ceil(self.spec.periods * spp), 0.0), 1.0)

    def cycles_left(self, thresholds: dict[str, float], min_cycles: int, max_cycles: int) -> int | None:
        """Settling cycles still to go from the count shown, by the last reports' decay."""
        left = predicted_cycles_left(self.settling, thresholds, min_cycles, max_cycles)
        if left is None or not self.settling:
            return left
        return max(left - max(self.cycles - self.settling[-1][0], 0), 0)

    def status_text(self) -> str:
        if self.status == "settling":
            return f"settling {self.cycles}" if self.cycles else "settling"
        if self.status == "capturing":
            return f"capturing {100 * self.fraction:.0f} %"
        return self.status + (f" ({self.note})" if self.note else "")


class PlanProgress:
    def __init__(self, plan: Plan, config: RigConfig, date: str, speed: float = 1.0,
                 done: frozenset[str] | set[str] = frozenset(), clock: Callable[[], float] = time.monotonic) -> None:
        self.clock, self.speed, self.config = clock, speed, config
        self.rows = [ExperimentRow(e, f"{date}{e.letter}",
                                   estimate_duration_s(replace(plan, experiments=(e,)), config,
                                                       e.static_position_mm * 1e-3),
                                   lead_samples=first_block_sample(config.steady_state, config.daq_rate_hz))
                     for e in plan.experiments]
        for row in self.rows:
            if row.spec.letter in done:
                row.status, row.note = "done", "earlier"
        self.by_label = {r.label: r for r in self.rows}
        self.ended: str | None = None
        self.unread: str | None = None     # why the controller's last status read failed (None: it answered)

    @property
    def current(self) -> ExperimentRow | None:
        return next((r for r in self.rows if r.status in ACTIVE), None)

    def observe(self, samples: int, read_at: float) -> ExperimentRow | None:
        """The DAQ's newest sample for the experiment running now (see ExperimentRow.observe)."""
        row = self.current
        if row is not None:
            row.observe(samples, read_at, self.config.daq_rate_hz)
        return row

    def apply(self, e: Event) -> ExperimentRow | None:
        """Take one event; returns the row it changed."""
        if e.kind == "session-end":
            self.ended = str(e.data.get("message", ""))
            for r in self.rows:
                if r.status in ACTIVE:
                    r.status = "interrupted" if e.data["exit_code"] == EXIT_INTERRUPTED else "failed"
                    r.finished = self.clock()
            return None
        row = self.by_label.get(e.experiment or "")
        if row is None:
            return None
        if e.kind == "phase":
            phase = str(e.data["phase"])
            if phase in ACTIVE:
                if row.started is None:
                    row.started = self.clock()
                row.status = phase
                if phase == "settling":
                    row.running_since = self.clock()
                if phase == "capturing":
                    # the acquisition's count at its decision: the log's, the record's
                    row.settled_at = row.cycles = int(e.data.get("cycles", row.cycles))
                    row.fraction = 0.0
        elif e.kind == "progress" and e.data.get("phase") == "settling":
            # Once the stream is read (observe) the count shown comes from it alone; the
            # report's own count dates its changes, for the prediction of the cycles left.
            row.status = "settling"
            if row.samples is None:
                row.cycles = int(e.data["cycles"])
            # the drift criterion's bound beside the changes: what decides the capture there
            bound = {"bias_sigma": float(e.data["bias_sigma"])} if "bias_sigma" in e.data else {}
            row.settling.append((int(e.data["cycles"]), dict(e.data["change"]) | bound))
        elif e.kind == "progress" and e.data.get("phase") == "capturing":
            row.status = "capturing"
            if row.samples is None:
                row.fraction = float(e.data["fraction"])
        elif e.kind == "experiment-done":
            row.status, row.finished = "done", self.clock()
            if e.data.get("flags"):
                row.note = "flagged"
        elif e.kind == "experiment-failed":
            row.status, row.finished, row.note = "skipped", self.clock(), "after an alarm"
        elif e.kind == "alarm":
            row.note = "alarm"
        return row

    def wall_per_rig_s(self) -> float:
        """Wall seconds per estimated rig second, from the experiments done in this run."""
        timed = [(r.finished - r.started, r.estimate_s) for r in self.rows
                 if r.status == "done" and r.started is not None and r.finished is not None]
        estimate = sum(e for _, e in timed)
        if estimate > 0:
            return sum(took for took, _ in timed) / estimate
        return 1.0 / self.speed

    def left_s(self, row: ExperimentRow) -> float:
        """Wall seconds left for one experiment (0 when done, nan when it ended otherwise)."""
        scale = self.wall_per_rig_s()
        if row.status == "pending":
            return row.estimate_s * scale
        if row.status in ACTIVE and row.started is not None:
            rest = self._rig_s_left(row)
            if rest is not None:
                return rest * scale
            return max(row.estimate_s * scale - (self.clock() - row.started), 0.0)
        return 0.0 if row.status == "done" else math.nan

    def rig_left_s(self, row: ExperimentRow) -> float:
        """Rig seconds left for one experiment (the plan table's column: one clock throughout)."""
        return self.left_s(row) / self.wall_per_rig_s()

    def _rig_s_left(self, row: ExperimentRow) -> float | None:
        """Rig time left from where the experiment is: the settling prediction (or the
        capture's fraction), the capture, the fade out; None when not known."""
        ss, f, periods = self.config.steady_state, row.spec.frequency_hz, row.spec.periods
        if row.status == "capturing":
            return (1 - row.fraction) * periods / f + ss.ramp_time_s
        if row.status == "settling" and row.settling:
            left = row.cycles_left(deciding(self.config), ss.min_cycles, ss.max_cycles)
            return None if left is None else (left + periods) / f + ss.ramp_time_s
        return None

    def session_left_s(self) -> float:
        if self.ended is not None:
            return 0.0
        left = [self.left_s(r) for r in self.rows if r.status == "pending" or r.status in ACTIVE]
        return sum(x for x in left if not math.isnan(x))
