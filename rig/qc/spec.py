"""The QC spec: a versioned TOML file that says how a production unit is tested and
judged — the plan (``[[experiment]]`` tables in the format ``rig run --plan`` reads, and
the steady-state criteria), the model and the parameters to estimate, the
characteristics with their limits, the guard band's coverage factor, and the table of
likely causes.  Its sha256 goes into every record: a verdict names the exact rules it
was given under.

Every problem is refused with one line naming the file and the key (exit 2)."""

from __future__ import annotations

import difflib
import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.config import SteadyStateCriteria, steady_state_from_table
from rig.errors import BadInput
from rig.planning.plans import Plan, PlanError, load_plan
from rig.tomlfile import read_toml

SPECS_DIR = Path(__file__).resolve().parent / "specs"

# The unit a characteristic is reported in, and its SI factor, by dimension.
UNITS: dict[str, tuple[str, float]] = {
    "Pa": ("pressure", 1.0), "kPa": ("pressure", 1e3), "mbar": ("pressure", 1e2), "bar": ("pressure", 1e5),
    "N": ("force", 1.0), "kN": ("force", 1e3),
    "J": ("energy", 1.0), "kJ": ("energy", 1e3),
}
# Each kind of characteristic: its dimension and the keys it takes beyond the common ones.
KINDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "gas_pressure": ("pressure", ("stroke_mm", "temperature_C")),    # the model's gas pressure at rest
    "orifice_force": ("force", ("velocity_m_s",)),                    # θ3·v·|v|
    "friction": ("force", ("pressure_bar",)),                         # θ8 + θ9·p
    "loop_energy": ("energy", ("experiment",)),                       # ∮F dq of a measured experiment
    "drop_peak_force": ("force", ("mass_kg", "velocity_m_s")),        # models.md drop test, identified model
    # measurands (rig/qc/measurands.py): computed from the captured channels of a plan's experiment, no model
    "gas_spring_pressure": ("pressure", ("experiment", "stroke_mm", "temperature_C")),
    "damping_force": ("force", ("experiment", "velocity_m_s", "direction")),
    "seal_friction": ("force", ("experiment",)),
    "cycle_energy": ("energy", ("experiment",)),
}
MEASURANDS = ("gas_spring_pressure", "damping_force", "seal_friction", "cycle_energy")
# Keys a kind may take besides: a loop energy's experiment conditions, from which the
# identified model computes it where the plan does not run the experiment.
OPTIONAL: dict[str, tuple[str, ...]] = {
    "loop_energy": ("static_mm", "amplitude_mm", "frequency_Hz"),
}
COMMON_KEYS = ("name", "kind", "unit", "nominal", "low", "high", "tolerance_percent", "u_cal", "description", "title",
               "predicted", "discrepancy_percent")
TOP_KEYS = ("name", "version", "title", "serial_pattern", "k", "periods", "capture", "identification", "steady_state",
            "experiment", "characteristic", "diagnosis", "release", "basis", "measurement", "calibration")
# The measurands' conditions of a spec ([measurement]) and the transducers' calibration ([calibration], per
# channel: u_gain_percent, u_offset in the channel's unit), as GUM type B standard uncertainties.
MEASUREMENT_KEYS = ("piston_area_mm2", "moving_mass_kg")
CALIBRATION_CHANNELS = {"stroke_mm": ("stroke", 1e-3), "force_N": ("force", 1.0), "pressure_bar": ("pressure", 1e5),
                        "gas_temperature_C": ("temperature", 1.0)}
MEASURAND_DIRECTIONS = ("compression", "rebound")
DIRECTIONS = ("low", "high")


class SpecError(BadInput):
    """A QC spec that cannot be used (names the file and the key)."""


@dataclass(frozen=True)
class Characteristic:
    """One judged quantity: how it is computed, its limits (in ``unit``) and the
    calibration uncertainty u_cal of the rig's transducers for it (GUM type B, in
    ``unit``), combined in quadrature with the identification's σ."""

    name: str
    kind: str
    unit: str
    nominal: float
    low: float | None
    high: float | None
    u_cal: float
    args: dict[str, Any]
    description: str = ""
    title: str = ""           # the readable name reports and screens show (``name`` is the identifier)
    predicted: bool = False   # computed from the identified model: shown, labelled predicted, never decides
    discrepancy: float = 0.0  # a predicted one's model discrepancy σ_δ, relative (from a type test)

    @property
    def measurand(self) -> bool:
        """Measured at the axle from the captured channels (rig/qc/measurands.py)."""
        return self.kind in MEASURANDS

    @property
    def shown(self) -> str:
        return self.title or self.name

    @property
    def si_factor(self) -> float:
        return UNITS[self.unit][1]


