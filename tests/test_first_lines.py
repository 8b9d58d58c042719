"""``rig run`` speaks at once, and while the plan is ordered (issue 34): the standard
plan's thermal ordering took 14.6 s of silence (24.1 s on a resume)."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console

import rig.session.lifecycle as lifecycle
import rig.session.terminal as terminal
from rig.drivers.shaker import ShakerLinkError
from rig.events import Event, EventBus, Kind
from rig.session.lifecycle import _ordered
from rig.session.run import RunOptions, execute, prepare

ADDRESSES = {"shaker": "tcp://127.0.0.1:1", "daq": "socket://127.0.0.1:1"}


def options(tmp_path: Path, **kw: object) -> RunOptions:
    return RunOptions(plan="standard", out=tmp_path / "s", **ADDRESSES, **kw)  # type: ignore[arg-type]


def test_the_first_line_comes_before_the_links_are_tried(tmp_path, monkeypatch):
    def dead(*args: object, **kwargs: object) -> None:
        raise ShakerLinkError("nothing answers at tcp://127.0.0.1:1 (injected)")

    monkeypatch.setattr(lifecycle, "connect", dead)
    out = io.StringIO()
    with pytest.raises(ShakerLinkError):
        execute(prepare(options(tmp_path)), Console(file=out, width=300))
    assert out.getvalue().splitlines()[0] == (
        "plan standard: 14 experiments in the order of least predicted rig time; connecting to the controller at "
        "tcp://127.0.0.1:1 and the DAQ at socket://127.0.0.1:1")


def test_ordering_says_it_begins_how_far_it_is_and_what_it_found(tmp_path, monkeypatch):
    monkeypatch.setattr(lifecycle, "ORDERING_PROGRESS_S", 0.0)     # every step said
    prep = prepare(options(tmp_path, experiments=["j", "n", "l"], order="thermal"))
    bus, said, events = EventBus(), [], []

    def keep(e: Event) -> None:
        said.append(e.data["message"])
        events.append(e)

    bus.subscribe(keep, inline=True)
    ordered = _ordered(prep, bus)
    letters = ", ".join(e.letter for e in ordered.plan.experiments)
    assert all(e.data["ordering"] for e in events)
    assert said[0].startswith("ordering the 3 experiments for the least predicted rig time")
    assert [s.split(" (")[0] for s in said[1:-1]] == ["ordering: 1 of 3 experiments' successors predicted",
                                                    "ordering: 2 of 3 experiments' successors predicted"]
    assert said[-1].startswith("ordered in ") and said[-1].endswith(f": {letters}")
    assert ordered.plan.order == "fixed" and sorted(letters.split(", ")) == ["j", "l", "n"]


def test_a_plan_run_as_listed_is_not_ordered_and_says_nothing_of_it(tmp_path):
    prep = prepare(options(tmp_path, experiments=["j", "n"]))
    bus, said = EventBus(), []
    bus.subscribe(said.append, inline=True)
    assert _ordered(prep, bus).plan.experiments == prep.plan.experiments and said == []


def test_early_lines_print_the_sessions_log_lines_until_the_progress_takes_over():
    out = io.StringIO()
    early = terminal._EarlyLines(Console(file=out, width=300))
    early(Event(Kind.LOG, None, {"message": "ordering: 3 of 14 experiments' successors predicted (4 s)",
                                 "ordering": True}, time=1.0))
    early(Event(Kind.LOG, None, {"message": "session aborted: … (before anything moved)"}, time=1.5))   # said last
    early.until = 2.0
    early(Event(Kind.LOG, None, {"message": "too late", "ordering": True}, time=3.0))
    assert out.getvalue().splitlines() == ["[session] Ordering: 3 of 14 experiments' successors predicted (4 s)"]
