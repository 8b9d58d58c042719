"""From a session folder to a judgement: read the captured experiments, identify the
spec's parameters, compute the characteristics, judge them.  ``qc run`` and ``qc judge``
both come here, reading the files, so that a re-judgement of the same data under the
same spec gives the same numbers; ``identify batch --db`` comes with its own fit
(:func:`evaluate_identified`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from identify.dataset import Experiment, read_dataset
from identify.errors import IdentifyError
from identify.fit import fit_experiments
from identify.fit_warnings import FitWarning, WarningCode
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.preparation import model_columns, resolve_outputs
from identify.result import FitResult
from rig.qc.characteristics import Identified, Measured, check_model, measure
from rig.qc.judge import Judgement, judge
from rig.qc.spec import Spec


@dataclass
class Evaluation:
    model: CompiledModel
    experiments: list[Experiment]
    fit: FitResult | None
    measured: list[Measured]
    judgement: Judgement
    fit_s: float                                   # identification and characteristics, wall time
    notes: list[str] = field(default_factory=list)  # fit warnings, or why there is no fit


FIT_ITERATIONS = 40          # a production unit's identification (identify.fit's default)
# A master check's or a study's run takes its time: data from a transducer that drifted
# since its calibration fit no model well and converge slowly (a load cell 3 % high: 54
# iterations), and such a run must still give its values to name what drifted.
STUDY_FIT_ITERATIONS = 150


def evaluate(spec: Spec, session: Path, max_iterations: int = FIT_ITERATIONS, diagnose: bool = True) -> Evaluation:
    """``diagnose`` False: no identification (a spec whose verdict rests on measurands
    alone is judged without it, e.g. while its record still grows); the predicted
    characteristics are then missing, which decides nothing."""
    t0 = time.perf_counter()
    model = check_model(spec)
    experiments = periodic_experiments(model, session)
    params = Parameters.from_file(model, spec.start) if spec.start else Parameters(model)
    notes: list[str] = []
    fit: FitResult | None = None
    if not diagnose and spec.model_free:
        return _judge(spec, model, experiments, None, None, notes, t0, diagnosed=False)
    try:
        fit = fit_experiments(model, experiments, params, list(spec.estimate), n=spec.grid_points,
                              max_iterations=max_iterations)
        notes += [_for_the_verdict(w, fit) for w in fit.findings]
        if not fit.converged:
            notes.append(f"identification did not converge: {fit.message}")
    except IdentifyError as exc:
        notes.append(f"identification failed: {exc}")
    return _judge(spec, model, experiments, fit, Identified.from_fit(fit), notes, t0)


def _for_the_verdict(warning: FitWarning, fit: FitResult) -> str:
    return verdict_note(warning, fit.covariance_residual is not None)


def verdict_note(warning: FitWarning, residual_based: bool) -> str:
    """A fit's warning as the QC report states it: the fit report says which σ it lists
    first, the verdict uses the residual-based one where there is one (``residual_based``;
    the σ notes say so per characteristic), so the report must not say the σ covers the
    noise only."""
    if warning.code is not WarningCode.MODEL_ERROR:
        return str(warning)
    if residual_based:
        return f"{warning.finding}; the verdict propagates the residual-based covariance, which includes it"
    return f"{warning.finding}; too few experiments for a residual-based covariance: the verdict's σ is noise-only"


def evaluate_identified(spec: Spec, session: Path, identified: Identified, notes: list[str]) -> Evaluation:
    """The same judgement from an identification made elsewhere (a batch's stored result,
    whose model and estimated set are the spec's): no fit here, the measured data read
    for the characteristics that come from them."""
    t0 = time.perf_counter()
    model = check_model(spec)
    return _judge(spec, model, periodic_experiments(model, session), None, identified, list(notes), t0)


def periodic_experiments(model: CompiledModel, session: Path) -> list[Experiment]:
    columns = model_columns(model, resolve_outputs(model, None))
    return [e for e in read_dataset(session, columns).experiments if e.kind == "periodic"]


def _judge(spec: Spec, model: CompiledModel, experiments: list[Experiment], fit: FitResult | None,
           identified: Identified | None, notes: list[str], t0: float, diagnosed: bool = True) -> Evaluation:
    measured = measure(spec, model, identified, experiments)
    notes += [f"{m.name}: {m.note}" for m in measured if m.note]
    if spec.model_free and identified is None and diagnosed:
        # the measurands decide; what only the model gives (the part to blame, the drop) is missing, and said so
        notes.append("diagnosis missing: no converged identification; the verdict rests on the measured "
                     "characteristics, the predicted ones have no value")
    return Evaluation(model, experiments, fit, measured, judge(spec, measured), time.perf_counter() - t0, notes)