@dataclass(frozen=True)
class Spec:
    name: str
    version: str
    title: str
    source: str
    text: str
    sha256: str
    serial_pattern: str
    k: float
    model: str
    estimate: tuple[str, ...]
    grid_points: int
    start: str | None
    steady_state: SteadyStateCriteria
    plan: Plan
    characteristics: tuple[Characteristic, ...]
    causes: dict[tuple[str, str], str] = field(default_factory=dict)   # (characteristic, low|high) → cause
    release_required: bool = False    # ``release = true``: a unit needs a second person's qc release
    basis: str = ""                    # what the nominal values and tolerances rest on (a type test, a model)
    measurement: dict[str, float] = field(default_factory=dict)   # [measurement]: the measurands' constants (SI)
    calibration: dict[str, tuple[float, float]] = field(default_factory=dict)   # channel → (u gain rel., u offset SI)

    @property
    def model_free(self) -> bool:
        """Every characteristic that decides is a measurand: the verdict needs no fit."""
        return all(c.measurand for c in self.characteristics if not c.predicted)

    def check_serial(self, serial: str) -> str:
        if not re.fullmatch(self.serial_pattern, serial):
            raise SpecError(f"serial number {serial!r} does not have the format of spec {self.name!r} "
                            f"(pattern {self.serial_pattern})")
        return serial

    def cause(self, characteristic: str, direction: str) -> str | None:
        return self.causes.get((characteristic, direction))

    def retest_periods(self) -> int:
        """The remedy for an inconclusive verdict: twice the plan's longest capture."""
        return 2 * max(e.periods for e in self.plan.experiments)


def spec_path(source: str) -> Path:
    """``default`` (or any name shipped in rig/qc/specs) or the path of a spec file."""
    shipped = SPECS_DIR / f"{source}.toml"
    if "/" not in source and not source.endswith(".toml") and shipped.is_file():
        return shipped
    path = Path(source)
    if not path.exists():   # a misspelt name reads as a missing file: say which specs there are
        names = sorted(p.stem for p in SPECS_DIR.glob("*.toml"))
        meant = difflib.get_close_matches(source, names, n=1)
        raise SpecError(f"spec {source!r}: no such spec and no such file"
                        + (f" (did you mean {meant[0]!r}?)" if meant else "")
                        + f"; the specs shipped: {', '.join(names)}, or the path of a spec TOML file")
    return path


