"""The virtual drop test: a fitted damper model landing a mass, with its uncertainty.

The paper's test of predictive power (Reitz et al.) is a landing: a mass touches the
extended damper at a sink speed, the damper takes it in a fifth of a second, five times
faster than the shaker ever moved it.  :func:`predict_drop` integrates the fitted
thermo-mechanical model for that landing (:func:`identify.transient.drop_test`) and
gives the force, stroke and pressure histories and their peaks with a standard
deviation of two parts:

* **the fit's**: the parameters' covariance of RESULT.json (the residual-based one
  where the fit found model error, else the noise one) propagated through the landing's
  sensitivities, forward differences of the integrated response;
* **the model discrepancy** σ_δ (:mod:`identify.discrepancy`): the part of the error no
  parameter σ covers, relative to the predicted quantity.  Given (``--discrepancy``), or
  estimated from a type test: reference units whose shaker data were fitted the same way
  and whose own drop was measured (:func:`type_test`); σ_δ is the RMS of their relative
  peak errors.

Var = J·C·Jᵀ + (σ_δ·y)², the model discrepancy in the sense of Kennedy & O'Hagan
(J. R. Stat. Soc. B 63, 2001).  One function for every caller: ``identify drop``, the
benchmarks, and later the simulator's drop rig and the QC report.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from identify.dataset import DatasetError, Experiment, load_csv, read_dataset, read_manifest
from identify.discrepancy import Discrepancy, from_errors
from identify.errors import InputError
from identify.model import CompiledModel, load_model
from identify.parameters import ParameterError, Parameters, load_document
from identify.transient import drop_test

if TYPE_CHECKING:
    from identify.result import FitResult

DROP_MASS_KG = 350.0        # the paper's drop-test mass
DROP_VELOCITY_M_S = 0.5     # at contact: the paper's landing reaches about 0.5 m/s
DROP_DURATION_S = 2.5       # the paper's drop-test record
SAMPLE_RATE_HZ = 1000.0     # of the predicted histories (a measured drop: its own samples)
RELATIVE_STEP = 1e-3        # forward differences of an integrated response: smaller steps meet its tolerance
THERMAL_UNIT = "K"          # the gas temperature's state: a landing heats the gas in a tenth of a second
HISTORIES = ("force_N", "stroke_mm", "pressure_bar")   # the dataset columns a drop rig records
# The parameters a landing's force at contact depends on beyond the shaker's usual three
# (θ4, θ6, θ16): held at their priors they left a −2 % bias on the plant's good units
# (benchmarks/bench_drop.py --goal), which no σ of the fit contains.
LANDING_PARAMETERS = {"theta3": "the orifice's damping", "theta5": "the gas charge", "theta8": "the seals' friction"}


class DropInputError(InputError):
    """A RESULT.json, type test or measured drop the virtual drop test cannot use."""


@dataclass(frozen=True)
class Landing:
    """The conditions of use (SI): the mass, its speed at contact with the extended damper,
    and how long the record runs."""

    mass_kg: float = DROP_MASS_KG
    velocity_m_s: float = DROP_VELOCITY_M_S
    duration_s: float = DROP_DURATION_S

    def __post_init__(self) -> None:
        for name, value in (("mass", self.mass_kg), ("duration", self.duration_s)):
            if not (math.isfinite(value) and value > 0):
                raise DropInputError(f"drop {name} {value:g}: must be a positive number")
        if not (math.isfinite(self.velocity_m_s) and self.velocity_m_s >= 0):
            raise DropInputError(f"drop velocity {self.velocity_m_s:g} m/s: must be zero or positive (a landing)")

    def times(self, rate_hz: float = SAMPLE_RATE_HZ) -> np.ndarray:
        return np.arange(int(round(self.duration_s * rate_hz)) + 1) / rate_hz

    def describe(self) -> str:
        how = f"landing at {self.velocity_m_s:g} m/s" if self.velocity_m_s > 0 else "released on the damper at rest"
        return f"{self.mass_kg:g} kg {how}, {self.duration_s:.3g} s"


@dataclass(frozen=True)
class Fitted:
    """A fit as the drop needs it: the model, θ̂, the estimated names and their covariance."""

    model: CompiledModel
    theta: np.ndarray
    estimated: tuple[str, ...]
    covariance: np.ndarray
    residual_based: bool         # the covariance includes the model error the fit found
    converged: bool
    source: str

    @classmethod
    def of(cls, result: FitResult, model: CompiledModel, source: str = "fit") -> Fitted:
        """A fit in memory (the residual-based covariance where it found model error)."""
        return cls(model, result.params.vector(), tuple(result.estimated), result.honest_covariance(),
                   result.covariance_residual is not None, result.converged, source)

    def held_at_prior(self, names: Sequence[str]) -> list[str]:
        """Those of ``names`` the fit did not estimate."""
        return [n for n in names if self.model.parameter_names[self.model.parameter_index(n)] not in self.estimated]


def check_damper(model: CompiledModel, source: str) -> None:
    """A landing needs the thermo-mechanical damper: a mass (θ1, θ2), the outputs a drop rig
    records, and the gas temperature as a state (the landing compresses the gas nearly
    adiabatically; a polytropic 1-dof model has no heat to lose and no time to lose it in)."""
    names = model.parameter_names
    missing = [o for o in HISTORIES if o not in model.output_names]
    if "theta1" not in names or "theta2" not in names or missing:
        raise DropInputError(f"{source}: model {model.name!r} is not a damper model with a mass and the outputs "
                             f"{', '.join(HISTORIES)}: no drop test")
    if not any(s.unit == THERMAL_UNIT for s in model.declaration.states):
        raise DropInputError(f"{source}: model {model.name!r} has no gas temperature state; a landing heats the "
                             f"gas within a tenth of a second: fit a thermo-mechanical model (2dof) for a drop test")


def load_fitted(path: str | Path, model_spec: str | None = None, model: CompiledModel | None = None) -> Fitted:
    """A RESULT.json of ``identify fit`` (or ``rig run --identify``) as :class:`Fitted`;
    its model by ``model``, else ``model_spec``, else the name it declares."""
    doc, source = load_document(path)
    if not isinstance(doc, dict) or "parameters" not in doc:
        raise DropInputError(f"{source}: not a RESULT.json (no 'parameters')")
    cov_doc = doc.get("covariance")
    if not isinstance(cov_doc, dict) or not cov_doc.get("estimated"):
        why = f" ({doc['message']})" if doc.get("message") else ""
        raise DropInputError(f"{source}: no covariance of estimated parameters: not the RESULT.json of a fit that "
                             f"ended{why}")
    if model is None:
        spec = model_spec or doc.get("model")
        if not isinstance(spec, str):
            raise DropInputError(f"{source}: names no model; give --model")
        try:
            model = load_model(spec)
        except InputError as exc:
            hint = "" if model_spec else " (a user model's RESULT.json needs --model path/file.py:ClassName)"
            raise DropInputError(f"{source}: {exc}{hint}") from None
    check_damper(model, source)
    try:
        params = Parameters.from_document(model, doc, source=source)
    except ParameterError as exc:
        raise DropInputError(str(exc)) from None
    estimated = tuple(str(n) for n in cov_doc["estimated"])
    residual = cov_doc.get("residual")
    matrix = residual if residual is not None else cov_doc.get("noise")
    try:
        cov = np.array(matrix, dtype=float)
    except (TypeError, ValueError):
        cov = np.empty(0)
    if cov.shape != (len(estimated), len(estimated)) or not np.all(np.isfinite(cov)):
        raise DropInputError(f"{source}: covariance is not a finite {len(estimated)}×{len(estimated)} matrix")
    unknown = [n for n in estimated if n not in model.parameter_names]
    if unknown:
        raise DropInputError(f"{source}: covariance names {', '.join(unknown)}, not parameters of model "
                             f"{model.name!r}")
    return Fitted(model, params.vector(), estimated, cov, residual is not None, bool(doc.get("converged")), source)


@dataclass(frozen=True)
class Peak:
    """A peak predicted (SI) with the fit's σ and the discrepancy's σ."""

    value: float
    fit_std: float
    discrepancy_std: float

    @property
    def std(self) -> float:
        return float(math.hypot(self.fit_std, self.discrepancy_std))


@dataclass(frozen=True)
class DropDiscrepancy:
    """σ_δ of the landing's force (and pressure, which the force balances) and its stroke."""

    force: Discrepancy
    stroke: Discrepancy

    @classmethod
    def given(cls, relative: float) -> DropDiscrepancy:
        if not (math.isfinite(relative) and 0 <= relative < 1):
            raise DropInputError(f"--discrepancy {relative:g}: a relative σ from 0 to below 1 (0.026 = 2.6 %)")
        d = Discrepancy(relative, 0, "given (--discrepancy)")
        return cls(d, d)


@dataclass(frozen=True)
class DropPrediction:
    """The landing predicted (SI histories on ``t``) with σ of each (fit and discrepancy
    combined), and the peaks."""

    landing: Landing
    t: np.ndarray
    force_N: np.ndarray
    stroke_m: np.ndarray
    pressure_Pa: np.ndarray
    force_std: np.ndarray
    stroke_std: np.ndarray
    pressure_std: np.ndarray
    peak_force: Peak
    peak_stroke: Peak
    discrepancy: DropDiscrepancy | None
    temperature_K: np.ndarray | None = None


def peak(y: np.ndarray) -> float:
    """Largest sample refined by a parabola through its neighbours, so that the peak
    varies smoothly with θ (a sample grid would make its derivative a staircase).  At the
    record's ends (a landing whose force is largest at contact) the sample itself."""
    i = int(np.argmax(y))
    if i == 0 or i == len(y) - 1:
        return float(y[i])
    f0, f1, f2 = y[i - 1], y[i], y[i + 1]
    c = f0 - 2 * f1 + f2
    return float(f1 - (f2 - f0) ** 2 / (8 * c)) if c < 0 else float(f1)


def _histories(model: CompiledModel, theta: np.ndarray, landing: Landing, t: np.ndarray) -> np.ndarray:
    """(force, stroke, pressure[, temperature]) in SI, the stroke as its transducer reads it."""
    out = drop_test(model, theta, landing.mass_kg, landing.velocity_m_s, t).outputs
    rows = [model.output_index("force_N"), model.output_index("stroke_mm"), model.output_index("pressure_bar")]
    if "gas_temperature_C" in model.output_names:
        rows.append(model.output_index("gas_temperature_C"))
    return out[rows]


