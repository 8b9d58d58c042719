"""Fits for the console (no Qt here): identification right after a session (the same
:func:`rig.session.fitting.fit_session` as ``rig run --identify``), a re-fit of a stored session
with another model or start file, and the 1-dof/2-dof comparison of ``identify
compare`` (both on the stroke, 1-dof estimating θ5, θ6, θ7).

Each fit runs in a process of its own: a fit holds Python's interpreter lock for long
stretches, and in the console's process that would stall the window (and the
acquisition's threads).  The process sends its progress and a :class:`FitSummary` —
what the fit view shows, all plain data — back through a queue, and can be ended at
once when the console closes.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from identify.dataset import Experiment, read_dataset, read_manifest
from identify.errors import IdentifyError, InputError
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.preparation import model_columns, resolve_outputs
from identify.result import ExperimentFit, FitResult
from rig.errors import BadInput, RigError

Progress = Callable[[int, float, np.ndarray], None]
ESTIMATE_1DOF = ["theta5", "theta6", "theta7"]


@dataclass
class FitSummary:
    """A fit as the fit view shows it: RESULT.json's document and the grid curves."""

    model: str
    outputs: list[str]
    estimated: list[str]
    converged: bool
    channel_variances: dict[str, float]
    experiments: list[ExperimentFit]
    document: dict[str, Any]

    @classmethod
    def of(cls, r: FitResult) -> FitSummary:
        return cls(r.model, list(r.outputs), list(r.estimated), r.converged, dict(r.channel_variances),
                   r.experiments, r.to_document())


# ----- the jobs (run in the fit process) -------------------------------------------------------------
def session_fit(session: Any, opt: Any, captured: list[Experiment], progress: Progress) -> FitSummary:
    """``rig run --identify``'s fit: RESULT.json and report.txt written into the session."""
    from rig.session.fitting import fit_session

    return FitSummary.of(fit_session(session, opt.model, opt.params, opt.estimate, captured, progress))


def _refit(folder: Path, model_name: str, params_path: str | None, estimate: list[str],
           outputs: list[str] | None, progress: Progress) -> FitResult:
    model = load_model(model_name)
    outputs = resolve_outputs(model, outputs)
    labels = [e.label for e in read_manifest(folder).experiments if e.kind == "periodic"]
    ds = read_dataset(folder, model_columns(model, outputs), labels)
    params = Parameters.from_file(model, params_path) if params_path else Parameters(model)
    return fit_experiments(model, ds.select(labels), params, estimate, outputs=outputs, progress=progress)


def refit(folder: Path, model_name: str, params_path: str | None, estimate: list[str],
          progress: Progress) -> FitSummary:
    """Fit the periodic experiments of a dataset folder, as ``identify fit`` does (nothing written)."""
    return FitSummary.of(_refit(folder, model_name, params_path, estimate, None, progress))


def compare_models(folder: Path, estimate_2dof: list[str], params_2dof: str | None,
                   progress: Progress) -> dict[str, FitSummary]:
    """1-dof and 2-dof fitted to the stroke of the same experiments (``identify compare``)."""
    return {"1dof": FitSummary.of(_refit(folder, "1dof", None, ESTIMATE_1DOF, ["stroke_mm"], progress)),
            "2dof": FitSummary.of(_refit(folder, "2dof", params_2dof, estimate_2dof, ["stroke_mm"], progress))}


def _child(out: Any, job: Callable[..., Any], args: tuple[Any, ...]) -> None:
    os.nice(10)    # background work: the console and the acquisition get the CPU first

    def progress(iteration: int, objective: float, _values: np.ndarray) -> None:
        out.put(("progress", iteration, objective))
    try:
        out.put(("done", job(*args, progress=progress)))
    except (InputError, IdentifyError, BadInput, RigError) as exc:
        out.put(("failed", str(exc)))
    except Exception:  # noqa: BLE001 — a bug: its traceback goes to the console's log
        out.put(("failed", "internal error:\n" + traceback.format_exc()))


# ----- the runner (in the console's process) -----------------------------------------------------------
@dataclass
class _Job:
    title: str
    job: Callable[..., Any]
    args: tuple[Any, ...]
    done: Callable[[Any], None]


class FitRunner:
    """Fits one after the other, each in a fresh process (spawned: the console's threads
    must not be forked); ``on_progress(title, iteration, objective)`` and
    ``on_failed(title, text)`` are called from the runner's thread."""

    def __init__(self, on_progress: Callable[[str, int, float], None],
                 on_failed: Callable[[str, str], None]) -> None:
        self.on_progress, self.on_failed = on_progress, on_failed
        self._context = multiprocessing.get_context("spawn")
        self._jobs: queue.Queue[_Job | None] = queue.Queue()
        self._process: Any = None
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fit", daemon=True)
        self._thread.start()

    def submit(self, title: str, job: Callable[..., Any], args: tuple[Any, ...], done: Callable[[Any], None]) -> None:
        self._jobs.put(_Job(title, job, args, done))

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            if not self._closed.is_set():
                self._one(job)

    def _one(self, job: _Job) -> None:
        out = self._context.Queue()
        process = self._context.Process(target=_child, args=(out, job.job, job.args), name="fit", daemon=True)
        self._process = process
        process.start()
        try:
            while True:
                try:
                    message = out.get(timeout=0.2)
                except queue.Empty:
                    if not process.is_alive():
                        if not self._closed.is_set():
                            self.on_failed(job.title, f"the fit process ended without a result "
                                                      f"(exit code {process.exitcode})")
                        return
                    continue
                if message[0] == "progress":
                    self.on_progress(job.title, message[1], message[2])
                elif message[0] == "done":
                    job.done(message[1])
                    return
                else:
                    self.on_failed(job.title, message[1])
                    return
        finally:
            process.join(timeout=5)
            self._process = None

    @property
    def busy(self) -> bool:
        """A fit process is running."""
        process = self._process
        return process is not None and process.is_alive()

    def close(self) -> None:
        """End the fit that runs (its result is not wanted any more) and the runner."""
        self._closed.set()
        process = self._process
        if process is not None and process.is_alive():
            process.terminate()
        self._jobs.put(None)
        self._thread.join(timeout=10)
