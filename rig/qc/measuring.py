"""A spec's measurand characteristics measured on a session's experiments: the spec's
words (kind, conditions, units, the rig's calibration) turned into a
:class:`rig.qc.measurands.Definition` and a :class:`Measured`
with its budget.  The arithmetic is rig.qc.measurands'; this is the spec's side of it."""

from __future__ import annotations

from dataclasses import dataclass

from identify.dataset import Experiment
from rig.qc.measurands import CELSIUS, Calibration, Definition, MeasurandError, Record, measure
from rig.qc.spec import Characteristic, Spec


def definition(spec: Spec, c: Characteristic) -> Definition:
    """What ``c`` measures, in SI (rig.qc.measurands.Definition)."""
    a = c.args
    if c.kind == "gas_spring_pressure":
        return Definition(c.kind, stroke_m=a["stroke_mm"] * 1e-3, temperature_k=a["temperature_C"] + CELSIUS)
    if c.kind == "damping_force":
        return Definition(c.kind, velocity_m_s=a["velocity_m_s"], direction=a["direction"],
                          area_m2=spec.measurement["area_m2"], moving_mass_kg=spec.measurement["moving_mass_kg"])
    return Definition(c.kind)


def calibration(spec: Spec) -> Calibration:
    """The spec's transducer calibration uncertainties (none stated: none counted)."""
    return Calibration({k: g for k, (g, _) in spec.calibration.items()},
                       {k: o for k, (_, o) in spec.calibration.items()})


def conditions(spec: Spec, c: Characteristic) -> str:
    """The experiment's conditions in words: ``14 ± 20 mm, 4 Hz``."""
    e = next(e for e in spec.plan.experiments if e.letter == c.args["experiment"])
    return f"{e.static_position_mm:g} ± {e.amplitude_mm:g} mm, {e.frequency_hz:g} Hz"


def describe(spec: Spec, c: Characteristic) -> str:
    return definition(spec, c).describe(conditions(spec, c))


@dataclass(frozen=True)
class Measured:
    """A characteristic's value and standard uncertainties, in its unit; ``value`` None
    when it could not be computed (``note`` says why)."""

    name: str
    unit: str
    value: float | None
    std: float | None        # combined: sqrt(std_fit² + u_cal²)
    std_fit: float | None    # from the fit's covariance, or from the scatter of the periods
    u_cal: float
    note: str = ""
    basis: str | None = None  # which σ: "noise" or "residual" (the fit's), "scatter" (of the periods), "budget"
    definition: str = ""      # a measurand's: what is measured under which conditions (rig.qc.measurands)
    budget: tuple[dict[str, object], ...] = ()   # a measurand's GUM budget rows, in its unit
    cycles: int = 0           # a measurand's: the cycles it was measured over
    predicted: bool = False   # from the identified model (shown, never decides)



def experiment_of(c: Characteristic, experiments: list[Experiment]) -> Experiment | None:
    return next((e for e in experiments if e.label.endswith(c.args["experiment"])), None)


def measured(spec: Spec, c: Characteristic, experiments: list[Experiment]) -> Measured:
    """``c`` measured on the session's experiment, in its unit, with its budget; no value
    (and a note why) when the experiment is missing or does not hold what it needs."""
    exp = experiment_of(c, experiments)
    text = describe(spec, c)
    if exp is None:
        return Measured(c.name, c.unit, None, None, None, c.u_cal,
                        f"no experiment {c.args['experiment']!r} in the session", definition=text)
    try:
        v = measure(definition(spec, c), Record.from_experiment(exp), calibration(spec))
    except MeasurandError as exc:
        return Measured(c.name, c.unit, None, None, None, c.u_cal, f"not measured: {exc}", definition=text)
    scale = c.si_factor
    rows = tuple(v.rows)
    u = v.u / scale
    u_a = next((r.u for r in rows if r.type == "A"), 0.0) / scale
    u_cal = (sum(r.u**2 for r in rows if r.type == "B") ** 0.5) / scale
    return Measured(c.name, c.unit, v.value / scale, u, u_a, u_cal, basis="budget", definition=text,
                    budget=tuple(r.to_json(scale) for r in rows), cycles=v.cycles)
