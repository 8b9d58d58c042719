"""A whole session: check the plan, connect, capture every experiment, store, and
optionally identify in memory right after the last capture.

Exit status: 0 done; 1 identification did not converge; 2 bad input (plan, limits,
files) refused before anything moved; 3 aborted (alarm, lost link) after a safe
stop; 130 interrupted by the operator after a safe stop.
"""

from __future__ import annotations

import signal
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from rich.console import Console

from identify.dataset import Experiment
from identify.files import atomic_write_bytes
from identify.estimator import EstimationError
from rig.acquisition import Acquisition, AcquisitionError, Interrupted
from rig.config import load_rig_config
from rig.daq import Calibration, Daq, DaqError
from rig.events import Event, EventBus
from rig.plans import check_plan, estimate_duration_s, load_plan
from rig.registers import load_register_map
from rig.session import Session, SessionLog
from rig.shaker import AlarmError, Shaker, ShakerError

EXIT_OK, EXIT_NOT_CONVERGED, EXIT_BAD_INPUT, EXIT_ABORTED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


@dataclass
class RunOptions:
    plan: str
    shaker: str
    daq: str
    out: Path
    experiments: list[str] | None = None
    periods: int | None = None
    resume: bool = False
    identify: bool = False
    on_alarm: str = "abort"                 # or "skip"
    rig_config: str | None = None
    calibration: str | None = None
    register_map: str | None = None
    model: str = "2dof"
    params: str | None = None
    estimate: list[str] = field(default_factory=lambda: ["theta4", "theta6", "theta16"])
    date: str | None = None
    unit_serial: str = "unknown"


class ConsoleProgress:
    """Queued subscriber: one line per phase, settling and capture progress, and the
    session's ETA (wall clock, scaled from the rig-time estimate of what is done)."""

    def __init__(self, console: Console, estimates_s: dict[str, float]) -> None:
        self.console, self.estimates = console, estimates_s
        self.total, self.done, self.done_s = len(estimates_s), 0, 0.0
        self.started = time.monotonic()
        self._captured = 0.0
        console.print(f"session: {self.total} experiments, about {sum(estimates_s.values()) / 60:.0f} min of rig time",
                      highlight=False)

    def _eta(self) -> str:
        if not self.done_s:
            return ""
        left = (time.monotonic() - self.started) / self.done_s * (sum(self.estimates.values()) - self.done_s)
        return f", session ETA {int(left // 60)}:{int(left % 60):02d}"

    def __call__(self, e: Event) -> None:
        if e.kind == "experiment-done":
            self.done += 1
            self.done_s += self.estimates.get(e.experiment or "", 0.0)
        number = self.done if e.kind == "experiment-done" else min(self.done + 1, self.total)
        head = f"[{number:2d}/{self.total}] {e.experiment or '':<8}"
        if e.kind == "phase":
            extra = "".join(f" {k}={v}" for k, v in e.data.items() if k != "phase")
            self._captured = 0.0
            self.console.print(f"{head} {e.data['phase']}{extra}", highlight=False)
        elif e.kind == "progress" and e.data.get("phase") == "settling":
            ch = e.data["change"]
            self.console.print(f"{head}   cycle {e.data['cycles']:4d}: change stroke {ch['stroke_mm']:.3f} mm, "
                               f"force {ch['force_N']:.1f} N, pressure {ch['pressure_bar']:.4f} bar, "
                               f"temperature {ch['gas_temperature_C']:.3f} °C", highlight=False, style="dim")
        elif e.kind == "progress" and e.data.get("phase") == "capturing":
            if e.data["fraction"] >= self._captured + 0.25:
                self._captured = e.data["fraction"]
                self.console.print(f"{head}   captured {100 * self._captured:.0f} %", highlight=False, style="dim")
        elif e.kind == "experiment-done":
            flags = f" FLAGGED: {'; '.join(e.data['flags'])}" if e.data["flags"] else ""
            self.console.print(f"{head} [green]captured[/green] {e.data['file']} ({e.data['samples']} samples, "
                               f"{e.data['lost']} lost in window){flags}{self._eta()}", highlight=False)
        elif e.kind in ("log", "alarm", "experiment-failed"):
            style = "red" if e.kind != "log" else "dim"
            self.console.print(f"{head} {e.data.get('message', '')}", style=style, highlight=False)


