"""One call from experiments to a fit result: the path ``identify fit`` takes, also used
in memory by the rig right after its last capture (so both give the same numbers)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from identify.dataset import Experiment
from identify.differentiation import Grid
from identify.errors import InputError
from identify.estimator import Estimator
from identify.fit_warnings import FitWarning, WarningCode
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.preparation import (
    BDF2_ERROR,
    MULTISINE_LINES,
    PeriodicData,
    bdf2_error,
    choose_points,
    excitation,
    fewest_samples,
    prepare_periodic,
    resolve_outputs,
)
from identify.result import FitResult
from identify.trajectory import TransientData, is_transient, prepare_transient

DEFAULT_POINTS = 800  # per period on the bdf2 grid, as in the paper
# Kinks (|ẋ|, hysteresis) make every scheme converge at second order in the step: a
# model grid four times finer than the data's cuts that error sixteenfold (Bouc-Wen at
# 750 Hz: 1.8 % of the output RMS on the data's grid, 0.08 % on the finer one).
NONSMOOTH_OVERSAMPLE = 4


@dataclass(frozen=True)
class GridChoice:
    """The grid a fit or prediction uses, and sentences saying what was chosen (notes) or
    what may make the numbers wrong (warnings, which the result carries too)."""

    scheme: str
    n: int
    oversample: int
    notes: list[str] = field(default_factory=list)
    warnings: list[FitWarning] = field(default_factory=list)


def choose_grid(model: CompiledModel, experiments: list[Experiment], outputs: list[str], n: int | None,
                scheme: str | None, oversample: int | None) -> GridChoice:
    """Scheme, points per period and model-grid oversampling, each as given or chosen:
    the scheme from the records (spectral where the inputs are broadband, with lines
    bdf2 would not resolve on its grid; a warning where bdf2 was asked for all the
    same), n from the data for the spectral scheme (DEFAULT_POINTS for bdf2),
    oversampling for spectral grids of models with kinks."""
    notes: list[str] = []
    warnings: list[FitWarning] = []
    if scheme in (None, "bdf2"):
        lines, highest, label = excitation(model, experiments)
        error = bdf2_error(highest, n or DEFAULT_POINTS) if highest else 0.0
        unresolved = lines >= MULTISINE_LINES and error > BDF2_ERROR
        if unresolved and scheme is None:
            scheme = "spectral"
            notes.append(f"scheme spectral: {label} is broadband ({lines} excited lines up to harmonic {highest}), "
                         f"which bdf2 on {n or DEFAULT_POINTS} points would differentiate {100 * error:.0f} % wrong "
                         f"(--scheme bdf2 --n N to insist)")
        elif unresolved:
            warnings.append(FitWarning(WarningCode.BDF2_UNRESOLVED, {
                "n": n or DEFAULT_POINTS, "record": label, "harmonic": highest, "lines": lines,
                "percent": float(100 * error)}))
        scheme = scheme or "bdf2"
    if n is None:
        if scheme == "spectral":
            n, why = choose_points(model, experiments, outputs)
            notes.append(why)
        else:
            # A model driven by an input's derivative gets no more points than a record has
            # samples per period (unless asked): finer grid points fold fewer than one
            # sample each, and the derivative taken there is mostly folding noise (800
            # points on 83-119 samples per period put a Dahl damper's force 5 σ off).
            # Other models keep bdf2's default: their derivatives come from the model's
            # states, and the fold's noise covariance covers the sparse bins (the 2-dof
            # standard set's 500 samples per period at 2 Hz, calibrated by bench_sigma).
            n = DEFAULT_POINTS
            if experiments:
                fewest, label = fewest_samples(experiments)
                if fewest < n * (1 - 1e-6):
                    if model.input_derivatives:
                        n = int(np.floor(fewest * (1 + 1e-6)))
                        notes.append(f"n = {n}, the fewest samples per period of the records ({fewest:.1f}, in "
                                     f"{label}): model {model.name!r} takes its inputs' derivatives, which bdf2's "
                                     f"default {DEFAULT_POINTS} points would take between the samples")
                    else:
                        notes.append(f"n = {n}, bdf2's default, finer than the records' {fewest:.1f} samples per "
                                     f"period in {label}: the outputs' derivatives come from the model, and the "
                                     f"fold's noise covariance covers the sparse grid points")
    elif experiments and model.input_derivatives:
        fewest, label = fewest_samples(experiments)
        if n > fewest * (1 + 1e-6):
            raise InputError(f"n = {n} is finer than the records ({fewest:.1f} samples per period in {label}): "
                             f"grid points between the samples hold folding noise, and the derivatives of model "
                             f"{model.name!r}'s inputs taken there are mostly that noise (errors in variables); "
                             f"use --n {int(fewest)} or fewer, or leave --n out")
    if oversample is None:
        oversample = NONSMOOTH_OVERSAMPLE if scheme == "spectral" and model.nonsmooth else 1
        if oversample > 1:
            notes.append(f"model solved on {oversample} x {n} points: model {model.name!r} has kinks (|x|, sign, "
                         f"max), whose error falls only with the square of the step")
    return GridChoice(scheme, n, oversample, notes, warnings)


def drift_warnings(model: CompiledModel, data: list[PeriodicData]) -> list[FitWarning]:
    """One warning per column whose mean drifted in some record (removed before folding,
    identify.folding): how much, where."""
    units = {ch.column: ch.unit for ch in [*model.declaration.inputs.values(), *model.declaration.outputs.values()]}
    out = []
    for column in dict.fromkeys(c for d in data for c in d.folded.drift):
        where = [(d.label, float(d.folded.drift[column])) for d in data if d.folded.drift.get(column)]
        if where:
            out.append(FitWarning(WarningCode.DRIFT, {"column": column, "records": where,
                                                      "unit": units.get(column, "")}))
    return out


def fit_experiments(model: CompiledModel, experiments: list[Experiment], params: Parameters, estimate: list[str], *,
                    n: int | None = DEFAULT_POINTS, scheme: str | None = "bdf2", outputs: list[str] | None = None,
                    max_iterations: int = 40,
                    progress: Callable[[int, float, np.ndarray], None] | None = None,
                    fixed: dict[str, dict[int, float]] | None = None, stability: bool = False,
                    oversample: int | None = 1, linear_solver: str = "auto",
                    time_limit_s: float | None = None, announce: Callable[[str], None] | None = None,
                    transient: bool | None = None, transient_oversample: int = 1) -> FitResult:
    """Joint Bayesian fit of ``estimate`` over all ``experiments`` (shared parameters).

    ``params`` gives the start values and priors; it is not modified.  ``fixed`` holds
    per-experiment values of fixed parameters ({label: {parameter index: value}}, e.g.
    friction from :mod:`identify.friction`).  ``n`` or ``oversample`` None: chosen
    (:func:`choose_grid`), ``scheme`` None likewise; ``linear_solver`` as for :class:`Grid`.  Each experiment of
    the result names the start of its first periodic solve (:mod:`identify.start`).
    Stopped by ``max_iterations``, ``time_limit_s`` or Ctrl-C, the result is the last
    iterate, not converged (``interrupted`` for Ctrl-C).  ``announce`` is told of slow
    steps after the iterations (``stability``'s Floquet multipliers).

    ``transient`` True fits every record sample by sample from its fitted initial state
    (:mod:`identify.trajectory`), False folds every one onto a period; None (the
    default) fits as transient the records whose dataset entry says ``capture =
    "transient"`` and folds the others.  A transient record's model is solved on
    ``transient_oversample`` points per sample step."""
    params = params.copy()
    # The original start: a fit restarted from a RESULT.json carries it as "initial".
    start = {p.name: p.value if p.initial is None else p.initial for p in params}
    params.set_estimated(estimate)
    outputs = resolve_outputs(model, outputs)
    as_transient = [e for e in experiments if (is_transient(e) if transient is None else transient)]
    periodic = [e for e in experiments if e not in as_transient]
    grid = choose_grid(model, periodic or experiments, outputs, n, scheme, oversample)
    n, oversample = grid.n, grid.oversample
    prepared: dict[str, PeriodicData | TransientData] = {
        d.label: d for d in prepare_periodic(model, periodic, n, outputs)}
    prepared.update({d.label: d for d in prepare_transient(model, as_transient, outputs, transient_oversample)})
    data = [prepared[e.label] for e in experiments]
    if fixed:
        names = params.names()
        for d in data:
            d.fixed = dict(fixed.get(d.label, {}))
            clash = [names[i] for i in d.fixed if names[i] in estimate]
            if clash:
                raise InputError(f"{', '.join(clash)}: estimated and also fixed per experiment")
    estimator = Estimator(model, data, params.copy(), Grid(n, grid.scheme, linear_solver, oversample), outputs,
                          max_iterations=max_iterations, progress=progress, stability=stability,
                          time_limit_s=time_limit_s, announce=announce)
    result = estimator.fit()
    result.start = {k: start[k] for k in result.estimated}
    result.priors = {k: params[k].prior_std for k in result.estimated}
    result.oversample = oversample
    result.findings += grid.warnings + drift_warnings(model, [d for d in data if isinstance(d, PeriodicData)])
    channels = list(model.declaration.inputs.values())
    result.units = {ch.column: ch.unit for ch in [*channels, *(model.declaration.outputs[o] for o in outputs)]}
    for e, d in zip(result.experiments, data, strict=True):
        e.start = estimator.solvers[e.label].starts_used.get(e.label, "")
        e.capture = "transient" if e.label in {x.label for x in as_transient} else "steady"
        e.inputs = {ch.column: ch.from_si(u) for ch, u in zip(channels, d.inputs[:len(channels)], strict=True)}
    return result
