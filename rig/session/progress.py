"""Terminal progress of a session: a queued subscriber of the session's events, and
:func:`describe`, an event in a sentence (the terminal, the console's log pane, the
session browser's view of session.log).

One line per phase, settling and capture progress, and the session's ETA, rendered
from the session's one :class:`~rig.session.session_progress.SessionProgress` (which
computes the time left; nothing here does).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from rig.drivers.registers import ControllerState
from rig.events import Event, Kind, Phase
from rig.session.acquisition import PaceReading
from rig.session.outcome import ExitStatus
from rig.session.session_progress import SessionProgress
from rig.session.storage import read_log

# How the settling change of each channel is said: its word, unit and decimals (the
# block means' resolution: a block averages thousands of samples of the transducer's noise).
CHANGE_WORDS = {"stroke_mm": ("stroke", "mm", 3), "force_N": ("force", "N", 1), "pressure_bar": ("pressure", "bar", 4),
                "gas_temperature_C": ("gas temperature", "°C", 3)}
PHASE_SENTENCES = {Phase.SETTLING: "Excitation running, settling."}
# The controller's states read after a stop in which nothing moves (OFF: hydraulics off too).
AT_REST_STATES = (ControllerState.OFF, ControllerState.IDLE)


def describe(e: Event) -> str:
    """An event as a sentence for people (the terminal, the console's log pane, the session
    browser), from its fields, numbers rounded to what they mean."""
    d = e.data
    if e.kind == Kind.SESSION_START:
        return f"Session started: controller at {d['shaker']}, DAQ at {d['daq']} ({d['identity']})."
    if e.kind == Kind.PHASE:
        phase = Phase(d["phase"])
        if phase is Phase.MOVING:
            return f"Moving to the static position {d['target_mm']:.1f} mm."
        if phase is Phase.CAPTURING:
            return f"Now capturing, after {d['cycles']} settling cycles."
        if phase is Phase.STOPPING:
            return f"Stopping: {d['reason']}." if d.get("reason") else "Fading out and stopping."
        if phase is Phase.ALARM:
            return f"ALARM: {d['message']}."
        if phase is Phase.IDLE:
            return at_rest_sentence(d)
        return PHASE_SENTENCES[phase]
    if e.kind == Kind.PROGRESS and d["phase"] == Phase.CAPTURING:
        return f"Captured {100 * d['fraction']:.0f} % of the window."
    if e.kind == Kind.PROGRESS:
        moved = ", ".join(f"{word} {_fixed(d['change'].get(channel), decimals)} {unit}"
                          for channel, (word, unit, decimals) in CHANGE_WORDS.items() if channel in d["change"])
        text = f"Cycle {d['cycles']}: the block means moved by {moved}"
        if "cycles_left" in d:     # the drift criterion, in what the operator waits for
            left = d["cycles_left"]
            text += ("; the transient is not yet seen to decay" if left is None else
                     f"; about {left} more cycle{'s' if left != 1 else ''} to settle" if left else "; settled")
            text += f" (it decays ×{d['ratio']:.3f} per cycle)" if left != 0 and 0 < d["ratio"] < 1 else ""
        elif "bias_sigma" in d:    # a session.log from before cycles_left
            text += f"; the transient decays ×{d['ratio']:.3f} per cycle"
        return text + "."
    if e.kind == Kind.EXPERIMENT_DONE:
        lost = "none lost in the window" if not d["lost"] else f"{d['lost']} lost in the window"
        flags = f"; FLAGGED: {'; '.join(d['flags'])}" if d["flags"] else ""
        return f"Written to {d['file']}: {d['samples']} samples, {lost}{flags}."
    if e.kind == Kind.SESSION_END:
        return f"Session {d['message']}."
    if e.kind in SAID_BY:
        return _sentence(SAID_BY[e.kind](d))
    return _sentence(str(d.get("message", "")))


def at_rest_sentence(d: dict) -> str:
    """What the controller said after a stop: "At rest" only when it was read at rest."""
    if "controller" not in d:   # a session.log written before the state was read
        return "Stopped (the controller's state after the stop is not on record)."
    state = d["controller"]
    if state in AT_REST_STATES:
        hydraulics = ", hydraulics off" if state == ControllerState.OFF else ""
        return f"At rest: the controller reads {state}{hydraulics}."
    if state == ControllerState.ALARM:   # the state as read back from session.log is its name
        return f"Stopped by the controller's alarm ({d.get('alarm', 'unknown')}); it stays latched until reset."
    if state is not None:
        return f"Not at rest: the controller reads {state} after the stop."
    why = f" ({d['unread']})" if d.get("unread") else ""
    return ("Not known to be at rest: the controller could not be read after the stop" + why
            + "; its watchdog stops the shaker once this program no longer feeds it.")


def _pace_probe(d: dict[str, Any]) -> str:
    pace = d["pace"]
    return (f"pace probe: {d['samples']} samples taken, {d['lost']} lost in the stream ({d['probes']} probes of "
            f"{d['probe_s'] * 1e3:.0f} ms, paces {d['pace_min']:.3g}…{d['pace_max']:.3g}); the links run {pace:.3g} "
            f"rig seconds per second (the median); DAQ start {d['daq_start_s'] * 1e3:.1f} ms, stop "
            f"{d['daq_stop_s'] * 1e3:.1f} ms, a status read {d['status_read_s'] * 1e3:.1f} ms: from a hold's end to "
            f"RUN {d['answer_s'] * 1e3:.1f} ms, {d['answer_s'] * pace:.2f} s of the rig's time; an experiment's "
            f"polls and commands {d['overhead_s'] * 1e3:.1f} ms, {d['overhead_s'] * pace:.2f} s")


def _hold(d: dict[str, Any]) -> str:
    # Said as what it is: the gas held compressed (or expanded) is far hotter (colder) than
    # during the experiment, and an operator who sees 15-25 °C on the trace afterwards must
    # not read the hold's target as a unit or sensor fault.
    squeeze, after = ("compressed", "drops") if d["compressed"] else ("expanded", "rises")
    return (f"conditioning: holding at {d['position_mm']:.1f} mm (gas {squeeze} beyond the experiment's "
            f"{d['experiment_mm']:.1f} mm) until the measured gas temperature reaches {d['target_c']:.2f} °C, the "
            f"model's temperature from which the move on lands the gas in its periodic state (about "
            f"{d['predicted_s']:.0f} s); it {after} when the move is made")


def _hold_end(d: dict[str, Any]) -> str:
    gas = "—" if d["gas_c"] is None else f"{d['gas_c']:.2f}"
    return (f"conditioning: the gas was at {gas} °C (wanted {d['target_c']:.2f} °C) when the move on was "
            f"commanded, after {d['held_s']:.1f} s at the hold (predicted {d['predicted_s']:.0f} s), "
            f"{d['lead_s'] * 1e3:.0f} ms ahead of the crossing (the stroke's delay on the move there)")


def _capture_window(d: dict[str, Any]) -> str:
    text = f"capture window {d['window']} lost {d['lost']} samples"
    if d["kept"]:
        return text + f", as the line's steady loss predicts ({d['steady_loss']:.2%}): kept, the holes declared"
    return text + ("; capturing again" if d["again"] else "")


def _phase_plan(d: dict[str, Any]) -> str:
    hold = f", a hold of {d['hold_s']:.0f} s" if d["hold_s"] else ""
    return (f"predicted: {d['total_s']:.0f} s of rig time (settling {d['settle_cycles']} cycles, "
            f"{d['settle_s']:.0f} s{hold}).")


SAID_BY: dict[Kind, Callable[[dict[str, Any]], str]] = {
    Kind.PACE_PROBE: _pace_probe, Kind.HOLD: _hold, Kind.HOLD_END: _hold_end, Kind.CAPTURE_WINDOW: _capture_window,
    Kind.PHASE_PLAN: _phase_plan}


def _fixed(x: float | None, decimals: int) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.{decimals}f}"


def _sentence(text: str) -> str:
    """A driver's or the acquisition's message as a sentence: capital first, a full stop last."""
    text = text.strip()
    if not text:
        return ""
    return text[0].upper() + text[1:] + ("" if text[-1] in ".!?)" else ".")


def log_text(path: Path) -> str:
    """A session.log as people read it: time, experiment, sentence, one event a line."""
    try:
        events = read_log(path)
    except OSError as exc:
        return f"({path.name} unreadable: {exc.strerror or exc})"
    lines = []
    for e in events:
        stamp = time.strftime("%H:%M:%S", time.localtime(e.time)) + f".{int(e.time % 1 * 1000):03d}" if e.time else ""
        lines.append(f"{stamp:12} {e.experiment or '':9} {describe(e)}".rstrip())
    return "\n".join(lines)


class ConsoleProgress:
    """Queued subscriber: the session in sentences, each line under the experiment it
    belongs to (``[ 2/14] 261126e``, the experiment's place in the session: an
    experiment's file is written while the next one moves), and the session's ETA,
    rendered from the session's one :class:`SessionProgress` (its wall time left at the
    measured pace)."""

    def __init__(self, console: Console, estimates_s: dict[str, float] | SessionProgress,
                 pace: float | Callable[[], float] = 1.0, rig_clock: Callable[[], float] = time.monotonic,
                 pace_reading: Callable[[], PaceReading] | None = None) -> None:
        # estimates_s: the session's progress (a lifecycle's, fed by its bus), or the rig
        # time per experiment to keep one here from the events this subscriber is given;
        # pace, rig_clock: the latter's (see SessionProgress); pace_reading: the pace with
        # what measured it (Acquisition.pace_reading), for the last line
        self.console = console
        self._own = not isinstance(estimates_s, SessionProgress)
        self.progress = estimates_s if isinstance(estimates_s, SessionProgress) else \
            SessionProgress(estimates_s, pace, rig_clock)
        progress = self.progress
        self._pace_reading = pace_reading or (lambda: PaceReading(progress.pace(), "the pace given"))
        labels = [r.label for r in progress.experiments.values() if r.note != "earlier"]
        self.total = len(labels)
        self.number = {label: i + 1 for i, label in enumerate(labels)}
        self._captured = 0.0
        self._criterion_said: set[str | None] = set()
        plural = "s" if self.total != 1 else ""
        console.print(f"session: {self.total} experiment{plural}, about {_min_s(progress.announced_s)} min:s of "
                      "rig time", highlight=False)

    def _eta(self) -> str:
        """The wall time left, as the session's progress has it (not said while it is not known)."""
        left = self.progress.wall_left_s()
        return "" if left is None or not self.progress.rig_done_s() else \
            f" About {_min_s(left)} left (m:s of wall clock)."

    def _head(self, label: str | None) -> str:
        width = 2 * len(str(self.total)) + 3 + 8
        if label is None or label not in self.number:
            return escape(f"{'[session]':<{width}}")      # not a rich style tag
        return f"{f'[{self.number[label]:{len(str(self.total))}d}/{self.total}]'} {label:<8}"

    def __call__(self, e: Event) -> None:
        def say(text: str, style: str = "") -> None:
            self.console.print(f"{self._head(e.experiment)} {text}", style=style, highlight=False)

        if self._own:
            self.progress(e)
        if e.kind == Kind.PHASE:
            self._captured = 0.0
            if e.data["phase"] != Phase.ALARM:          # the alarm event that follows says it, in red
                say(describe(e))
        elif e.kind == Kind.PROGRESS and e.data.get("phase") == Phase.SETTLING:
            if "bias_limit_sigma" in e.data and e.experiment not in self._criterion_said:
                self._criterion_said.add(e.experiment)   # once per experiment: what settling waits for
                limit = e.data["bias_limit_sigma"]
                say(f"Settling: the capture waits until the transient left by the move could shift the fitted "
                    f"parameters by less than {limit:g} of their standard deviation; the lines below count the "
                    "cycles left until then.", "dim")
            say(describe(e), "dim")
        elif e.kind == Kind.PROGRESS and e.data.get("phase") == Phase.CAPTURING:
            if e.data["fraction"] >= self._captured + 0.25:
                self._captured = e.data["fraction"]
                say(describe(e), "dim")
        elif e.kind == Kind.EXPERIMENT_DONE:
            say(f"[green]{describe(e)}[/green]{self._eta()}")
        elif e.kind == Kind.PREDICTION:   # the rest predicted again (qc run: from the unit's own parameters)
            left = self.progress.wall_left_s()
            said = "" if left is None else f" About {_min_s(left)} left (m:s of wall clock)."
            say(f"{escape(describe(e))}{said}")
        elif e.kind == Kind.SESSION_END:
            self._last_line()
        elif e.kind in (Kind.LOG, Kind.PACE_PROBE, Kind.HOLD, Kind.HOLD_END, Kind.CAPTURE_WINDOW):
            say(describe(e), "dim")
        elif e.kind in (Kind.LINK, Kind.ALARM, Kind.EXPERIMENT_FAILED):
            say(describe(e), "red")

    def _last_line(self) -> None:
        progress = self.progress
        took, announced, pace = progress.rig_clock() - progress.rig_started, progress.announced_s, \
            self._pace_reading()
        if pace.rig_s_per_s > 1.0 and progress.gone:   # no reading of the rig's time after the link went
            self.console.print(f"session took {_min_s(took)} min:s of this computer's clock; its rig time is not "
                               f"known: the {' and the '.join(progress.gone)} link was lost, and the pace measured "
                               f"before ({pace}) says nothing of the time after; announced {_min_s(announced)}",
                               highlight=False)
        elif pace.rig_s_per_s > 1.0:   # links faster than the rig's time: its minutes, from the measured pace
            self.console.print(f"session took {_min_s(took)} min:s of this computer's clock; at {pace}, about "
                               f"{_min_s(took * pace.rig_s_per_s)} min:s of rig time; announced "
                               f"{_min_s(announced)}", highlight=False)
        else:
            self.console.print(f"session took {_min_s(took)} min:s of rig time; announced {_min_s(announced)}",
                               highlight=False)