def run_session(opt: RunOptions, console: Console | None = None) -> int:
    console = console or Console(stderr=True)
    config = load_rig_config(opt.rig_config)
    calibration = Calibration.from_file(opt.calibration)
    register_map = load_register_map(opt.register_map)
    if opt.resume:
        session = Session.resume(opt.out)
        plan = load_plan(session.meta["plan"]).select(session.meta["experiments"]).with_periods(session.meta["periods"])
    else:
        plan = load_plan(opt.plan).select(opt.experiments).with_periods(opt.periods)
    problems = check_plan(plan, config)
    if problems:
        console.print(f"[red]plan refused, nothing moved[/red] ({len(problems)} violation"
                      f"{'s' if len(problems) > 1 else ''} of the limits in {config.source}):", highlight=False)
        for p in problems:
            console.print(f"  {p}", highlight=False)
        return EXIT_BAD_INPUT
    if not opt.resume:
        snapshot = {"rig.toml": config.text, "daq-calibration.toml": calibration.text,
                    "register-map.toml": register_map.text, "plan.toml" if plan.text != "standard" else "plan.txt":
                    plan.text + "\n"}
        session = Session.create(opt.out, plan_source=opt.plan if opt.plan == "standard" else str(Path(opt.plan).resolve()),
                                 letters=[e.letter for e in plan.experiments], periods=opt.periods, date=opt.date,
                                 snapshot=snapshot, unit={"serial": opt.unit_serial},
                                 endpoints={"shaker": opt.shaker, "daq": opt.daq})
    todo = [e for e in plan.experiments if e.letter not in session.completed()]

    bus = EventBus()
    log = SessionLog(session.path / "session.log")
    bus.subscribe(log, inline=True)
    estimates = {session.label(e.letter): estimate_duration_s(replace(plan, experiments=(e,)), config,
                                                              e.static_position_mm * 1e-3) for e in todo}
    bus.subscribe(ConsoleProgress(console, estimates))
    if opt.resume:
        kept = sorted(session.completed())
        bus.publish("log", message=f"resuming: {len(kept)} experiments kept as captured ({', '.join(kept) or 'none'}), "
                                   f"{len(todo)} to do")
    shaker = Shaker(opt.shaker, config.limits, register_map, reconnect_s=config.reconnect_s,
                    on_event=lambda m: bus.publish("log", message=m))
    daq = Daq(opt.daq, calibration, rate_hz=config.daq_rate_hz, journal=session.journal_path,
              reconnect_s=config.reconnect_s, on_event=lambda m: bus.publish("log", message=m))
    acquisition = Acquisition(shaker, daq, config, bus)
    previous = signal.signal(signal.SIGINT, lambda *_: acquisition.stop_requested.set())
    status, code, captured = "complete", EXIT_OK, []
    try:
        try:
            shaker.connect()
            ident = daq.open()
            bus.publish("session-start", message=f"shaker {opt.shaker}, DAQ {opt.daq} ({ident})")
        except (ShakerError, DaqError) as exc:
            console.print(f"[red]error:[/red] {exc}", highlight=False)
            session.finish("not started")
            return EXIT_ABORTED
        for spec in todo:
            label = session.label(spec.letter)
            try:
                record = acquisition.run_experiment(spec, label)
            except AlarmError as exc:
                bus.publish("alarm", label, message=str(exc))
                acquisition.safe_stop(str(exc))
                if opt.on_alarm == "skip":
                    try:
                        shaker.reset_alarm()
                        bus.publish("experiment-failed", label, message=f"{label} skipped after the alarm")
                        continue
                    except ShakerError as reset_exc:
                        bus.publish("log", label, message=f"alarm reset failed: {reset_exc}")
                status, code = f"aborted: {exc}", EXIT_ABORTED
                break
            session_exp = session.write_experiment(record)
            captured.append(session_exp)
            bus.publish("experiment-done", label, file=session_exp.file, samples=len(record.index),
                        lost=record.lost_samples, flags=record.flags)
        acquisition.safe_stop("end of session" if code == EXIT_OK else status)
    except Interrupted:
        acquisition.safe_stop("interrupted by the operator")
        status, code = "interrupted", EXIT_INTERRUPTED
    except (ShakerError, DaqError, AcquisitionError) as exc:
        bus.publish("log", message=f"aborting: {exc}")
        acquisition.safe_stop(str(exc))
        status, code = f"aborted: {exc}", EXIT_ABORTED
    finally:
        signal.signal(signal.SIGINT, previous)
        session.finish(status)
        bus.publish("session-end", message=status)
        shaker.close()
        daq.close()
        bus.close()
        log.close()
    if code != EXIT_OK:
        console.print(f"[red]session {status}[/red]; resume with --resume --out {session.path}", highlight=False)
        return code
    console.print(f"session complete: {session.path}", highlight=False)
    if opt.identify:
        return identify_session(session, opt, console, captured)
    return EXIT_OK


def identify_session(session: Session, opt: RunOptions, console: Console, captured: list[Experiment]) -> int:
    """Fit the session's experiments in memory; RESULT.json and report.txt into the session."""
    from identify.dataset import read_dataset
    from identify.fit import fit_experiments
    from identify.model import load_model
    from identify.parameters import Parameters
    from identify.preparation import model_columns, resolve_outputs

    model = load_model(opt.model)
    params = Parameters.from_file(model, opt.params) if opt.params else Parameters(model)
    # Experiments captured in this run are in memory already; earlier ones (resume) come from their files.
    in_memory = {e.label: e for e in captured}
    earlier = [e["label"] for e in session.manifest["experiments"] if e["label"] not in in_memory]
    ds = read_dataset(session.path, model_columns(model, resolve_outputs(model, None)), earlier) \
        if earlier else None
    experiments: list[Experiment] = [in_memory.get(e["label"]) or ds.experiment(e["label"])
                                     for e in session.manifest["experiments"] if e.get("kind") == "periodic"]
    command = (f"python -m identify fit {session.path} --model {opt.model} --estimate {','.join(opt.estimate)}"
               + (f" --params {opt.params}" if opt.params else "") + f" --output RESULT.json")
    console.print(f"identifying {', '.join(opt.estimate)} ({opt.model}) on {len(experiments)} experiments; "
                  f"same as: {command}", highlight=False)
    try:
        result = fit_experiments(model, experiments, params, opt.estimate)
    except EstimationError as exc:
        console.print(f"[red]identification failed:[/red] {exc}", highlight=False)
        return EXIT_NOT_CONVERGED
    result.write_json(session.path / "RESULT.json")
    report = result.fit_report()
    atomic_write_bytes(session.path / "report.txt", (report + "\n").encode())
    print(report)
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED


def main_run(opt: RunOptions) -> int:
    try:
        return run_session(opt)
    except Exception as exc:  # noqa: BLE001 — turned into one clear line below
        from rig.cli import known_error

        message = known_error(exc)
        if message is None:
            raise
        print(f"error: {message}", file=sys.stderr)
        return EXIT_BAD_INPUT
