"""Fit results: RESULT.json (the contract other tools rely on) and a readable report."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from identify import notation
from identify.files import atomic_write_bytes
from identify.fit_warnings import FitWarning, WarningCode
from identify.model import CompiledModel
from identify.parameters import Parameters

if TYPE_CHECKING:
    import pandas as pd

RELATIVE_STD_WARNING = 0.10  # a parameter known to worse than 10 % is flagged
UNDETERMINED = 100.0  # a σ this many times the value: a flat direction, printed without digits that mean nothing
# Monte-Carlo calibration of the reported σ, written by benchmarks/bench_sigma.py --record.
CALIBRATION_FILE = Path(__file__).with_name("calibration.json")
CONDITION_WARNING = 1e6  # of the weighted, parameter-scaled sensitivity matrix
CORRELATION_REPORT = 0.5


def _parameter_entry(p: Any, estimated: bool, std: float | None, initial: float | None,
                     prior_std: float | None) -> dict[str, Any]:
    """One parameter of RESULT.json, the same fields whether the fit had a result or not."""
    entry: dict[str, Any] = {"value": p.value, "std": std, "estimated": estimated, "unit": p.unit, "alias": p.alias}
    for key, bound in (("min", p.minimum), ("max", p.maximum)):
        if bound is not None:
            entry[key] = bound
    if initial is not None:
        entry["initial"] = initial
    if prior_std:                      # what a restart needs to take the same steps
        entry["prior_std"] = prior_std
    return entry


def failed_document(model: CompiledModel, params: Parameters, message: str) -> dict[str, Any]:
    """RESULT.json of a fit that has no result (it failed, or was interrupted before its
    first iterate): the start values, ``converged`` false, the fields of
    :meth:`FitResult.to_document` where there is something to say."""
    return {"model": model.name, "converged": False, "iterations": 0, "message": message,
            # it started, and stopped, at the start values
            "parameters": {p.name: _parameter_entry(p, p.vary, None, p.value, p.prior_std if p.vary else None)
                           for p in params},
            "correlation": {}, "channels": {}, "experiments": {}}


def write_document(path: str | Path, doc: dict[str, Any]) -> None:
    """RESULT.json on disk, atomically: the one writer of the file."""
    atomic_write_bytes(Path(path), (json.dumps(doc, indent=2) + "\n").encode())


@dataclass(frozen=True)
class ParameterEstimate:
    name: str
    alias: str
    unit: str
    value: float
    std: float
    estimated: bool


@dataclass
class ExperimentFit:
    """Measured and predicted grid values of one experiment, in column units."""

    label: str
    frequency_hz: float
    measured: dict[str, np.ndarray]
    predicted: dict[str, np.ndarray]
    newton_iterations: int
    floquet: np.ndarray | None = None  # multipliers, largest magnitude first (when asked for)
    start: str = ""  # where the first periodic solve started (identify.start: static, transient, ...)
    inputs: dict[str, np.ndarray] = field(default_factory=dict)  # the model's inputs on the grid, column units
    # "steady": folded onto one period (measured/predicted on its grid); "transient": fitted
    # sample by sample from its fitted initial state (measured/predicted per sample).
    capture: str = "steady"

    def residual(self, column: str) -> np.ndarray:
        return self.measured[column] - self.predicted[column]

    def stats(self, column: str) -> tuple[float, float]:
        r = self.residual(column)
        return float(np.mean(r)), float(np.std(r, ddof=1))


@dataclass
class FitResult:
    """Everything a fit found; ``to_document`` is RESULT.json, ``fit_report`` the text."""

    model: str
    params: Parameters
    estimated: list[str]
    std: dict[str, float]
    correlation: np.ndarray
    covariance: np.ndarray
    outputs: list[str]
    channel_variances: dict[str, float]
    experiments: list[ExperimentFit]
    converged: bool
    iterations: int
    message: str
    objective_history: list[float]
    elapsed_s: float
    n_grid: int
    scheme: str
    singular_values: np.ndarray
    findings: list[FitWarning] = field(default_factory=list)  # the warnings as data; ``warnings`` renders them
    start: dict[str, float] = field(default_factory=dict)
    # Residual-based σ, given where the residuals exceed the measurement noise (model error).
    std_residual: dict[str, float] | None = None
    priors: dict[str, float | None] = field(default_factory=dict)  # as given (None: 50 % of the size)
    oversample: int = 1  # the model solved on n·oversample points per period
    covariance_residual: np.ndarray | None = None  # beside std_residual
    # Its independent units: what they are (experiments, frequency lines), their number, their effective number.
    residual_units: tuple[str, float, float] | None = None
    interrupted: bool = False  # stopped by Ctrl-C: the last iterate, not converged
    units: dict[str, str] = field(default_factory=dict)  # of the input and output columns

    @classmethod
    def build(cls, *, model: CompiledModel, params: Parameters, estimated: list[str], std: np.ndarray,
              correlation: np.ndarray, covariance: np.ndarray, outputs: list[str],
              experiments: list[ExperimentFit], converged: bool, iterations: int, message: str,
              objective_history: list[float], elapsed_s: float, n_grid: int, scheme: str,
              singular_values: np.ndarray, sensitivity_matrix: np.ndarray,
              notes: Sequence[FitWarning] = (), std_residual: np.ndarray | None = None,
              covariance_residual: np.ndarray | None = None,
              residual_units: tuple[str, float, float] | None = None) -> FitResult:
        n_par = len(estimated)
        variances = {}
        for o in outputs:
            r = np.concatenate([e.residual(o) for e in experiments])
            # Bias correction: the estimated parameters' degrees of freedom, shared by the channels.
            variances[o] = float(np.sum(r**2) / max(r.size - n_par / len(outputs), 1.0))
        result = cls(
            model=model.name, params=params, estimated=estimated,
            std={nm: float(s) for nm, s in zip(estimated, std, strict=True)}, correlation=correlation,
            covariance=covariance, outputs=outputs,
            channel_variances=variances, experiments=experiments, converged=converged, iterations=iterations,
            message=message, objective_history=objective_history, elapsed_s=elapsed_s, n_grid=n_grid,
            scheme=scheme, singular_values=singular_values,
            std_residual=None if std_residual is None else
            {nm: float(s) for nm, s in zip(estimated, std_residual, strict=True)},
            covariance_residual=covariance_residual, residual_units=residual_units,
        )
        result.findings = result._bound_warnings() + result._identifiability_warnings(sensitivity_matrix) + list(notes)
        return result

    @property
    def warnings(self) -> list[str]:
        """The warnings' sentences, rendered from :attr:`findings`."""
        return [str(w) for w in self.findings]

    def _bound_warnings(self) -> list[FitWarning]:
        """Estimates the bounds stopped: the data pull them beyond, where the model's
        declaration says no physical value lies (negative mass or damping), or beyond the
        START file's range."""
        out = []
        for nm in self.estimated:
            p = self.params[nm]
            side = p.at_bound()
            if side is None:
                continue
            limit = p.minimum if side == "minimum" else p.maximum
            physical = limit == p.physical[0 if side == "minimum" else 1]
            out.append(FitWarning(WarningCode.AT_BOUND, {"name": nm, "alias": p.alias, "side": side, "limit": limit,
                                                          "unit": p.unit, "physical": physical}))
        return out

    def _identifiability_warnings(self, Sw: np.ndarray) -> list[FitWarning]:
        out = []
        for nm in self.estimated:
            value = self.params[nm].value
            s = self.honest_std(nm)
            if value == 0 or s / abs(value) > UNDETERMINED:
                out.append(FitWarning(WarningCode.UNDETERMINED, {"name": nm, "alias": self.params[nm].alias,
                                                                 "std": float(s), "factor": UNDETERMINED}))
            elif s / abs(value) > RELATIVE_STD_WARNING:
                out.append(FitWarning(WarningCode.POORLY_IDENTIFIABLE, {
                    "name": nm, "alias": self.params[nm].alias, "percent": float(100 * s / abs(value)),
                    "residual": self.std_residual is not None}))
        if Sw.size and len(self.singular_values) > 1:
            sv = self.singular_values
            cond = sv[0] / max(sv[-1], 1e-300)
            if cond > CONDITION_WARNING:
                _, _, vt = np.linalg.svd(Sw, full_matrices=False)
                weak = np.abs(vt[-1])
                names = [self.estimated[i] for i in np.argsort(weak)[::-1] if weak[i] > 0.3]
                out.append(FitWarning(WarningCode.ILL_CONDITIONED, {"condition": float(cond), "names": names}))
        return out

    # ----------------------------------------------------------------------------------
    def value(self, name: str) -> float:
        return self.params[name].value

    @property
    def parameters(self) -> dict[str, ParameterEstimate]:
        """Every parameter by name: value, std (NaN where it was held fixed), unit."""
        return {p.name: ParameterEstimate(p.name, p.alias, p.unit, p.value, self.std.get(p.name, math.nan),
                                          p.name in self.estimated) for p in self.params}

    def to_frame(self) -> pd.DataFrame:
        """The parameters as a table (index: name), for notebooks and scripts."""
        import pandas as pd  # the fit itself needs no pandas

        rows = [vars(p) for p in self.parameters.values()]
        frame = pd.DataFrame(rows).set_index("name")
        frame["relative_std"] = frame["std"] / frame["value"].abs()
        return frame

    def report(self) -> str:
        """The readable report (as ``identify report`` prints it)."""
        return self.fit_report()

    def relative_std(self, name: str) -> float:
        return self.std[name] / abs(self.value(name))

    def honest_std(self, name: str) -> float:
        """The σ to quote: the residual-based one where model error was found, else the noise σ."""
        return self.std_residual[name] if self.std_residual is not None else self.std[name]

    def honest_covariance(self) -> np.ndarray:
        """The covariance to propagate (QC guard bands): the residual-based one where model
        error was found, else the noise covariance."""
        return self.covariance_residual if self.covariance_residual is not None else self.covariance

    def to_document(self) -> dict[str, Any]:
        """RESULT.json (contract: model, converged, iterations, parameters, correlation,
        channels, experiments; extended with report details)."""
        params = {}
        for p in self.params:
            est = p.name in self.estimated
            params[p.name] = _parameter_entry(p, est, self.std[p.name] if est else None, self.start.get(p.name),
                                              self.priors.get(p.name) if est else None)
            if est and self.std_residual is not None:
                params[p.name]["std_residual"] = self.std_residual[p.name]
            if est and p.at_bound():
                params[p.name]["at_bound"] = p.at_bound()
        corr = {a: {b: _finite(self.correlation[i, j]) for j, b in enumerate(self.estimated)}
                for i, a in enumerate(self.estimated)}
        experiments = {}
        primary = self.outputs[0]
        for e in self.experiments:
            mean, std = e.stats(primary)
            experiments[e.label] = {
                "residual_mean": mean, "residual_std": std, "channel": primary,
                "frequency_Hz": e.frequency_hz, "newton_iterations": e.newton_iterations,
                "channels": {o: dict(zip(("residual_mean", "residual_std"), e.stats(o), strict=True))
                             for o in self.outputs},
            }
            if e.start:
                experiments[e.label]["start"] = e.start
            if e.capture != "steady":
                experiments[e.label]["capture"] = e.capture
            if e.floquet is not None:
                experiments[e.label]["floquet_max_multiplier"] = float(np.abs(e.floquet[0]))
                experiments[e.label]["stable"] = bool(np.abs(e.floquet[0]) < 1.0)
        return {
            "model": self.model,
            "converged": self.converged,
            "interrupted": self.interrupted,
            "iterations": self.iterations,
            "message": self.message,
            "parameters": params,
            "correlation": corr,
            # The matrices themselves, in the order of "estimated": whoever propagates the
            # fit to another quantity (QC's characteristics, from a stored batch result)
            # needs the residual-based one's off-diagonal terms, which std and the noise
            # correlation do not give.
            "covariance": {"estimated": list(self.estimated), "noise": _matrix(self.covariance),
                           "residual": None if self.covariance_residual is None else
                           _matrix(self.covariance_residual)},
            "channels": {o: {"variance": self.channel_variances[o]} for o in self.outputs},
            "experiments": experiments,
            "objective": self.objective_history[-1] if self.objective_history else None,
            "n": self.n_grid,
            "scheme": self.scheme,
            "oversample": self.oversample,
            "elapsed_s": self.elapsed_s,
            "warnings": self.warnings,
            "findings": [w.to_json() for w in self.findings],  # the same, as codes and numbers
            **({"std_residual_units": dict(zip(("units", "number", "effective_number"), self.residual_units,
                                               strict=True))}
               if self.std_residual is not None and self.residual_units else {}),
        }

    def write_json(self, path: str | Path) -> None:
        write_document(path, self.to_document())

    # ----------------------------------------------------------------------------------
    def fit_report(self, correlation_threshold: float = CORRELATION_REPORT) -> str:
        """A readable report in the spirit of lmfit's ``fit_report``."""
        n_points = sum(len(e.measured[self.outputs[0]]) for e in self.experiments) * len(self.outputs)
        lines = [
            "[[Fit statistics]]",
            f"    model              = {self.model}",
            f"    scheme, n          = {self.scheme}, {self.n_grid} points per period"
            + (f" (model on {self.n_grid * self.oversample})" if self.oversample > 1 else ""),
            f"    experiments        = {len(self.experiments)} ({', '.join(e.label for e in self.experiments)})",
            *([f"    fitted as transient = {', '.join(transient)} (sample by sample from a fitted initial state)"]
              if (transient := [e.label for e in self.experiments if e.capture == "transient"]) else []),
            f"    fitted outputs     = {', '.join(self.outputs)}",
            f"    data points        = {n_points}",
            f"    variables          = {len(self.estimated)}",
            f"    iterations         = {self.iterations}",
            f"    converged          = {self.converged}  ({self.message})",
            f"    objective (Σ N log v) = {self.objective_history[-1]:.6g}" if self.objective_history else "",
            f"    time               = {self.elapsed_s:.3f} s",
            "[[Variables]]",
        ]
        for p in self.params:
            if p.name in self.estimated:
                s = self.std[p.name]
                unit = notation.unit_text(p.unit) if p.unit != "-" else ""
                init = self.start.get(p.name)
                init_s = f"(init = {init:.6g})" if init is not None else ""
                prior = self.priors.get(p.name)
                prior_s = "prior std 50 % of its size" if not prior else f"prior std {prior:.3g} {unit}".rstrip()
                residual = ""
                if self.std_residual is not None:
                    sr = self.std_residual[p.name]
                    residual = f"   [{_with_std(p.value, sr)}{_relative(p.value, sr)} *]"
                side = p.at_bound()
                bound = f"   [AT {side.upper()}, see warnings]" if side else ""
                lines.append(f"    {p.name:8s} {p.alias:18s} {_with_std(p.value, s, unit)}"
                             f"{_relative(p.value, s)} {init_s}, {prior_s}" + residual + bound)
        if self.std_residual is not None:
            E = float(len(self.experiments))
            what, units, effective = self.residual_units or ("experiments", E, E)
            draw = ("each experiment's misfit" if what == "experiments" else
                    "the misfit at each excited frequency line of the records" if what.startswith("excited") else
                    "the misfit at each frequency line of the records")
            count = (f"{units:.0f} {what}" if units == effective else
                     f"{units:.0f} {what}, the misfit carried by an effective {effective:.2g} of them")
            lines.append(f"    * residual-based σ: the residuals exceed the measurement noise (see warnings), and "
                         f"the +/- before it covers the noise only: quote the one marked *.  It treats {draw} as "
                         f"one random draw ({count}), is itself uncertain by about "
                         f"±{100 / math.sqrt(2 * max(effective - len(self.estimated), 1)):.0f} %, "
                         f"and does not cover a bias the model error may cause")
        calibration = _calibration_line(self.model, [e.frequency_hz for e in self.experiments], self.estimated)
        if any(e.capture == "transient" for e in self.experiments):
            # That calibration is of periodic fits; the transient fit's σ has its own check.
            calibration = ("    σ of a transient fit: its Monte-Carlo check is benchmarks/bench_transient.py "
                           "(docs/identify.md)")
        if calibration:
            lines.append(calibration)
        fixed = [p for p in self.params if p.name not in self.estimated]
        if fixed:
            lines.append("    fixed: " + ", ".join(f"{p.name}={p.value:.6g}" for p in fixed))
        pairs = []
        for i in range(len(self.estimated)):
            for j in range(i + 1, len(self.estimated)):
                c = self.correlation[i, j]
                if np.isfinite(c) and abs(c) >= correlation_threshold:
                    pairs.append((abs(c), f"    C({self.estimated[i]}, {self.estimated[j]}) = {c:+.4f}"))
        lines.append(f"[[Correlations]] (|C| >= {correlation_threshold})")
        lines += [p for _, p in sorted(pairs, reverse=True)] or ["    none"]
        lines.append("[[Channels]]")
        for o in self.outputs:
            lines.append(f"    {o:18s} residual variance {self.channel_variances[o]:.4g}   "
                         f"(std {math.sqrt(self.channel_variances[o]):.4g})")
        lines.append(f"[[Experiments]] residual mean +/- 2 sigma per fitted output ({', '.join(self.outputs)})")
        for e in self.experiments:
            stability = "" if e.floquet is None else (
                f", Floquet |μ|max {np.abs(e.floquet[0]):.4g} ({'stable' if np.abs(e.floquet[0]) < 1 else 'UNSTABLE'})")
            started = f"first solve started {e.start}; " if e.start else ""
            residuals = "   ".join(f"{o} {mean:+.4g} +/- {2 * std:.4g}"
                                   for o, (mean, std) in ((o, e.stats(o)) for o in self.outputs))
            its = e.newton_iterations
            lines.append(f"    {e.label:12s} {e.frequency_hz:8.4g} Hz   {residuals}"
                         f"   ({started}last solve {its} Newton iteration{'s' if its != 1 else ''}{stability})")
        if self.warnings:
            lines.append("[[Warnings]]")
            lines += [f"    {w}" for w in self.warnings]
        return "\n".join(ln for ln in lines if ln != "")


