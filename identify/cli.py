"""``python -m identify``: fit, compare, friction, predict, drop, report, batch.

Exit status: 0 success (a fit converged); 1 a fit did not converge — the iteration cap
(``--max-iterations``), the time limit (``--time-limit``) or a failed line search —
with RESULT.json written all the same (``converged`` false, the last iterate, which
``--params RESULT.json`` restarts from), or a session of a batch failed; 2 bad input
(message names file and place, no traceback); 130 interrupted by Ctrl-C: a fit writes
its last iterate as for 1 (``interrupted`` true), a batch keeps its results.  A batch
with ``--db`` also exits 1 when a session's result could not be written to the QC
records database.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from identify import notation
from identify.argparsing import OneLineParser
from identify.dataset import Experiment, csv_bytes, read_dataset, read_manifest
from identify.differentiation import SCHEMES, Grid
from identify.errors import ComputationError, InputError
from identify.estimator import EstimationError
from identify.exit_codes import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_NOT_CONVERGED, EXIT_OK
from identify.files import atomic_write_bytes
from identify.fit import DEFAULT_POINTS, GridChoice, choose_grid, fit_experiments
from identify.model import DEFAULT_ESTIMATE, CompiledModel, load_model
from identify.parameters import Parameters, load_document
from identify.periodic import PeriodicSolver
from identify.plans import Purpose
from identify.preparation import model_columns, prepare_periodic, resolve_outputs
from identify.result import FitResult, failed_document, write_document
from identify.sinks import BatchState, DeliveryState
from identify.trajectory import is_transient
from identify.transient import drop_test

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from identify import batch, sinks

TABLE_ROWS = 40  # a longer batch shows only its failed sessions on the terminal (summary.csv has all)


class UsageError(InputError):
    """Command-line input that does not fit (reported like bad input)."""


def _csv_list(text: str | None) -> list[str] | None:
    return [x.strip() for x in text.split(",") if x.strip()] if text else None


def _labels(dataset_labels: list[str], wanted: list[str] | None) -> list[str]:
    """Experiment labels from full labels or their final letters (``a`` for ``920713a``);
    empty when none are wanted."""
    if not wanted:
        return []
    out = []
    for w in wanted:
        if w in dataset_labels:
            out.append(w)
            continue
        hits = [lb for lb in dataset_labels if lb.endswith(w)]
        if len(hits) != 1:
            raise UsageError(f"--experiments: {w!r} matches {len(hits)} labels "
                             f"(labels: {', '.join(dataset_labels)})")
        out.append(hits[0])
    return out


def _chosen_labels(dataset: str, experiments: str | None) -> list[str]:
    """Labels named by ``--experiments`` (labels or letters), else every periodic experiment."""
    manifest = read_manifest(dataset)
    periodic = [e.label for e in manifest.experiments if e.kind == "periodic"]
    return _labels(manifest.labels(), _csv_list(experiments)) or periodic


def _load_params(model: CompiledModel, path: str | None) -> Parameters:
    return Parameters.from_file(model, path) if path else Parameters(model)


def _grid_args(args: argparse.Namespace) -> tuple[str | None, int | None, int | None, str | None]:
    """--scheme, --n and --oversample as given, those not given taken from the fit whose
    RESULT.json is --params (a spectral fit predicted on bdf2's 800 points was 95 % off,
    silently), and a sentence saying what was taken."""
    given = (args.scheme, args.n, args.oversample)
    if not args.params:
        return (*given, None)
    doc, source = load_document(args.params)
    scheme = doc.get("scheme") if isinstance(doc, dict) and "parameters" in doc else None
    if scheme not in SCHEMES or args.scheme not in (None, scheme):
        return (*given, None)
    n = args.n if args.n is not None else doc.get("n") if isinstance(doc.get("n"), int) else None
    oversample = args.oversample if args.oversample is not None else (
        doc.get("oversample") if isinstance(doc.get("oversample"), int) else None)
    taken = [f"scheme {scheme}"] if args.scheme is None else []
    taken += [f"n = {n}"] if args.n is None and n is not None else []
    taken += [f"oversample {oversample}"] if args.oversample is None and oversample is not None else []
    note = (f"{', '.join(taken)}: the fit's, from {source} (--scheme, --n, --oversample to change)"
            if taken else None)
    return scheme, n, oversample, note


def _progress(console, params: Parameters, estimate: list[str]):
    """Per iteration a row of the estimates under a header naming them, in ``--estimate``
    order (the estimator reports them in the model's declaration order)."""
    declared = sorted(params.index(e) for e in estimate)
    order = [declared.index(params.index(e)) for e in estimate]
    width = max(12, *(len(e) for e in estimate))
    console.print(f"  {'iteration':>9s}  {'objective':>12s}  " + "  ".join(f"{e:>{width}s}" for e in estimate),
                  highlight=False)

    def report(iteration: int, objective: float, values: np.ndarray) -> None:
        console.print(f"  {iteration:9d}  {objective:12.6g}  " + "  ".join(f"{values[i]:{width}.6g}" for i in order),
                      highlight=False)
    return report


@dataclass
class _FitJob:
    """``identify fit``'s inputs, read and checked: the model, the data, the start, the grid."""

    model: CompiledModel
    outputs: list[str]
    groups: list[list[Experiment]]       # one joint group, or one per experiment (--per-experiment)
    params: Parameters
    estimate: list[str]
    choice: GridChoice
    transient: bool | None               # --capture: None as each record says, else all transient or all steady
    fixed: dict[str, dict[int, float]] | None = None   # friction held fixed per experiment (--friction)


def run_fit(args: argparse.Namespace) -> int:
    from rich.console import Console

    console = Console(stderr=True, soft_wrap=True)   # log lines unbroken when stderr is a file
    job = _fit_job(args, console)
    results = _fit_groups(job, args, console)
    if isinstance(results, int):                     # failed before a result: RESULT.json holds the start
        return results
    interrupted = any(r.interrupted for _, r in results)
    if interrupted:
        console.print("interrupted: RESULT.json holds the last iterate (converged false); restart with "
                      "--params RESULT.json", highlight=False, soft_wrap=True)
    if args.per_experiment:
        return _per_experiment_output(job, results, args, console)
    result = results[0][1]
    result.write_json(args.output)
    report = result.fit_report()
    print(report)
    if args.report:
        atomic_write_bytes(Path(args.report), (report + "\n").encode())
    if args.figures:
        _write_figures(result, Path(args.figures), console, bool(job.model.input_derivatives))
    return EXIT_INTERRUPTED if interrupted else EXIT_OK if result.converged else EXIT_NOT_CONVERGED


def _purpose(dataset: str) -> Purpose | None:
    """What the plan of the dataset's session was designed for (dataset.json's ``purpose``)."""
    manifest = read_manifest(dataset).manifest
    return Purpose.from_document(manifest["purpose"], f"{dataset}/dataset.json") if "purpose" in manifest else None


def _fit_job(args: argparse.Namespace, console: Console) -> _FitJob:
    """Model, data, start and grid, each checked before the (slow) fit; the grid said."""
    model = load_model(args.model)
    outputs = resolve_outputs(model, _csv_list(args.outputs))
    labels = _chosen_labels(args.dataset, args.experiments)
    ds = read_dataset(args.dataset, model_columns(model, outputs), labels)
    params = _load_params(model, args.params)
    purpose = _purpose(args.dataset)
    estimate = _csv_list(args.estimate)
    if args.estimate is None and purpose is not None and purpose.model in (args.model, model.name):
        estimate = list(purpose.estimate)
        console.print(f"estimating {', '.join(estimate)}: what the plan was designed for ({purpose.use.value}; "
                      f"--estimate to choose others)", highlight=False)
    elif purpose is not None and (departure := purpose.departure(estimate or [])):
        console.print(departure, highlight=False)
    if not estimate:
        raise UsageError("--estimate names no parameter" if args.estimate is not None else
                         "--estimate: name the parameters to fit (the dataset's plan states no purpose to take them "
                         "from)")
    params.copy().set_estimated(estimate)  # names checked before the (slower) folding
    scheme, n_given, oversample_given, taken = _grid_args(args)
    choice = choose_grid(model, ds.select(labels), outputs, n_given, scheme, oversample_given)
    grid = Grid(choice.n, choice.scheme, oversample=choice.oversample)
    plural = "s" if len(labels) != 1 else ""
    console.print(f"fitting {', '.join(estimate)} of model {model.name} on {len(labels)} experiment{plural} "
                  f"({grid.scheme}, n = {grid.n})", highlight=False)
    for note in [taken] * bool(taken) + choice.notes + [f"warning: {w}" for w in choice.warnings]:
        console.print(f"  {note}", highlight=False)
    transient = {"auto": None, "steady": False, "transient": True}[args.capture]
    if args.transient_oversample < 1:
        raise UsageError(f"--transient-oversample {args.transient_oversample}: must be 1 or more")
    as_transient = [e.label for e in ds.select(labels) if (is_transient(e) if transient is None else transient)]
    if as_transient:
        console.print(f"  fitted as transient records (from a fitted initial state, sample by sample"
                      f"{', ' if args.capture == 'auto' else ''}"
                      f"{'as the dataset says' if args.capture == 'auto' else ''}): {', '.join(as_transient)}",
                      highlight=False)
    if args.time_limit is not None and not args.time_limit > 0:
        raise UsageError(f"--time-limit {args.time_limit:g}: must be a positive number of seconds")
    groups = [[e] for e in ds.select(labels)] if args.per_experiment else [ds.select(labels)]
    fixed = None
    if args.friction:
        from identify.friction import load_fixed

        fixed = load_fixed(args.friction, params.names())
    return _FitJob(model, outputs, groups, params, estimate, choice, transient, fixed)


def _fit_groups(job: _FitJob, args: argparse.Namespace, console: Console) -> list[tuple[str, FitResult]] | int:
    """Each group's fit, until one is interrupted; an exit status where one had no result."""
    results: list[tuple[str, FitResult]] = []
    for group in job.groups:
        if args.per_experiment:
            console.print(f"experiment {group[0].label}", highlight=False)
        progress = _progress(console, job.params, job.estimate) if not args.quiet else None
        try:
            result = fit_experiments(job.model, group, job.params, job.estimate, n=job.choice.n,
                                     scheme=job.choice.scheme, outputs=job.outputs,
                                     max_iterations=args.max_iterations, progress=progress, fixed=job.fixed,
                                     stability=args.stability, oversample=job.choice.oversample,
                                     time_limit_s=args.time_limit,
                                     announce=lambda text: console.print(f"  {text}", highlight=False),
                                     transient=job.transient, transient_oversample=args.transient_oversample)
        except EstimationError as exc:
            console.print(f"[red]fit failed:[/red] {exc}", highlight=False)
            _write_failed(args.output, job.model, job.params, str(exc))
            return EXIT_NOT_CONVERGED
        except KeyboardInterrupt:  # while the start was evaluated, or a second Ctrl-C during the wrap-up
            console.print("interrupted before the fit had a result; RESULT.json holds the start", highlight=False)
            _write_failed(args.output, job.model, job.params, "interrupted (Ctrl-C) before the fit had a result")
            return EXIT_INTERRUPTED
        results.append((group[0].label if args.per_experiment else "joint", result))
        if result.interrupted:
            break
    return results


def _per_experiment_output(job: _FitJob, results: list[tuple[str, FitResult]], args: argparse.Namespace,
                           console: Console) -> int:
    """--per-experiment: the table, the reports and figures per experiment, one RESULT.json of all."""
    _per_experiment_table(results)
    if args.report:
        atomic_write_bytes(Path(args.report), "".join(f"=== experiment {label} ===\n{r.fit_report()}\n"
                                                      for label, r in results).encode())
    for label, r in results if args.figures else []:  # a folder per experiment: the same file names in each
        _write_figures(r, Path(args.figures) / label, console, bool(job.model.input_derivatives))
    for label, r in results:
        for w in r.warnings:
            print(f"warning ({label}): {w}")
    interrupted = any(r.interrupted for _, r in results)
    converged = all(r.converged for _, r in results) and len(results) == len(job.groups)
    write_document(args.output, {"model": job.model.name, "converged": converged, "interrupted": interrupted,
                                 "per_experiment": {lb: r.to_document() for lb, r in results}})
    return EXIT_INTERRUPTED if interrupted else EXIT_OK if converged else EXIT_NOT_CONVERGED


def _write_figures(result: FitResult, folder: Path, console: Console, loops: bool) -> None:
    from identify.figures import write_figures

    for path in write_figures(result, folder, loops):
        console.print(f"figure {path}", highlight=False, soft_wrap=True)  # a path whole, to copy


def _write_failed(path: str, model: CompiledModel, params: Parameters, message: str) -> None:
    write_document(path, failed_document(model, params, message))


def _print_table(table: Table) -> None:
    """A table on stdout, numbers never cut: on a terminal at its width (cells fold onto
    a second line), into a file or a pipe as wide as the table needs (rich would cut it
    to 80 columns there, `-5.16528…`)."""
    from rich.console import Console
    from rich.measure import Measurement

    console = Console()
    if not console.is_terminal:
        wide = console.options.update(max_width=100_000)
        console = Console(width=max(80, Measurement.get(console, wide, table).maximum))
    console.print(table)


def _per_experiment_table(results: list[tuple[str, FitResult]]) -> None:
    from rich.table import Table

    names = results[0][1].estimated
    table = Table(title="per-experiment estimates (value ± std)")
    table.add_column("experiment", overflow="fold")
    table.add_column("f [Hz]", justify="right", overflow="fold")
    for nm in names:
        unit = results[0][1].params[nm].unit
        table.add_column(f"{nm} [{notation.unit_text(unit)}]" if unit and unit != "-" else nm, justify="right",
                         overflow="fold")
    for label, r in results:
        mark = "*" if r.std_residual is not None else ""
        table.add_row(label, f"{r.experiments[0].frequency_hz:g}",
                      *[notation.plus_minus(r.value(nm), r.honest_std(nm)) + mark for nm in names])
    _print_table(table)
    if any(r.std_residual is not None for _, r in results):
        print("* residual-based σ: residuals exceed the measurement noise, so this σ includes the model error "
              "(the noise-only σ is in RESULT.json as std)")


def run_predict(args: argparse.Namespace) -> int:
    model = load_model(args.model)
    params = _load_params(model, args.params)
    manifest = read_manifest(args.dataset)
    label = _labels(manifest.labels(), [args.experiment])[0]
    exp = manifest.experiment(label)
    d = model.declaration
    input_cols = [ch.column for ch in d.inputs.values()] if exp.kind == "periodic" else []
    ds = read_dataset(args.dataset, input_cols, [label])
    exp = ds.experiment(label)
    theta = params.vector()
    t = exp.time_s
    cols: dict[str, np.ndarray] = {"time_s": t}
    if exp.kind == "periodic":
        scheme, n_given, oversample_given, taken = _grid_args(args)
        choice = choose_grid(model, [exp], [], n_given, scheme, oversample_given)
        for note in [taken] * bool(taken) + choice.notes + [f"warning: {w}" for w in choice.warnings]:
            print(note, file=sys.stderr)
        grid = Grid(choice.n, choice.scheme, oversample=choice.oversample)
        data = prepare_periodic(model, [exp], choice.n, [])[0]
        sol = PeriodicSolver(model, grid).solve(data.inputs, data.frequency_hz, theta, label=label)
        y = model.output(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        phase = t * exp.frequency_hz
        for ch in d.inputs.values():
            cols[ch.column] = exp.column(ch.column)
        for i, name in enumerate(model.output_names):
            if name not in cols:
                cols[name] = d.outputs[name].from_si(grid.interpolate(y[i], phase))
    elif model.input_derivatives:
        raise InputError(f"experiment {label!r} is a {exp.kind} record, and model {model.name!r} takes its inputs' "
                         f"derivatives, which identify takes on a periodic record's grid only")
    else:
        mass = float(exp.meta["drop_mass_kg"])
        v0 = float(exp.meta.get("drop_velocity_m_s", 0.0))
        traj = drop_test(model, theta, mass, v0, t - t[0])
        for i, name in enumerate(model.output_names):
            cols[name] = d.outputs[name].from_si(traj.outputs[i])
        assert exp.data is not None  # read_dataset loaded the chosen experiment
        for name in model.output_names:
            if name in exp.data.columns:
                rms = float(np.sqrt(np.mean((cols[name] - exp.column(name)) ** 2)))
                print(f"{name:20s} RMS error {rms:.5g}")
    atomic_write_bytes(Path(args.output), csv_bytes(cols))
    print(f"wrote {args.output} ({len(t)} samples, columns {', '.join(cols)})")
    return EXIT_OK


def run_drop(args: argparse.Namespace) -> int:
    """The virtual drop test of a fit (identify/drop.py): the peaks with σ, the histories
    as CSV and a figure, beside a measured drop when one is given."""
    from identify import drop

    fitted = drop.load_fitted(args.result, args.model)
    asked = {"mass_kg": args.mass, "velocity_m_s": args.velocity, "duration_s": args.duration}
    measured = drop.read_measured(args.measured, args.duration) if args.measured else None
    if measured is not None and measured.landing is not None:
        differs = [f"{k} {v:g} (the record's {getattr(measured.landing, k):g})" for k, v in asked.items()
                   if v is not None and k != "duration_s" and v != getattr(measured.landing, k)]
        if differs:
            raise UsageError(f"--measured {args.measured}: a drop of other conditions than asked: "
                             f"{', '.join(differs)}; leave them out to predict the record's")
        landing = measured.landing
    else:
        landing = drop.Landing(**{k: v for k, v in asked.items() if v is not None})
    if args.discrepancy is not None:
        discrepancy: drop.DropDiscrepancy | None = drop.DropDiscrepancy.given(args.discrepancy)
        units: list[drop.TypeTestUnit] = []
    elif args.type_test:
        discrepancy, units = drop.type_test(fitted, args.type_test)
    else:
        discrepancy, units = None, []
    for out in (args.plot, args.csv):
        if out and not Path(out).resolve().parent.is_dir():
            raise UsageError(f"{out}: folder {Path(out).resolve().parent} does not exist")
    t = measured.t if measured is not None else None
    pred = drop.predict_drop(fitted, landing, t, discrepancy)
    for line in _drop_warnings(fitted, discrepancy):
        print(line)
    print(f"drop test: {landing.describe()}; model {fitted.model.name} from {fitted.source} "
          f"({', '.join(fitted.estimated)} estimated, {'residual-based' if fitted.residual_based else 'noise'} "
          f"covariance)")
    for u in units:
        stroke = f", stroke {100 * u.stroke_error:+.2f} %" if u.stroke_error is not None else ""
        print(f"  type-test unit {u.source}: measured peak force {100 * u.force_error:+.2f} %{stroke} "
              f"against its fit's prediction")
    for name, pk, scale, unit, d in (("peak force", pred.peak_force, 1e-3, "kN",
                                      discrepancy.force if discrepancy else None),
                                     ("peak stroke", pred.peak_stroke, 1e3, "mm",
                                      discrepancy.stroke if discrepancy else None)):
        parts = f"fit σ {pk.fit_std * scale:.3g} {unit}"
        if d is not None:
            parts += f", discrepancy {pk.discrepancy_std * scale:.3g} {unit} ({100 * d.relative:.3g} %, {d.source})"
        print(f"{name:12s} {notation.plus_minus(pk.value * scale, pk.std * scale, unit)}   ({parts})")
    if measured is not None:
        _drop_against(pred, measured)
    if args.csv:
        cols = {"time_s": pred.t, "force_N": pred.force_N, "force_sigma_N": pred.force_std,
                "stroke_mm": pred.stroke_m * 1e3, "stroke_sigma_mm": pred.stroke_std * 1e3,
                "pressure_bar": pred.pressure_Pa * 1e-5, "pressure_sigma_bar": pred.pressure_std * 1e-5}
        if pred.temperature_K is not None:
            cols["gas_temperature_C"] = pred.temperature_K - 273.15
        atomic_write_bytes(Path(args.csv), csv_bytes(cols))
        print(f"wrote {args.csv} ({len(pred.t)} samples; *_sigma: one σ, fit and discrepancy)")
    if args.plot:
        from identify.figures import drop_figure

        title = (f"drop test {landing.describe()}: model {fitted.model.name}, peak force "
                 f"{notation.plus_minus(pred.peak_force.value / 1e3, pred.peak_force.std / 1e3, 'kN')}"
                 + ("" if discrepancy else "\n(no model discrepancy given: the band is the fit's σ alone)"))
        print(f"figure {drop_figure(pred, measured, title, Path(args.plot))}")
    return EXIT_OK


def _drop_warnings(fitted, discrepancy) -> list[str]:
    """What the σ printed does not cover, said before the figures."""
    from identify.drop import LANDING_PARAMETERS

    lines = []
    held = fitted.held_at_prior([p for p in LANDING_PARAMETERS if p in fitted.model.parameter_names])
    if held:
        what = ", ".join(f"{p} ({LANDING_PARAMETERS[p]})" for p in held)
        lines.append(f"warning: this fit held {what} at the prior: a landing's force depends on "
                     f"{'it' if len(held) == 1 else 'them'} and the error there is in no σ (a plan from rig design "
                     f"--predict drop fits them)")
    if not fitted.converged:
        lines.append(f"warning: {fitted.source}: the fit did not converge; the prediction is of its last iterate")
    if discrepancy is None:
        lines.append("note: no model discrepancy given (--discrepancy REL or --type-test DIR…): σ is the fit's "
                     "alone and covers no model error")
    return lines


def _drop_against(pred, measured) -> None:
    """The measured drop's peaks beside the prediction, in σ of the prediction."""
    from identify.drop import peak

    rows = [("force", pred.peak_force, measured.force_N, 1e-3, "kN", pred.force_N)]
    if measured.stroke_m is not None:
        rows.append(("stroke", pred.peak_stroke, measured.stroke_m, 1e3, "mm", pred.stroke_m))
    for name, pk, series, scale, unit, history in rows:
        m = peak(series)
        err = pk.value - m
        within = "within" if abs(err) <= 2 * pk.std else "OUTSIDE"
        rms = float(np.sqrt(np.mean((history - series) ** 2)))
        print(f"measured peak {name} {m * scale:.4g} {unit} ({measured.source}): predicted "
              f"{100 * err / m:+.2f} % ({err / pk.std:+.2g} σ, {within} 2σ); {name} history RMS error "
              f"{rms * scale:.3g} {unit}" if pk.std > 0 else
              f"measured peak {name} {m * scale:.4g} {unit} ({measured.source}): predicted {100 * err / m:+.2f} %")


def run_friction(args: argparse.Namespace) -> int:
    from identify.folding import fold
    from identify.friction import extract

    columns = ("stroke_mm", "force_N", "pressure_bar")
    labels = _chosen_labels(args.dataset, args.experiments)
    ds = read_dataset(args.dataset, columns, labels)
    records = [fold(e.label, e.time_s, {c: e.column(c) for c in columns}, e.frequency_hz, args.n, e.sample_rate_hz)
               for e in ds.select(labels)]
    result = extract(records)
    print(result.table())
    atomic_write_bytes(Path(args.output), (json.dumps(result.to_document(), indent=2) + "\n").encode())
    if args.figure:
        from identify.figures import friction_figure

        print(f"figure {friction_figure(result, Path(args.figure))}")
    return EXIT_OK


def run_compare(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    console = Console(stderr=True, soft_wrap=True)   # log lines unbroken when stderr is a file
    labels = _chosen_labels(args.dataset, args.experiments)
    column = "stroke_mm"
    fits: dict[str, FitResult] = {}
    for name, params_path, estimate in (("1dof", args.params_1dof, args.estimate_1dof),
                                        ("2dof", args.params_2dof, args.estimate_2dof)):
        model = load_model(name)
        ds = read_dataset(args.dataset, model_columns(model, [column]), labels)
        console.print(f"fitting {estimate} of {name} on {len(labels)} experiments (output {column})", highlight=False)
        try:
            fits[name] = fit_experiments(model, ds.select(labels), _load_params(model, params_path),
                                         _csv_list(estimate) or [], n=args.n, scheme=args.scheme, outputs=[column])
        except EstimationError as exc:
            console.print(f"[red]{name} fit failed:[/red] {exc}", highlight=False)
            return EXIT_NOT_CONVERGED
    table = Table(title=f"model comparison: {column} residual mean ± 2σ per experiment (mm)")
    for col in ("experiment", "f [Hz]", "1-dof", "2-dof"):
        table.add_column(col, justify="right" if col != "experiment" else "left")
    rows, rms = [], {}
    for e1, e2 in zip(fits["1dof"].experiments, fits["2dof"].experiments, strict=True):
        (m1, s1), (m2, s2) = e1.stats(column), e2.stats(column)
        table.add_row(e1.label, f"{e1.frequency_hz:g}", f"{m1:+.4f} ± {2 * s1:.4f}", f"{m2:+.4f} ± {2 * s2:.4f}")
        rows.append({"label": e1.label, "frequency_Hz": e1.frequency_hz, "1dof": {"mean": m1, "std": s1},
                     "2dof": {"mean": m2, "std": s2}})
    for name, fit in fits.items():
        rms[name] = float(np.sqrt(np.mean(np.concatenate([e.residual(column) for e in fit.experiments]) ** 2)))
    ratio = rms["1dof"] / rms["2dof"]
    _print_table(table)
    for name, fit in fits.items():
        if not fit.converged:
            print(f"warning: the {name} fit did not converge ({fit.message}); its residuals are not its best")
        for w in fit.warnings:
            print(f"warning ({name}): {w}")
    print(f"overall {column} residual RMS: 1-dof {rms['1dof']:.4g} mm, 2-dof {rms['2dof']:.4g} mm, "
          f"ratio 1-dof/2-dof {ratio:.3g}")
    if args.output:
        doc = {"column": column, "experiments": rows, "rms": rms, "ratio_1dof_2dof": ratio,
               "fits": {k: v.to_document() for k, v in fits.items()}}
        atomic_write_bytes(Path(args.output), (json.dumps(doc, indent=2) + "\n").encode())
    return EXIT_OK if all(f.converged for f in fits.values()) else EXIT_NOT_CONVERGED


def run_report(args: argparse.Namespace) -> int:
    try:
        doc = json.loads(Path(args.result).read_text())
    except FileNotFoundError:
        raise UsageError(f"{args.result}: file not found") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"{args.result}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(doc, dict) or "parameters" not in doc:
        raise UsageError(f"{args.result}: not a RESULT.json (no 'parameters')")
    lines = [f"model {doc.get('model')}  converged {doc.get('converged')}  iterations {doc.get('iterations')}"
             + ("  (interrupted: the last iterate)" if doc.get("interrupted") else "")]
    for name, p in doc["parameters"].items():
        if p.get("estimated"):
            unit = p.get("unit", "") if p.get("unit") != "-" else ""
            rel = f" ({100 * p['std'] / abs(p['value']):.2g} %)" if p.get("std") and p["value"] else ""
            residual = (f"   [{notation.plus_minus(p['value'], p['std_residual'])} *]"
                        if p.get("std_residual") is not None else "")
            bound = f"   [AT {p['at_bound'].upper()}]" if p.get("at_bound") else ""
            lines.append(f"  {name:8s} {notation.plus_minus(p['value'], p.get('std'), unit)}{rel}" + residual + bound)
    if any(p.get("std_residual") is not None for p in doc["parameters"].values()):
        lines.append("  * residual-based σ (includes the model error; quote it): the residuals exceed the noise")
    for label, e in doc.get("experiments", {}).items():
        channels = e.get("channels") or {e.get("channel", ""): e}
        lines.append(f"  {label:12s} residual " + "   ".join(
            f"{o} {c['residual_mean']:+.4g} +/- {2 * c['residual_std']:.4g}" for o, c in channels.items())
            + " (2 sigma)")
    for w in doc.get("warnings", []):
        lines.append(f"  warning: {w}")
    print("\n".join(lines))
    return EXIT_OK


def run_batch(args: argparse.Namespace) -> int:
    from rich.console import Console

    from identify import batch, sinks

    console = Console(stderr=True, soft_wrap=True)   # log lines unbroken when stderr is a file
    named = list(args.sessions) + (batch.read_session_list(args.list) if args.list else [])
    sessions = batch.check_sessions(named)
    settings = batch.FitSettings.resolve(args.model, args.params, _csv_list(args.estimate) or [], n=args.n,
                                         scheme=args.scheme, max_iterations=args.max_iterations,
                                         oversample=args.oversample)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: exists and is not a folder")
    # Opened before the cluster: a missing database or a wrong URL costs no fit.
    sink = sinks.open_sink("db", args.db) if args.db is not None else None
    try:
        return _run_batch(args, console, sessions, settings, out, sink)
    finally:
        if sink is not None:
            sink.close()


def _run_batch(args: argparse.Namespace, console: Console, sessions: list[Path], settings: batch.FitSettings,
               out: Path, sink: sinks.ResultSink | None) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from identify import batch

    counts = dict.fromkeys(BatchState, 0)
    try:
        with batch.connect(args.scheduler, args.workers) as client:
            try:  # only now: input refused before this point leaves no folder behind
                out.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise UsageError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") from None
            workers = len(client.scheduler_info().get("workers", {}))
            link = batch.dashboard_link(client)
            console.print(f"identifying {', '.join(settings.estimate)} of model {settings.model_name} in "
                          f"{len(sessions)} session{'s' if len(sessions) != 1 else ''} on {workers} "
                          f"worker{'s' if workers != 1 else ''}"
                          + (f"; dashboard {link}" if link else "")
                          + (f"; results to {sink.name} too" if sink else ""), highlight=False)
            columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
            with Progress(*columns, console=console) as progress:
                bar = progress.add_task("sessions", total=len(sessions))

                def advance(outcome: batch.SessionOutcome) -> None:
                    counts[outcome.state] += 1
                    progress.update(bar, advance=1, description=", ".join(f"{v} {k}" for k, v in counts.items()))

                rows = batch.run_batch(client, sessions, settings, out, advance, sink)
    except KeyboardInterrupt:
        console.print(f"interrupted with {sum(counts.values())} of {len(sessions)} sessions reported; every result "
                      f"written is kept in {out}, and the same command goes on from there", highlight=False)
        return EXIT_INTERRUPTED
    _batch_table(rows, settings.estimate)
    print(f"{len(rows)} sessions: " + ", ".join(f"{v} {k}" for k, v in counts.items())
          + f"; results in {out}, summary {out / batch.SUMMARY}")
    undelivered = [(r.session, r.delivery.text) for r in rows
                   if r.delivery and r.delivery.state is DeliveryState.FAILED]
    if sink is not None:
        for line in sink.summary():
            print(line)
        for session, reason in undelivered:  # each on its own line, whole, as a failed fit's
            print(f"{session}: not written to {sink.name}: {reason}")
    return EXIT_NOT_CONVERGED if counts[BatchState.FAILED] or undelivered else EXIT_OK


def _batch_table(rows: list[batch.SessionOutcome], estimate: tuple[str, ...]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()  # stdout: the table is the command's result, progress went to stderr
    shown = rows if len(rows) <= TABLE_ROWS else [r for r in rows if r.failed]
    if shown:
        converged = {BatchState.OK: "yes", BatchState.SKIPPED: "earlier", BatchState.FAILED: "no"}
        caption = ("value(std): the std in units of the value's last digits, summary.csv has both in full"
                   + ("; *: residual-based std, the residuals exceed the measurement noise (model error)"
                      if any(r.residual_std for r in shown) else "")
                   + "; fit: seconds; conv.: converged (earlier: done before, skipped)")
        table = Table(title="batch identification" if shown is rows else "failed sessions", box=None,
                      header_style="bold underline", padding=(0, 1), collapse_padding=True, pad_edge=False,
                      caption=caption)
        table.add_column("session", no_wrap=True, min_width=8)  # identifiers: whole, or cut with an ellipsis
        table.add_column("serial", no_wrap=True, min_width=6)
        table.add_column("conv.", no_wrap=True)
        for col in estimate:
            table.add_column(col, justify="right", overflow="fold")
        table.add_column("fit", justify="right", no_wrap=True, min_width=4)
        for r in shown:
            mark = "*" if r.residual_std else ""
            cells = [notation.concise(r.values[p], r.stds.get(p)) + mark if p in r.values else "" for p in estimate]
            table.add_row(r.session, r.serial, converged[r.state], *cells,
                          "" if r.fit_s is None else f"{r.fit_s:.2f}")
        _print_table(table)
    for r in rows:
        if r.failed:  # the reason names a file and line: too long for a cell, whole on its own line
            console.print(f"{r.session}: {r.status}", highlight=False, soft_wrap=True)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m identify", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def model_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--model", default="2dof", help="1dof, 2dof, duffing, bouc-wen or path/file.py:ClassName")
        p.add_argument("--params", help="START.json / RESULT.json / flat {name: value} (default: nominal)")
        p.add_argument("--scheme", choices=SCHEMES,
                       help="grid differentiation scheme (default: the --params RESULT.json fit's; else spectral for "
                            "broadband records that bdf2 cannot resolve on its grid, bdf2 otherwise)")
        p.add_argument("--n", type=int, help=f"grid points per period (default: the --params RESULT.json fit's; else "
                                             f"{DEFAULT_POINTS} for bdf2, for spectral chosen from the data's "
                                             f"highest harmonic with signal)")
        p.add_argument("--oversample", type=int, help="solve the model on n x this many points (default: 4 for "
                                                      "spectral grids of models with kinks such as |x|, else 1)")

    fit = sub.add_parser("fit", help="estimate parameters from periodic experiments")
    fit.add_argument("dataset", help="dataset folder (dataset.json + CSVs)")
    model_args(fit)
    fit.add_argument("--estimate", help="comma-separated parameters (names or aliases); default: those the "
                                        "session's plan was designed for (dataset.json's purpose)")
    fit.add_argument("--output", required=True, help="RESULT.json to write")
    fit.add_argument("--experiments", help="comma-separated labels or letters (default: all periodic)")
    fit.add_argument("--outputs", help="fitted output columns (default: the model's, e.g. stroke_mm,pressure_bar)")
    fit.add_argument("--per-experiment", action="store_true", help="fit each experiment on its own, print a table")
    fit.add_argument("--max-iterations", type=int, default=40,
                     help="stop after this many iterations (exit 1, RESULT.json holds the last iterate)")
    fit.add_argument("--time-limit", type=float, metavar="SECONDS",
                     help="start no iteration after this long (exit 1, RESULT.json holds the last iterate)")
    fit.add_argument("--report", help="also write the text report here")
    fit.add_argument("--figures", help="folder for PNG figures (measured vs predicted, residual bands; multisine "
                                                    "records: frequency response at the excited lines)")
    fit.add_argument("--quiet", action="store_true", help="no iteration progress")
    fit.add_argument("--capture", choices=("auto", "steady", "transient"), default="auto",
                     help="fit records as steady states folded onto a period, or as transients sample by sample "
                          "from a fitted initial state (default auto: transient where dataset.json says "
                          "capture = \"transient\")")
    fit.add_argument("--transient-oversample", type=int, default=1, metavar="K",
                     help="solve a transient record's model on K points per sample step (default 1; more for "
                          "content near the sampling rate, e.g. 8 for Silverbox)")
    fit.add_argument("--friction", help="FRICTION.json: fixed per-experiment theta8, theta9, theta10")
    fit.add_argument("--stability", action="store_true",
                     help="Floquet multipliers of each periodic solution (warns about unstable orbits)")
    fit.set_defaults(func=run_fit)

    pred = sub.add_parser("predict", help="model prediction on an experiment's time base")
    pred.add_argument("dataset")
    model_args(pred)
    pred.add_argument("--experiment", required=True, help="label (or letter) of the experiment")
    pred.add_argument("--output", required=True, help="CSV to write")
    pred.set_defaults(func=run_predict)

    dr = sub.add_parser("drop", help="virtual drop test of a fit: a mass landing on the damper, peaks with σ")
    dr.add_argument("result", help="RESULT.json of a fit of a thermo-mechanical damper model (2dof)")
    dr.add_argument("--model", help="the model, where RESULT.json names a user model (path/file.py:ClassName)")
    dr.add_argument("--mass", type=float, metavar="KG", help="dropped mass (default 350 kg, the paper's)")
    dr.add_argument("--velocity", type=float, metavar="M_S",
                    help="speed at contact with the extended damper (default 0.5 m/s, the paper's landing)")
    dr.add_argument("--duration", type=float, metavar="S", help="record length (default 2.5 s)")
    delta = dr.add_mutually_exclusive_group()
    delta.add_argument("--discrepancy", type=float, metavar="REL",
                       help="model discrepancy σ_δ relative to each quantity (0.026 = 2.6 %%)")
    delta.add_argument("--type-test", nargs="+", metavar="DIR",
                       help="reference units (dataset folders with their drop record, and their RESULT.json or "
                            "shaker data to fit as RESULT.json was): σ_δ from their peak errors")
    dr.add_argument("--measured", metavar="DROP",
                    help="a measured drop to compare with: a dataset folder with a drop record (its mass and "
                         "velocity are used) or a CSV (time_s, force_N[, stroke_mm, pressure_bar])")
    dr.add_argument("--plot", metavar="PNG", help="figure: force, stroke, pressure with the 2σ band")
    dr.add_argument("--csv", metavar="OUT", help="force, stroke and pressure histories with their σ")
    dr.set_defaults(func=run_drop)

    fr = sub.add_parser("friction", help="theta8-theta10 from the force jumps at velocity reversals (paper Fig. 7)")
    fr.add_argument("dataset")
    fr.add_argument("--output", required=True, help="FRICTION.json to write (usable as fit --friction)")
    fr.add_argument("--experiments", help="comma-separated labels or letters (default: all periodic)")
    fr.add_argument("--n", type=int, default=800, help="grid points per period for folding")
    fr.add_argument("--figure", help="PNG of friction amplitude against pressure with the fitted line")
    fr.set_defaults(func=run_friction)

    cmp_ = sub.add_parser("compare", help="1-dof against 2-dof on one dataset: residuals per experiment")
    cmp_.add_argument("dataset")
    cmp_.add_argument("--params-1dof", help="start values of the 1-dof fit (default: nominal)")
    cmp_.add_argument("--params-2dof", help="start values of the 2-dof fit (default: nominal)")
    cmp_.add_argument("--estimate-1dof", default=",".join(DEFAULT_ESTIMATE["1dof"]),
                      help="(theta4 and theta5 enter the 1-dof gas force as a product: estimate one of them)")
    cmp_.add_argument("--estimate-2dof", default=",".join(DEFAULT_ESTIMATE["2dof"]))
    cmp_.add_argument("--experiments", help="comma-separated labels or letters (default: all periodic)")
    cmp_.add_argument("--scheme", choices=SCHEMES, default="bdf2")
    cmp_.add_argument("--n", type=int, default=800)
    cmp_.add_argument("--output", help="COMPARE.json to write")
    cmp_.set_defaults(func=run_compare)

    bat = sub.add_parser("batch", help="identify many sessions on a Dask cluster, one task per session (resumable)")
    bat.add_argument("sessions", nargs="*", help="session folders (dataset.json + CSVs)")
    bat.add_argument("--list", help="file of session folders, one per line (# comments; relative to the file)")
    model_args(bat)
    bat.add_argument("--estimate", required=True, help="comma-separated parameters (names or aliases)")
    bat.add_argument("--out", required=True, help="RESULTS_DIR: <session folder name>.json each, summary.csv")
    bat.add_argument("--max-iterations", type=int, default=40)
    where = bat.add_mutually_exclusive_group()
    where.add_argument("--scheduler", help="address of a running Dask scheduler, tcp://HOST:8786")
    where.add_argument("--workers", type=int, help="worker processes of a local cluster (default: one per core)")
    bat.add_argument("--db", metavar="URL",
                     help="an existing QC records database (sqlite:///FILE or postgresql://USER@HOST:PORT/DB): "
                          "each converged session whose data has a QC record is re-judged with this fit, under "
                          "the spec of its latest record when that spec's model and estimated set are the "
                          "batch's; a new record refers to the first, once per result (a rerun adds none)")
    bat.set_defaults(func=run_batch)

    rep = sub.add_parser("report", help="print a RESULT.json as a report")
    rep.add_argument("result")
    rep.set_defaults(func=run_report)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ComputationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    except BrokenPipeError:
        # The reader went away (`identify report R.json | head`): what it wanted was printed.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # no second error at exit's flush
        return EXIT_OK
