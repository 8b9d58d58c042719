"""A session's periodic experiments fitted (``rig run --identify``, the console's fit):
RESULT.json and report.txt written into the session."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console

from identify.dataset import Experiment
from identify.exit_codes import EXIT_NOT_CONVERGED, EXIT_OK
from identify.files import atomic_write_bytes
from rig.session.preparation import RunOptions
from rig.session.storage import Session

if TYPE_CHECKING:  # the numerics are imported when a fit runs, not with the command line
    from identify.result import FitResult

def fit_session(session: Session, model_name: str, params_file: str | Path | None, estimate: list[str],
                captured: list[Experiment],
                progress: Callable[[int, float, np.ndarray], None] | None = None) -> FitResult:
    """Fit the session's periodic experiments: those captured in this run from memory,
    earlier ones (a resumed session) from their files; RESULT.json and report.txt are
    written into the session.  The numbers equal ``python -m identify fit`` on the folder;
    ``progress`` follows the estimator's iterations (the GUI's fit view)."""
    from identify.dataset import read_dataset
    from identify.fit import fit_experiments
    from identify.model import load_model
    from identify.parameters import Parameters
    from identify.preparation import model_columns, resolve_outputs

    model = load_model(model_name)
    params = Parameters.from_file(model, params_file) if params_file else Parameters(model)
    by_label = {e.label: e for e in captured}
    earlier = [e["label"] for e in session.manifest["experiments"] if e["label"] not in by_label]
    if earlier:
        stored = read_dataset(session.path, model_columns(model, resolve_outputs(model, None)), earlier)
        by_label.update((label, stored.experiment(label)) for label in earlier)
    experiments = [by_label[e["label"]] for e in session.manifest["experiments"] if e.get("kind") == "periodic"]
    result = fit_experiments(model, experiments, params, estimate, progress=progress)
    result.write_json(session.path / "RESULT.json")
    atomic_write_bytes(session.path / "report.txt", (result.fit_report() + "\n").encode())
    return result


def purpose_departure(manifest: dict[str, Any], estimate: list[str]) -> str | None:
    """The warning a fit's first line carries where it holds a parameter the session's plan
    was designed for at its prior (None without a purpose, or where it fits them all)."""
    from identify.plans import Purpose

    if "purpose" not in manifest:
        return None
    return Purpose.from_document(manifest["purpose"], "dataset.json").departure(estimate)


def identify_session(session: Session, opt: RunOptions, console: Console, captured: list[Experiment]) -> int:
    """``rig run --identify``: fit in memory right after the capture, print the report."""
    from identify.errors import IdentifyError

    command = (f"python -m identify fit {session.path} --model {opt.model} --estimate {','.join(opt.estimate)}"
               + (f" --params {opt.params}" if opt.params else "") + " --output RESULT.json")
    departure = purpose_departure(session.manifest, opt.estimate)
    if departure:
        console.print(departure, highlight=False)
    console.print(f"identifying {', '.join(opt.estimate)} ({opt.model}) on the session's periodic experiments; "
                  f"same as: {command}", highlight=False)
    try:
        result = fit_session(session, opt.model, opt.params, opt.estimate, captured)
    except IdentifyError as exc:
        console.print(f"[red]identification failed:[/red] {exc} (the captured session is complete and kept)",
                      highlight=False)
        return EXIT_NOT_CONVERGED
    print(result.fit_report())
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED
