"""Predicted against real rig time, phase by phase, read from a session's ``session.log``
(``python -m rig log-times SESSION``): where a session's announced time went wrong.

The prediction is on record as one ``prediction`` event per experiment; the real time
from the ``phase`` events' ``clock_s`` (the acquisition's clock) times the links' pace
(the ``pace-probe`` event: 1 on a rig, a simulator's speed on one), and a conditioning
hold's from its ``hold-end`` event (counted in the DAQ's samples, the rig's own time).
No sentence is parsed: every number is a field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rig.errors import BadInput
from rig.events import Event, Kind, Phase
from rig.session.storage import read_log

# Each phase an experiment passes through, the one that ends it, and its predicted rig
# time from the prediction's fields.
PHASES: tuple[tuple[Phase, Phase, tuple[str, ...]], ...] = (
    (Phase.MOVING, Phase.SETTLING, ("move_s", "hold_s")),
    (Phase.SETTLING, Phase.CAPTURING, ("lead_in_s", "settle_s")),
    (Phase.CAPTURING, Phase.STOPPING, ("capture_s",)),
    (Phase.STOPPING, Phase.IDLE, ("fade_s",)),
)


@dataclass(frozen=True)
class PhaseTime:
    experiment: str
    phase: str                  # moving (with any hold), hold, settling, capturing, stopping, total
    predicted_s: float
    taken_s: float              # rig seconds

    @property
    def error(self) -> float:
        """Taken against predicted, as a fraction of the prediction (NaN for a zero prediction)."""
        return self.taken_s / self.predicted_s - 1 if self.predicted_s else float("nan")


class LogTimesError(BadInput):
    """A session folder whose log holds no prediction or phase timing to compare."""


def log_times(session_dir: str | Path) -> list[PhaseTime]:
    """Per experiment, in the order they ran: each phase it completed, predicted and taken
    (rig seconds), then its hold (if it had one) and its total."""
    path = Path(session_dir) / "session.log"
    if not path.is_file():
        raise LogTimesError(f"{path}: no session log here")
    events = read_log(path)
    return phase_times(events, path)


def phase_times(events: list[Event], source: str | Path = "session.log") -> list[PhaseTime]:
    """:func:`log_times` on events already read."""
    predicted = {e.experiment: e.data for e in events if e.kind == Kind.PHASE_PLAN and e.experiment}
    if not predicted:
        raise LogTimesError(f"{source}: no prediction events (a session from before they were logged)")
    pace = next((e.data["pace"] for e in reversed(events) if e.kind == Kind.PACE_PROBE), 1.0)
    entered: dict[str, dict[Phase, float]] = {}
    held: dict[str, float] = {}
    for e in events:
        if e.kind == Kind.PHASE and e.experiment and "clock_s" in e.data:
            entered.setdefault(e.experiment, {}).setdefault(Phase(e.data["phase"]), e.data["clock_s"])
        elif e.kind == Kind.HOLD_END and e.experiment:
            held[e.experiment] = e.data["held_s"]
    rows = []
    for label, times in entered.items():
        if label not in predicted:
            continue
        p = predicted[label]
        for phase, until, parts in PHASES:
            if phase in times and until in times:
                rows.append(PhaseTime(label, phase.value, sum(p[k] for k in parts),
                                      (times[until] - times[phase]) * pace))
        if label in held:
            rows.append(PhaseTime(label, "hold", p["hold_s"], held[label]))
        if Phase.MOVING in times and Phase.IDLE in times:
            rows.append(PhaseTime(label, "total", sum(p[k] for _, _, parts in PHASES for k in parts) + p["links_s"],
                                  (times[Phase.IDLE] - times[Phase.MOVING]) * pace))
    return rows


def format_times(rows: list[PhaseTime]) -> str:
    """The comparison as a table (rig seconds; the error relative to the prediction)."""
    lines = [f"{'experiment':<11} {'phase':<10} {'predicted s':>12} {'taken s':>10} {'error':>8}"]
    for r in rows:
        error = f"{r.error:+.0%}" if r.predicted_s else "—"
        lines.append(f"{r.experiment:<11} {r.phase:<10} {r.predicted_s:>12.1f} {r.taken_s:>10.1f} {error:>8}")
    return "\n".join(lines)