def _with_std(value: float, std: float, unit: str = "") -> str:
    """value ± σ, or the value alone where σ dwarfs it (a flat direction: "(0.0 ± 2.8)×10¹⁶"
    carries no digit that means anything)."""
    if not value or std > UNDETERMINED * abs(value):
        return notation.plus_minus(value, None, unit)
    return notation.plus_minus(value, std, unit)


def _relative(value: float, std: float) -> str:
    if not value or std > UNDETERMINED * abs(value):
        return " (not determined, see warnings)"
    return f" ({100 * std / abs(value):.2g} %)"


def _calibration_line(model: str, frequencies_hz: Sequence[float], estimated: Sequence[str]) -> str | None:
    """What the Monte-Carlo calibration on record (CALIBRATION_FILE) says about σ, scoped
    to where it was validated: the model, the plan (its experiments' frequencies) and the
    parameters estimated it names.  A fit outside that scope is told "not validated"."""
    try:
        doc = json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))
        lo, hi = doc["spread_over_sigma_range"]
        seeds, calibrated, plan = int(doc["seeds"]), str(doc["model"]), str(doc["plan"])
        plan_hz, names = sorted(float(f) for f in doc["plan_frequencies_hz"]), [str(n) for n in doc["estimated"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    scope = (f"model {calibrated}, the {plan} plan ({len(plan_hz)} experiments), {', '.join(names)} estimated, "
             f"{seeds} seeds per case")
    same_plan = np.allclose(sorted(frequencies_hz), plan_hz) if len(frequencies_hz) == len(plan_hz) else False
    if calibrated == model and same_plan and sorted(estimated) == sorted(names):
        return (f"    σ validated by Monte-Carlo for {scope}: spread/σ {lo:.2f}–{hi:.2f} (benchmarks/bench_sigma.py, "
                f"docs/uncertainty.md)")
    differs = [what for what, same in (
        (f"model {model}", calibrated == model),
        (f"{len(frequencies_hz)} experiment{'s' if len(frequencies_hz) != 1 else ''} not the {plan} plan", same_plan),
        (f"{', '.join(estimated)} estimated", sorted(estimated) == sorted(names))) if not same]
    return (f"    σ not validated by Monte-Carlo for this fit ({'; '.join(differs)}): the calibration on record "
            f"covers {scope} only (docs/uncertainty.md)")


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _matrix(m: np.ndarray) -> list[list[float | None]]:
    """A matrix as JSON (a non-finite entry as null, as in the correlation)."""
    return [[_finite(x) for x in row] for row in np.asarray(m, dtype=float)]
