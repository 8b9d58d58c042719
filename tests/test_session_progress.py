"""One session's progress (rig.session.session_progress.SessionProgress) is computed once:
the terminal, the console's plan tab and its QC tab render the same object, so that they
cannot show three different times left."""

from __future__ import annotations

import io
import math

from rich.console import Console

from rig.events import Event, Kind, Message
from rig.gui.plan_state import PlanProgress
from rig.gui.qc import QcProgress, QcTracker
from rig.session.lifecycle import SessionContext
from rig.session.progress import ConsoleProgress
from rig.session.session_progress import SessionProgress


class Spy:
    """Every rig time left the session's progress gave, and to whom."""

    def __init__(self, progress: SessionProgress) -> None:
        self.given: list[float | None] = []
        computed = progress.rig_left_s

        def rig_left_s() -> float | None:
            left = computed()
            self.given.append(left)
            return left

        progress.rig_left_s = rig_left_s     # type: ignore[method-assign]  # the instance's, read by every view


def test_the_terminal_the_plan_tab_and_the_qc_tab_render_one_progress(vrig, tmp_path):
    views: dict[str, object] = {}
    posted: list[Message] = []
    terminal = io.StringIO()
    spies: list[Spy] = []
    plan_tab_left: list[float | None] = []

    def attach(ctx: SessionContext) -> list:
        spies.append(Spy(ctx.progress))
        views["context"] = ctx.progress
        views["terminal"] = ConsoleProgress(Console(file=terminal, width=300), ctx.progress,
                                            pace_reading=ctx.runner.acquisition.pace_reading)
        views["plan tab"] = PlanProgress(ctx.progress)           # what the session worker hands the window
        views["QC tab"] = QcTracker(ctx.progress, posted.append)
        return [views["terminal"], views["QC tab"], plan_tab]

    def plan_tab(e: Event) -> None:       # the window's handler: the table and the ETA line read these
        table = views["plan tab"]
        assert isinstance(table, PlanProgress)
        if table.apply(e) is not None or e.kind == Kind.SESSION_END:
            plan_tab_left.append(table.session_rig_left_s())

    result = vrig.run_session(tmp_path / "s", ["j", "n"], attach=attach)
    vrig.bus.close()                      # every queued view has rendered every event
    assert result.exit_code == 0, result.status

    terminal_view, plan_view, qc_view = views["terminal"], views["plan tab"], views["QC tab"]
    assert isinstance(terminal_view, ConsoleProgress) and isinstance(plan_view, PlanProgress)
    assert isinstance(qc_view, QcTracker)
    assert terminal_view.progress is plan_view.session is qc_view.progress is views["context"]

    (spy,) = spies
    qc_left = [m.rig_left_s for m in posted if isinstance(m, QcProgress)]
    assert len(qc_left) > 3 and plan_tab_left
    # each view's time left is one the session's progress gave: none computed its own
    for left in qc_left + plan_tab_left:
        assert any(left == given or (left is not None and given is not None and math.isclose(left, given))
                   for given in spy.given), (left, spy.given[-5:])
    # the terminal's ETA is that figure at the measured pace, said after the first experiment
    eta = [line for line in terminal.getvalue().splitlines() if "left (m:s of wall clock)" in line]
    assert eta, terminal.getvalue()
    assert qc_left[-1] == 0.0 and plan_tab_left[-1] == 0.0      # the session ended: nothing left anywhere
