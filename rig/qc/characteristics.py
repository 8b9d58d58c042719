"""The characteristics of a unit, computed from its identified model or from its data,
each with its standard uncertainty.

Model-based characteristics propagate the fit's covariance linearly, σ² = J·C·Jᵀ, with
J = ∂c/∂θ over the estimated parameters by central differences (forward ones for the
drop test, whose every evaluation is a time integration).  The loop energy comes from
the measured samples: one work loop ∮F dq per captured period, σ from their scatter.
The rig's calibration uncertainty u_cal (spec) is added in quadrature to either.

Inside everything is SI; a :class:`Measured` is in the characteristic's unit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from identify.dataset import Experiment
from identify.fit_warnings import WarningCode
from identify.model import CompiledModel, ModelError, load_model
from identify.parameters import Parameters
from identify.plans import ExperimentSpec
from identify.result import FitResult
from identify.transient import drop_test
from rig.qc.measuring import Measured, measured
from rig.qc.spec import Characteristic, Spec, SpecError

CELSIUS = 273.15
DROP_WINDOW_S = 1.0        # the first compression, where the peak force lies, is over by about 0.5 s
DROP_STEP_S = 2.5e-4
RELATIVE_STEP = 1e-5       # of |θ| for the finite differences (1e-3 for the integrated drop test)


@dataclass(frozen=True)
class Identified:
    """What the model-based characteristics need of a converged identification: the
    whole parameter vector (SI), the estimated names and the covariance to propagate
    (theirs, in that order).  From a fit in this process, or from a stored result
    (``identify batch``'s, re-judged)."""

    theta: np.ndarray
    estimated: tuple[str, ...]
    covariance: np.ndarray
    basis: str = "noise"      # "residual" where the residuals exceeded the noise (model error), "noise-misfit"
                              # where they did but too few experiments gave no residual-based covariance

    @classmethod
    def from_fit(cls, fit: FitResult | None) -> Identified | None:
        """None for a fit that did not converge (or did not happen)."""
        if fit is None or not fit.converged:
            return None
        # The residual-based covariance where the fit found model error: a guard band of the
        # noise-only σ would pass units on a precision the model does not have.
        misfit = any(w.code is WarningCode.MODEL_ERROR for w in fit.findings)
        basis = "residual" if fit.covariance_residual is not None else "noise-misfit" if misfit else "noise"
        return cls(fit.params.vector(), tuple(fit.estimated), fit.honest_covariance(), basis)


def check_model(spec: Spec) -> CompiledModel:
    """The spec's model, with every name the spec relies on present (refused with one line)."""
    try:
        model = load_model(spec.model)
        for name in spec.estimate:
            model.parameter_index(name)
        needed = {"orifice_force": ["theta3"], "friction": ["theta8", "theta9"],
                  "drop_peak_force": ["theta1", "theta2"]}
        for c in spec.characteristics:
            for name in needed.get(c.kind, []):
                model.parameter_index(name)
            if c.kind == "gas_pressure":
                model.output_index("pressure_bar")
            if c.kind == "drop_peak_force":
                model.output_index("force_N")
    except ModelError as exc:
        raise SpecError(f"spec {spec.source}: {exc}") from None
    return model


def measure(spec: Spec, model: CompiledModel, identified: Identified | None,
            experiments: list[Experiment]) -> list[Measured]:
    """Every characteristic of the spec; model-based ones need a converged identification."""
    out = []
    run = {e.letter for e in spec.plan.experiments}
    for c in spec.characteristics:
        if c.measurand:
            out.append(measured(spec, c, experiments))
            continue
        if c.kind == "loop_energy" and c.args["experiment"] in run:
            exp = next((e for e in experiments if e.label.endswith(c.args["experiment"])), None)
            if exp is None:
                out.append(_missing(c, f"no experiment {c.args['experiment']!r} in the session"))
                continue
            value, std = loop_energy(exp)
            basis = "scatter"
        elif identified is None:
            out.append(_missing(c, "the identification did not converge"))
            continue
        else:
            value, std = _propagate(model, identified, model_function(model, c), c.kind == "drop_peak_force")
            std = math.hypot(std, c.discrepancy * value)     # the model's own error (a type test's σ_δ)
            basis = identified.basis
        scale = c.si_factor
        std_fit = std / scale
        out.append(Measured(c.name, c.unit, value / scale, math.hypot(std_fit, c.u_cal), std_fit, c.u_cal,
                            basis=basis, predicted=c.predicted))
    return out


def _missing(c: Characteristic, why: str) -> Measured:
    return Measured(c.name, c.unit, None, None, None, c.u_cal, why, predicted=c.predicted)


def model_function(model: CompiledModel, c: Characteristic) -> Callable[[np.ndarray], float]:
    """θ (full vector, SI) → the characteristic (SI)."""
    a = c.args
    if c.kind == "gas_pressure":
        return lambda theta: gas_pressure(model, theta, a["stroke_mm"] * 1e-3, a["temperature_C"] + CELSIUS)
    if c.kind == "orifice_force":
        i3, v = model.parameter_index("theta3"), a["velocity_m_s"]
        return lambda theta: float(theta[i3] * v * abs(v))
    if c.kind == "friction":
        i8, i9, p = model.parameter_index("theta8"), model.parameter_index("theta9"), a["pressure_bar"] * 1e5
        return lambda theta: float(theta[i8] + theta[i9] * p)
    if c.kind == "drop_peak_force":
        return lambda theta: drop_peak_force(model, theta, a["mass_kg"], a["velocity_m_s"])
    if c.kind == "loop_energy":     # an experiment the plan does not run (spec: its conditions given)
        from rig.planning.imposed import loop_energy_j

        run = ExperimentSpec(a["experiment"], "", a["static_mm"], a["amplitude_mm"], a["frequency_Hz"])
        params = Parameters(model)

        def energy(theta: np.ndarray) -> float:
            params.set_vector(theta)
            return loop_energy_j(params, run)

        return energy
    raise AssertionError(f"no model function for kind {c.kind!r}")  # spec.KINDS lists the kinds handled here


def gas_pressure(model: CompiledModel, theta: np.ndarray, stroke_m: float, temperature_k: float) -> float:
    """The model's gas pressure with the damper at rest at this stroke and gas temperature."""
    states = {"q": stroke_m, "T": temperature_k}
    X = np.array([[states.get(s, 0.0)] for s in model.state_names])
    zeros = np.zeros_like(X)
    U = np.zeros((len(model.input_names), 1))
    return float(model.output(X, zeros, zeros, U, theta)[model.output_index("pressure_bar"), 0])


def drop_peak_force(model: CompiledModel, theta: np.ndarray, mass_kg: float, velocity_m_s: float) -> float:
    """Peak damper force of the drop test (docs/models.md), refined by a parabola through
    the largest sample so that it varies smoothly with θ."""
    window = DROP_WINDOW_S
    while True:
        t = np.arange(0.0, window + DROP_STEP_S / 2, DROP_STEP_S)
        force = drop_test(model, theta, mass_kg, velocity_m_s, t).outputs[model.output_index("force_N")]
        if np.argmax(force) < len(force) - 2 or window > 30:
            break
        window *= 4        # still rising at the window's end: a very soft unit
    i = int(np.clip(np.argmax(force), 1, len(force) - 2))
    f0, f1, f2 = force[i - 1], force[i], force[i + 1]
    curvature = f0 - 2 * f1 + f2
    return float(f1 - (f2 - f0) ** 2 / (8 * curvature)) if curvature < 0 else float(f1)


def _propagate(model: CompiledModel, identified: Identified, f: Callable[[np.ndarray], float],
               integrated: bool) -> tuple[float, float]:
    theta = identified.theta
    value = f(theta)
    J = np.empty(len(identified.estimated))
    for col, name in enumerate(identified.estimated):
        i = model.parameter_index(name)
        h = (1e-3 if integrated else RELATIVE_STEP) * (abs(theta[i]) or 1.0)
        up = theta.copy()
        up[i] += h
        if integrated:
            J[col] = (f(up) - value) / h
        else:
            down = theta.copy()
            down[i] -= h
            J[col] = (f(up) - f(down)) / (2 * h)
    return value, float(np.sqrt(max(J @ identified.covariance @ J, 0.0)))


def loop_energy(exp: Experiment) -> tuple[float, float]:
    """Energy dissipated per cycle [J]: the mean work loop ∮F dq over the captured whole
    periods, and its standard error from their scatter."""
    t, q, force = exp.time_s, exp.column("stroke_mm") * 1e-3, exp.column("force_N")
    period = 1.0 / exp.frequency_hz
    dt = float(np.median(np.diff(t)))
    k = int(math.floor((t[-1] - t[0] + dt) / period * (1 + 1e-6)))   # each sample stands for dt
    loops = []
    for j in range(k):
        sel = (t >= t[0] + j * period - 1e-9) & (t < t[0] + (j + 1) * period - 1e-9)
        qq, ff = np.append(q[sel], q[sel][0]), np.append(force[sel], force[sel][0])   # closed loop
        loops.append(float(np.sum(0.5 * (ff[1:] + ff[:-1]) * np.diff(qq))))
    if len(loops) < 2:
        raise SpecError(f"experiment {exp.label}: {len(loops)} whole period captured; the loop energy needs 2")
    return float(np.mean(loops)), float(np.std(loops, ddof=1) / math.sqrt(len(loops)))
