"""The one prediction of a plan's rig time: ``rig design``, ``rig run``'s announcement,
``rig qc run`` (its first announcement and its re-prediction after each experiment)
and the console's sessions (the same lifecycle) call :func:`predict`.

Rig time depends on the links as well as on the damper: at 10x a host's millisecond is
ten of the rig's, the acquisition's polls and commands add seconds per experiment, and
conditioning holds too short for the link to end on time are not planned (which makes
settling longer).  So the prediction takes the links' :class:`LinkTiming`: measured by
the pace probe of the session that runs (:meth:`rig.session.acquisition.Acquisition.measure_pace`),
or, before any session (``rig design``), the last one measured on this computer
(:func:`last_measured`, kept by every session's probe in :func:`timing_file`), or
none (a rig's own pace, no line latency), and every prediction says which.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from identify.files import atomic_write_bytes
from identify.parameters import Parameters
from rig.config import RigConfig
from rig.planning.plans import ExperimentDuration, Plan, estimate_experiment_durations
from rig.planning.settling import DRIFT_DRAWS, PAUSE_S

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LinkTiming:
    """The links' pace (rig seconds per second of the host's clock) and latencies
    (seconds of that clock: ``answer_s`` from a hold's end to RUN, ``overhead_s`` an
    experiment's polls and commands), and where they come from, in words."""

    pace: float = 1.0
    answer_s: float = 0.0
    overhead_s: float = 0.0
    basis: str = "none measured on this computer yet: a simulator faster than the rig takes longer"
    measured: str | None = None           # ISO time of the measurement, None when assumed
    links: str | None = None              # the controller's and the DAQ's addresses it was measured on

    @property
    def is_measured(self) -> bool:
        return self.measured is not None

    def describe(self) -> str:
        """One clause: the pace and latencies and their source."""
        if not self.is_measured:
            return f"at a rig's own pace and no line latency ({self.basis})"
        return (f"at {self.pace:.3g} rig seconds per second, {self.overhead_s * 1e3:.0f} ms of polls and commands per "
                f"experiment, {self.answer_s * 1e3:.0f} ms from a hold's end to RUN ({self.basis})")


NOT_MEASURED = LinkTiming()


def measured(pace: float, answer_s: float, overhead_s: float, links: str, basis: str) -> LinkTiming:
    """A timing measured now on ``links``."""
    now = _dt.datetime.now().astimezone().isoformat(timespec="seconds")
    return LinkTiming(pace, answer_s, overhead_s, basis, now, links)


def predict(plan: Plan, config: RigConfig, timing: LinkTiming = NOT_MEASURED, start_position_m: float = 0.0,
            params: Parameters | None = None, *, noise_draws: int = DRIFT_DRAWS,
            pause_s: float | Sequence[float] = PAUSE_S) -> list[ExperimentDuration]:
    """Rig time per experiment of ``plan`` in the order given (order it first: :meth:`Plan.ordered`),
    run from rest at ``start_position_m`` on links of this ``timing``, the damper at
    ``params`` (default: the model's nominal values)."""
    return estimate_experiment_durations(plan, config, start_position_m, params, pause_s=pause_s, pace=timing.pace,
                                         answer_s=timing.answer_s, overhead_s=timing.overhead_s,
                                         noise_draws=noise_draws)


def predict_s(plan: Plan, config: RigConfig, timing: LinkTiming = NOT_MEASURED, start_position_m: float = 0.0,
              params: Parameters | None = None, *, noise_draws: int = DRIFT_DRAWS) -> float:
    """The whole plan's rig time [s] (see :func:`predict`)."""
    return sum(d.total_s for d in predict(plan, config, timing, start_position_m, params, noise_draws=noise_draws))


# ----- the last timing measured on this computer ---------------------------------------------------
def timing_file() -> Path:
    """Where the last measured timing is kept: ``$XDG_STATE_HOME/damper-rig/link-timing.json``
    (``~/.local/state`` by default)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "damper-rig" / "link-timing.json"


def remember(timing: LinkTiming) -> None:
    """Keep a measured timing for the next prediction made before a session.  Not being
    able to write it costs that prediction its basis only (it says so), never a session."""
    if not timing.is_measured:
        return
    path = timing_file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, (json.dumps(asdict(timing), indent=1) + "\n").encode())
    except OSError as exc:
        log.warning("the link timing measured now is not kept in %s (%s): the next prediction before a session "
                    "says its timing is not measured", path, exc.strerror or exc)


def last_measured() -> LinkTiming:
    """The last timing a session measured on this computer, or :data:`NOT_MEASURED`."""
    path = timing_file()
    try:
        doc = json.loads(path.read_text())
        timing = LinkTiming(**doc)
    except FileNotFoundError:     # nothing measured on this computer yet
        return NOT_MEASURED
    except (OSError, ValueError, TypeError) as exc:
        log.warning("the last link timing, %s, cannot be used (%s): predicted as not measured", path, exc)
        return NOT_MEASURED
    if not timing.is_measured:
        return NOT_MEASURED
    return replace(timing, basis=f"the pace probe of {timing.measured} on {timing.links}, the last measured on this "
                                 f"computer")