def load_spec(source: str) -> Spec:
    path = spec_path(source)
    text, doc = read_toml(path, SpecError, "spec ")
    where = f"spec {path}"
    _no_unknown(doc, TOP_KEYS, where)
    try:
        plan = load_plan(str(path))
    except PlanError as exc:
        raise SpecError(str(exc)) from None
    ident = _table(doc, "identification", where)
    _no_unknown(ident, ("model", "estimate", "grid_points", "start"), f"{where}, [identification]")
    estimate = ident.get("estimate")
    if not isinstance(estimate, list) or not estimate or not all(isinstance(x, str) for x in estimate):
        raise SpecError(f"{where}, [identification]: 'estimate' must be a non-empty list of parameter names")
    characteristics = tuple(_characteristic(c, i, where, plan) for i, c in
                            enumerate(_tables(doc, "characteristic", where), 1))
    names = [c.name for c in characteristics]
    if not names:
        raise SpecError(f"{where}: no [[characteristic]] tables: nothing to judge")
    if len(set(names)) != len(names):
        raise SpecError(f"{where}: a characteristic name is used twice ({', '.join(names)})")
    causes = {}
    for i, d in enumerate(_tables(doc, "diagnosis", where), 1):
        at = f"{where}, diagnosis {i}"
        _no_unknown(d, ("characteristic", "when", "cause"), at)
        key = (_str(d, "characteristic", at), _str(d, "when", at))
        if key[0] not in names:
            raise SpecError(f"{at}: no characteristic {key[0]!r} (characteristics: {', '.join(names)})")
        if key[1] not in DIRECTIONS:
            raise SpecError(f"{at}: 'when' must be 'low' or 'high', not {key[1]!r}")
        causes[key] = _str(d, "cause", at)
    pattern = str(doc.get("serial_pattern", r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}"))
    try:
        re.compile(pattern)
    except re.error as exc:
        raise SpecError(f"{where}: serial_pattern is not a regular expression ({exc})") from None
    k = _number(doc, "k", where, default=2.0)
    if not k > 0:
        raise SpecError(f"{where}: k (the guard band's coverage factor) must be positive")
    start = ident.get("start")
    if start is not None:
        start = str((path.parent / str(start)).resolve())
    release = doc.get("release", False)
    if not isinstance(release, bool):
        raise SpecError(f"{where}: release must be true (a second person releases each unit: qc release) or false")
    return Spec(name=_str(doc, "name", where), version=str(_str(doc, "version", where)),
                title=str(doc.get("title", "")), source=str(path), text=text,
                sha256=hashlib.sha256(path.read_bytes()).hexdigest(), serial_pattern=pattern, k=k,
                model=str(ident.get("model", "2dof")), estimate=tuple(estimate),
                grid_points=int(_number(ident, "grid_points", f"{where}, [identification]", default=800)),
                start=start, steady_state=_steady_state(doc, where), plan=plan, characteristics=characteristics,
                causes=causes, release_required=release, basis=str(doc.get("basis", "")),
                measurement=_measurement(doc, where, characteristics), calibration=_calibration(doc, where))


def _measurement(doc: dict[str, Any], where: str, characteristics: tuple[Characteristic, ...]) -> dict[str, float]:
    table = doc.get("measurement", {})
    at = f"{where}, [measurement]"
    if not isinstance(table, dict):
        raise SpecError(f"{at}: expected a table")
    _no_unknown(table, MEASUREMENT_KEYS, at)
    if any(c.kind == "damping_force" for c in characteristics):
        for key in MEASUREMENT_KEYS:
            if key not in table:
                raise SpecError(f"{at}: missing key {key!r} (the damping force subtracts the gas force and the "
                                "moving mass)")
    out = {}
    if "piston_area_mm2" in table:
        out["area_m2"] = _number(table, "piston_area_mm2", at) * 1e-6
    if "moving_mass_kg" in table:
        out["moving_mass_kg"] = _number(table, "moving_mass_kg", at)
    return out


def _calibration(doc: dict[str, Any], where: str) -> dict[str, tuple[float, float]]:
    table = doc.get("calibration", {})
    at = f"{where}, [calibration]"
    if not isinstance(table, dict):
        raise SpecError(f"{at}: expected a table")
    _no_unknown(table, tuple(CALIBRATION_CHANNELS), at)
    out = {}
    for channel, entry in table.items():
        name, si = CALIBRATION_CHANNELS[channel]
        if not isinstance(entry, dict):
            raise SpecError(f"{at}: {channel!r} must be a table of u_gain_percent and u_offset")
        _no_unknown(entry, ("u_gain_percent", "u_offset"), f"{at}, {channel}")
        gain, offset = (_number(entry, key, f"{at}, {channel}", default=0.0) for key in ("u_gain_percent", "u_offset"))
        if gain < 0 or offset < 0:
            raise SpecError(f"{at}, {channel}: uncertainties must not be negative")
        out[name] = (gain / 100, offset * si)
    return out


def _steady_state(doc: dict[str, Any], where: str) -> SteadyStateCriteria:
    ss = _table(doc, "steady_state", where)
    at = f"{where}, [steady_state]"
    channels = ("stroke_mm", "force_N", "pressure_bar", "gas_temperature_C")
    drift = ("criterion", "drift_sigma_fraction", "drift_fit_cycles", "drift_max_time_constant_s", "drift_noise",
             "drift_model_time_constant_factor")
    _no_unknown(ss, ("block_s", "min_cycles", "max_cycles", "max_recaptures", "ramp_time_s", *channels, *drift), at)
    return steady_state_from_table(ss, at, SpecError)


def _characteristic(c: Any, i: int, where: str, plan: Plan) -> Characteristic:
    at = f"{where}, characteristic {i}"
    if not isinstance(c, dict):
        raise SpecError(f"{at}: expected a table")
    name = _str(c, "name", at)
    at = f"{where}, characteristic {name!r}"
    kind = _str(c, "kind", at)
    if kind not in KINDS:
        raise SpecError(f"{at}: unknown kind {kind!r} (kinds: {', '.join(KINDS)})")
    dimension, extra = KINDS[kind]
    optional = OPTIONAL.get(kind, ())
    _no_unknown(c, COMMON_KEYS + extra + optional, at)
    unit = _str(c, "unit", at)
    if unit not in UNITS or UNITS[unit][0] != dimension:
        options = ", ".join(u for u, (d, _) in UNITS.items() if d == dimension)
        raise SpecError(f"{at}: unit {unit!r} is not a unit of {dimension} ({options})")
    nominal = _number(c, "nominal", at)
    low: float | None
    high: float | None
    if "tolerance_percent" in c:
        if "low" in c or "high" in c:
            raise SpecError(f"{at}: give either 'tolerance_percent' or 'low'/'high', not both")
        tol = _number(c, "tolerance_percent", at)
        # rounded: 6.00 ± 5 % is 5.70, not 5.699999999999999, in every record and report
        low, high = (float(f"{nominal * (1 + sign * tol / 100):.12g}") for sign in (-1, 1))
    else:
        low = _number(c, "low", at) if "low" in c else None
        high = _number(c, "high", at) if "high" in c else None
        if low is None and high is None:
            raise SpecError(f"{at}: no limits ('low', 'high' or 'tolerance_percent')")
    if low is not None and high is not None and not low < high:
        raise SpecError(f"{at}: low {low:g} is not below high {high:g}")
    u_cal = _number(c, "u_cal", at, default=0.0)
    if u_cal < 0:
        raise SpecError(f"{at}: u_cal must not be negative")
    args: dict[str, Any] = {}
    given = [key for key in optional if key in c]
    if given and len(given) != len(optional):
        raise SpecError(f"{at}: give all of {', '.join(optional)} (the conditions the model computes it at), "
                        f"or none")
    for key in given:
        args[key] = _number(c, key, at)
    for key in extra:
        if key == "direction":
            direction = _str(c, key, at)
            if direction not in MEASURAND_DIRECTIONS:
                raise SpecError(f"{at}: direction must be one of {', '.join(MEASURAND_DIRECTIONS)}, not {direction!r}")
            args[key] = direction
        elif key == "experiment" and kind in MEASURANDS:
            letter = _str(c, key, at)
            spec = next((e for e in plan.experiments if e.letter == letter), None)
            if spec is None:
                raise SpecError(f"{at}: the plan has no experiment {letter!r} to measure it in")
            args[key] = letter
        elif key == "experiment":
            letter = _str(c, key, at)
            spec = next((e for e in plan.experiments if e.letter == letter), None)
            if spec is None and given:
                args[key] = letter      # not run: computed from the model at the conditions given
                continue
            if spec is None:
                raise SpecError(f"{at}: the plan has no experiment {letter!r} (and no static_mm, amplitude_mm, "
                                f"frequency_Hz to compute it from the model at)")
            if spec.periods < 2:
                raise SpecError(f"{at}: experiment {letter!r} captures {spec.periods} period; the energy's "
                                "scatter needs at least 2")
            args[key] = letter
        else:
            args[key] = _number(c, key, at)
    predicted = c.get("predicted", False)
    if not isinstance(predicted, bool):
        raise SpecError(f"{at}: 'predicted' must be true or false")
    if predicted and kind in MEASURANDS:
        raise SpecError(f"{at}: a measurand is measured, not predicted")
    discrepancy = _number(c, "discrepancy_percent", at, default=0.0) / 100
    if discrepancy < 0 or (discrepancy and not predicted):
        raise SpecError(f"{at}: 'discrepancy_percent' is a predicted characteristic's model discrepancy (≥ 0)")
    return Characteristic(name, kind, unit, nominal, low, high, u_cal, args, str(c.get("description", "")),
                          str(c.get("title", "")), predicted, discrepancy)


def _no_unknown(table: dict[str, Any], known: tuple[str, ...], where: str) -> None:
    unknown = [k for k in table if k not in known]
    if unknown:
        raise SpecError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
                        f"(known: {', '.join(known)})")


def _table(doc: dict[str, Any], key: str, where: str) -> dict[str, Any]:
    value = doc.get(key)
    if not isinstance(value, dict):
        raise SpecError(f"{where}: no [{key}] table")
    return value


def _tables(doc: dict[str, Any], key: str, where: str) -> list[dict[str, Any]]:
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(x, dict) for x in value):
        raise SpecError(f"{where}: '{key}' must be [[{key}]] tables")
    return value


def _str(table: dict[str, Any], key: str, where: str) -> str:
    value = table.get(key)
    if not isinstance(value, str) or not value:
        raise SpecError(f"{where}: {key!r} must be a non-empty string")
    return value


def _number(table: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = table.get(key, default)
    if value is None:
        raise SpecError(f"{where}: missing key {key!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SpecError(f"{where}: {key!r} must be a finite number, not {value!r}")
    return float(value)
