"""Terminal progress of a session: a queued subscriber of the session's events.

One line per phase, settling and capture progress, and the session's ETA: the rig
time announced at the start comes from the plan's per-experiment estimates; while the
session runs, the time left is corrected by how long the finished experiments took
against their estimates, as far as they are the session, and given in wall clock at
the links' pace (a simulator's speed, corrected from the session's own streams).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rich.console import Console

from rig.events import Event


class ConsoleProgress:
    """Queued subscriber: one line per phase, settling and capture progress, and the
    session's ETA (wall clock, from the rig-time estimate corrected by what is done)."""

    def __init__(self, console: Console, estimates_s: dict[str, float], pace: float | Callable[[], float] = 1.0,
                 rig_clock: Callable[[], float] = time.monotonic) -> None:
        # pace: the links' rig seconds per second, or where to read it as the session
        # corrects it from its streams (Acquisition.current_pace); rig_clock: the
        # acquisition's (a test's in-process simulator runs on its own)
        self.console, self.estimates, self.rig_clock = console, estimates_s, rig_clock
        self._pace = pace if callable(pace) else lambda: pace
        self.rig_started = rig_clock()
        self.total, self.done, self.done_s = len(estimates_s), 0, 0.0
        self._captured = 0.0
        plural = "s" if self.total != 1 else ""
        console.print(f"session: {self.total} experiment{plural}, about {_min_s(sum(estimates_s.values()))} min:s of "
                      "rig time", highlight=False)

    def _eta(self) -> str:
        """The rig time left, corrected from the progress made, at the links' pace.

        The experiments done took ``ratio`` times their estimate; the rest is scaled by
        that ratio only as far as the done ones are the session (their share of the
        estimate): one experiment's settling is tens of per cent off either way (a busy
        host's late hold end), the whole plan's much less, and a first short experiment
        that ran fast said -40 % where the announcement had been right."""
        if not self.done_s:
            return ""
        total, pace = sum(self.estimates.values()), self._pace()
        ratio = (self.rig_clock() - self.rig_started) * pace / self.done_s
        left = (total - self.done_s) * (1 + (ratio - 1) * self.done_s / total) / pace
        return f", session ETA {_min_s(left)} (min:s, wall clock)"

    def __call__(self, e: Event) -> None:
        if e.kind in ("experiment-done", "experiment-failed"):
            self.done += 1
            self.done_s += self.estimates.get(e.experiment or "", 0.0)
        number = self.done if e.kind == "experiment-done" else min(self.done + 1, self.total)
        head = f"[{number:2d}/{self.total}] {e.experiment or '':<8}"
        if e.kind == "phase":
            extra = ("".join(f" {k}={v}" for k, v in e.data.items() if k != "phase")
                     if e.data["phase"] != "capturing" else f" after {e.data.get('cycles')} settling cycles")
            self._captured = 0.0
            self.console.print(f"{head} {e.data['phase']}{extra}", highlight=False)
        elif e.kind == "progress" and e.data.get("phase") == "settling":
            ch = e.data["change"]
            self.console.print(f"{head}   cycle {e.data['cycles']:4d}: change stroke {ch['stroke_mm']:.3f} mm, "
                               f"force {ch['force_N']:.1f} N, pressure {ch['pressure_bar']:.4f} bar, "
                               f"temperature {ch['gas_temperature_C']:.3f} °C"
                               + (f"; decay {e.data['ratio']:.3f}/cycle, bias ≤ {e.data['bias_sigma']:.2f} σ"
                                  if "bias_sigma" in e.data else ""), highlight=False, style="dim")
        elif e.kind == "progress" and e.data.get("phase") == "capturing":
            if e.data["fraction"] >= self._captured + 0.25:
                self._captured = e.data["fraction"]
                self.console.print(f"{head}   captured {100 * self._captured:.0f} %", highlight=False, style="dim")
        elif e.kind == "experiment-done":
            flags = f" FLAGGED: {'; '.join(e.data['flags'])}" if e.data["flags"] else ""
            self.console.print(f"{head} [green]captured[/green] {e.data['file']} ({e.data['samples']} samples, "
                               f"{e.data['lost']} lost in window){flags}{self._eta()}", highlight=False)
        elif e.kind == "session-end":
            took, announced, pace = self.rig_clock() - self.rig_started, sum(self.estimates.values()), self._pace()
            if pace > 1.0:   # links faster than the rig's time: its minutes, from the measured pace
                self.console.print(f"session took {_min_s(took)} min:s of wall clock at {pace:.3g} rig seconds "
                                   f"per second, about {_min_s(took * pace)} min:s of rig time; announced "
                                   f"{_min_s(announced)}", highlight=False)
            else:
                self.console.print(f"session took {_min_s(took)} min:s of rig time; announced {_min_s(announced)}",
                                   highlight=False)
        elif e.kind in ("log", "alarm", "experiment-failed"):
            style = "red" if e.kind != "log" else "dim"
            self.console.print(f"{head} {e.data.get('message', '')}", style=style, highlight=False)


class ProgressBar:
    """Queued subscriber for notebooks: one bar over the session's rig time (a widget in
    Jupyter, text elsewhere), advancing as experiments end and naming the running one."""

    def __init__(self, estimates_s: dict[str, float]) -> None:
        from tqdm.auto import tqdm  # only notebooks and scripts that ask for the bar load it

        self.estimates = estimates_s
        self.bar = tqdm(total=round(sum(estimates_s.values())), unit="s", desc="session",
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s of rig time")

    def __call__(self, e: Event) -> None:
        if e.kind == "phase" and e.experiment:
            extra = f" {e.data['cycles']} cycles" if "cycles" in e.data else ""
            self.bar.set_description(f"{e.experiment} {e.data['phase']}{extra}")
        elif e.kind in ("experiment-done", "experiment-failed"):
            self.bar.update(round(self.estimates.get(e.experiment or "", 0.0)))
        elif e.kind == "session-end":
            self.bar.set_description(str(e.data.get("message", "ended")))
            if e.data.get("message") == "complete":
                self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()


def _min_s(seconds: float) -> str:
    """Minutes and seconds: whole minutes hid the ETA's error on a short session (a
    1.4 min experiment announced as 1 min 'took 2 min')."""
    return f"{int(seconds // 60)}:{int(seconds % 60):02d}"