def predict_drop(fitted: Fitted, landing: Landing = Landing(), t: np.ndarray | None = None,
                 discrepancy: DropDiscrepancy | None = None) -> DropPrediction:
    """The landing of ``fitted``'s model on ``t`` (default: ``landing``'s duration at
    1 kHz), with σ from the fit's covariance and ``discrepancy``."""
    model, theta = fitted.model, fitted.theta
    t = landing.times() if t is None else np.asarray(t, dtype=float)
    y = _histories(model, theta, landing, t)
    # One forward difference per estimated parameter: the histories' and the peaks'
    # sensitivities from the same integrations.
    J = np.empty((3, len(t), len(fitted.estimated)))
    Jpeak = np.empty((2, len(fitted.estimated)))
    peaks = np.array([peak(y[0]), peak(y[1])])
    for k, name in enumerate(fitted.estimated):
        i = model.parameter_index(name)
        h = RELATIVE_STEP * (abs(theta[i]) or 1.0)
        up = theta.copy()
        up[i] += h
        y2 = _histories(model, up, landing, t)
        J[..., k] = (y2[:3] - y[:3]) / h
        Jpeak[:, k] = (np.array([peak(y2[0]), peak(y2[1])]) - peaks) / h
    C = fitted.covariance
    fit_std = np.sqrt(np.maximum(np.einsum("oij,jk,oik->oi", J, C, J), 0.0))
    peak_std = np.sqrt(np.maximum(np.einsum("oj,jk,ok->o", Jpeak, C, Jpeak), 0.0))
    rel_force = discrepancy.force.relative if discrepancy else 0.0
    rel_stroke = discrepancy.stroke.relative if discrepancy else 0.0
    rel = np.array([rel_force, rel_stroke, rel_force])[:, None]   # the pressure balances the force
    std = np.hypot(fit_std, rel * np.abs(y[:3]))
    return DropPrediction(landing, t, y[0], y[1], y[2], std[0], std[1], std[2],
                          Peak(float(peaks[0]), float(peak_std[0]), rel_force * abs(peaks[0])),
                          Peak(float(peaks[1]), float(peak_std[1]), rel_stroke * abs(peaks[1])),
                          discrepancy, y[3] if len(y) > 3 else None)


# ----- measured drops and the type test ------------------------------------------------------
@dataclass(frozen=True)
class MeasuredDrop:
    """A drop rig's record (SI), from its contact on; absent columns are None."""

    t: np.ndarray
    force_N: np.ndarray
    stroke_m: np.ndarray | None
    pressure_Pa: np.ndarray | None
    landing: Landing | None      # as its dataset entry declares it (None: a bare CSV)
    source: str


def _from_columns(data, source: str, landing: Landing | None, duration_s: float | None) -> MeasuredDrop:
    t = data["time_s"].to_numpy()
    if duration_s is not None:   # the first seconds of a longer record
        data = data[t - t[0] <= duration_s + 1e-9]
        t = data["time_s"].to_numpy()
    cols = set(data.columns)
    return MeasuredDrop(t - t[0], data["force_N"].to_numpy(),
                        data["stroke_mm"].to_numpy() * 1e-3 if "stroke_mm" in cols else None,
                        data["pressure_bar"].to_numpy() * 1e5 if "pressure_bar" in cols else None,
                        landing, source)


