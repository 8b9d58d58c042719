"""The plan table's view of a session (no Qt here): its rows are the experiments of the
session's one :class:`~rig.session.session_progress.SessionProgress`, in the plan's
order, and every number it shows (settling count, capture, cycles left, times left) is
that object's: nothing is computed here.  What only the console knows is kept beside
it: whether the controller answers its status reads (``unread``).

Before a session, the preview is a progress of its own, of the plan's rig time as
:func:`rig.planning.prediction.predict` has it on the links last measured on this
computer (:func:`rig.planning.prediction.last_measured`): the one prediction.
"""

from __future__ import annotations

from rig.config import RigConfig
from rig.events import Event, Kind
from rig.planning.plans import Plan
from rig.planning.prediction import last_measured, predict
from rig.session.session_progress import ACTIVE, ExperimentProgress, SessionProgress

__all__ = ["ACTIVE", "ExperimentRow", "PlanProgress"]

ExperimentRow = ExperimentProgress      # one row of the table is one experiment's progress
# the events that change a row (the rest are said in the log pane only)
ROW_EVENTS = (Kind.PHASE, Kind.PROGRESS, Kind.EXPERIMENT_DONE, Kind.EXPERIMENT_FAILED, Kind.ALARM)


class PlanProgress:
    def __init__(self, session: SessionProgress, *, fed: bool = True) -> None:
        # fed: the session's bus feeds ``session`` (a lifecycle's, inline); else the
        # window's events are handed on to it here (a progress of the console's own)
        if session.config is None:
            raise ValueError("the plan table shows a session of a known rig configuration")
        self.session, self._fed = session, fed
        self.config: RigConfig = session.config
        self.rows = [r for r in session.experiments.values() if r.spec is not None]
        self.by_label = {r.label: r for r in self.rows}
        self.unread: str | None = None     # why the controller's last status read failed (None: it answered)
        self.basis = "the session's own prediction"   # what its times come from, in words

    @classmethod
    def preview(cls, plan: Plan, config: RigConfig) -> PlanProgress:
        """The plan's experiments, all pending, their rig time from the one prediction (seconds of CPU)."""
        timing = last_measured()
        durations = predict(plan, config, timing)
        specs = {e.letter: e for e in plan.experiments}
        estimates = {d.letter: d.total_s for d in durations}
        progress = cls(SessionProgress(estimates, timing.pace, specs=specs, config=config), fed=False)
        progress.basis = (f"the links as measured {timing.measured[:16].replace('T', ' ')}" if timing.is_measured
                          and timing.measured else "at a rig's own pace: the session measures its links")
        return progress

    @property
    def ended(self) -> str | None:
        return self.session.ended

    @property
    def current(self) -> ExperimentRow | None:
        return self.session.current

    def observe(self, samples: int, read_at: float) -> ExperimentRow | None:
        """The DAQ's newest sample for the experiment running now (SessionProgress.observe)."""
        return self.session.observe(samples, read_at)

    def apply(self, e: Event) -> ExperimentRow | None:
        """An event the window was given; returns the row it changed (the session's progress
        heard it first, on the bus)."""
        if not self._fed:
            self.session.apply(e)
        return self.by_label.get(e.experiment or "") if e.kind in ROW_EVENTS else None

    def cycles_left(self, row: ExperimentRow) -> int | None:
        return self.session.cycles_left(row)

    def rig_left_s(self, row: ExperimentRow) -> float:
        """Rig seconds left for one experiment (the plan table's column)."""
        return self.session.experiment_rig_left_s(row)

    def session_rig_left_s(self) -> float | None:
        return self.session.rig_left_s()

    def session_left_s(self) -> float | None:
        """Wall seconds left for the session, at the pace the session measured."""
        return self.session.wall_left_s()

    @property
    def estimate_s(self) -> float:
        return self.session.announced_s