class ProgressBar:
    """Queued subscriber for notebooks: one bar over the session's rig time (a widget in
    Jupyter, text elsewhere), rendered from the session's :class:`SessionProgress`: what
    is done and what is left, the running experiment named."""

    def __init__(self, progress: SessionProgress | dict[str, float]) -> None:
        from tqdm.auto import tqdm  # only notebooks and scripts that ask for the bar load it

        self._own = not isinstance(progress, SessionProgress)
        self.progress = progress if isinstance(progress, SessionProgress) else SessionProgress(progress)
        self.bar = tqdm(total=round(self.progress.announced_s), unit="s", desc="session",
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s of rig time")

    def __call__(self, e: Event) -> None:
        if self._own:
            self.progress(e)
        if e.kind == Kind.PHASE and e.experiment:
            extra = f" {e.data['cycles']} cycles" if "cycles" in e.data else ""
            self.bar.set_description(f"{e.experiment} {e.data['phase']}{extra}")
        elif e.kind in (Kind.EXPERIMENT_DONE, Kind.EXPERIMENT_FAILED, Kind.PREDICTION):
            done, left = self.progress.rig_done_s(), self.progress.rig_left_s()
            if left is not None:
                self.bar.total = round(done + left)
            self.bar.n = min(round(done), self.bar.total)
            self.bar.refresh()
        elif e.kind == Kind.SESSION_END:
            self.bar.set_description(str(e.data.get("message", "ended")))
            if e.data.get("exit_status") == ExitStatus.COMPLETE:
                self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()


def _min_s(seconds: float) -> str:
    """Minutes and seconds: whole minutes hid the ETA's error on a short session (a
    1.4 min experiment announced as 1 min 'took 2 min')."""
    return f"{int(seconds // 60)}:{int(seconds % 60):02d}"