def read_measured(path: str | Path, duration_s: float | None = None) -> MeasuredDrop:
    """A measured drop: a dataset folder's drop record (its mass and contact velocity from
    dataset.json) or a CSV with ``time_s`` and ``force_N`` (``stroke_mm``,
    ``pressure_bar`` if there).  The first sample is the contact."""
    path = Path(path)
    if path.is_dir():
        ds = read_manifest(path)
        drops = ds.select(kind="drop")
        if not drops:
            raise DropInputError(f"{path}: the dataset holds no drop record (kind \"drop\" in dataset.json)")
        exp: Experiment = read_dataset(path, ("force_N",), [drops[0].label]).experiment(drops[0].label)
        assert exp.data is not None   # read_dataset loaded the chosen record
        meta = exp.meta
        landing = Landing(float(meta["drop_mass_kg"]), float(meta.get("drop_velocity_m_s", 0.0)),
                          min(duration_s or math.inf, float(exp.time_s[-1] - exp.time_s[0])))
        return _from_columns(exp.data, f"{path / exp.file}", landing, duration_s)
    if not path.exists():
        raise DropInputError(f"{path}: file not found")
    try:
        data = load_csv(path, ("force_N",))
    except DatasetError as exc:
        raise DropInputError(str(exc)) from None
    return _from_columns(data, str(path), None, duration_s)


@dataclass(frozen=True)
class TypeTestUnit:
    """One reference unit: its fit, its measured drop, and the relative peak errors."""

    source: str
    force_error: float          # (measured − predicted) / predicted peak force
    stroke_error: float | None


def _fitted_of(folder: Path, like: Fitted) -> Fitted:
    """The unit's own RESULT.json, or its periodic experiments fitted as ``like`` was:
    the same model and estimated parameters, started from ``like``'s values."""
    result = folder / "RESULT.json"
    if result.is_file():
        fitted = load_fitted(result, model=like.model)
        if set(fitted.estimated) != set(like.estimated):
            raise DropInputError(f"{result}: estimated {', '.join(fitted.estimated)}, not "
                                 f"{', '.join(like.estimated)} as {like.source}: a type test fitted otherwise "
                                 f"says nothing about this fit's discrepancy")
        return fitted
    from identify.fit import fit_experiments
    from identify.preparation import model_columns, resolve_outputs

    model = like.model
    experiments = read_dataset(folder, model_columns(model, resolve_outputs(model, None))).select(kind="periodic")
    if not experiments:
        raise DropInputError(f"{folder}: no RESULT.json and no periodic experiment to fit")
    params = Parameters(model)
    for name, value in zip(model.parameter_names, like.theta, strict=True):
        params[name].value = float(value)
    return Fitted.of(fit_experiments(model, experiments, params, list(like.estimated)), model, str(folder))


def type_test(fitted: Fitted, folders: Sequence[str | Path]) -> tuple[DropDiscrepancy, list[TypeTestUnit]]:
    """σ_δ of the landing from reference units: each folder holds a unit's shaker data
    (and its RESULT.json, else it is fitted as ``fitted`` was) and its measured drop; each
    unit's drop is predicted at its own conditions and its relative peak errors are one
    draw of the discrepancy."""
    units = []
    for f in folders:
        folder = Path(f)
        if not folder.is_dir():
            raise DropInputError(f"--type-test {folder}: not a folder (a reference unit's dataset with its drop)")
        measured = read_measured(folder)
        assert measured.landing is not None   # a folder's drop declares its conditions
        unit = _fitted_of(folder, fitted)
        pred = predict_drop(unit, measured.landing, measured.t)
        f_err = (peak(measured.force_N) - pred.peak_force.value) / pred.peak_force.value
        s_err = ((peak(measured.stroke_m) - pred.peak_stroke.value) / pred.peak_stroke.value
                 if measured.stroke_m is not None else None)
        units.append(TypeTestUnit(str(folder), float(f_err), s_err))
    if not units:
        raise DropInputError("--type-test: no reference unit given")
    source = f"drop type test of {len(units)} unit{'s' if len(units) != 1 else ''}"
    force = from_errors([u.force_error for u in units], source)
    strokes = [u.stroke_error for u in units if u.stroke_error is not None]
    stroke = from_errors(strokes, source) if strokes else force
    return DropDiscrepancy(force, stroke), units
