"""Physics of the virtual rig: the damper of docs/models.md in displacement control.

The shaker imposes the stroke; a servo-hydraulic actuator tracks the commanded stroke
with a finite bandwidth (second order) and a velocity limit.  The controller closes its
loop on the stroke transducer, which is also the DAQ's stroke channel: what it tracks,
limits and reports is the measured stroke q + θ12, so the damper sits at
q = measured − θ12 and the physics is evaluated there.  The gas temperature
follows from the energy balance g2 integrated in time, the pressure from the gas law,
and the axle force from g1 solved for Fe (inverse dynamics).  The equations are
written here from docs/models.md independently of ``identify``'s generated code, so that
identification on simulated data also checks one against the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from scipy.integrate import solve_ivp
from scipy.signal import cont2discrete, lfilter, lfilter_zi

from identify.models.damper import Damper1Dof, Damper2Dof
from identify.plans import ExperimentSpec
from simulator.errors import SimulatorError

FloatOrArray = TypeVar("FloatOrArray", float, np.ndarray)
G0 = 9.81
DECLARATIONS = {"1dof": Damper1Dof, "2dof": Damper2Dof}


class TruthError(SimulatorError, ValueError):
    """True parameters the simulator cannot represent; it refuses them rather than
    simulate something else than they say."""


def check_truth(theta: dict[str, float], model: str) -> None:
    """Raise :class:`TruthError` (one line) unless every parameter of ``theta`` is one of
    the model's and has a value the simulator honours as models.md reads it."""
    declared = [p.name for p in DECLARATIONS[model].parameters]
    unknown = [k for k in theta if k not in declared]
    if unknown:
        raise TruthError(f"unknown parameter(s) {', '.join(unknown)} for the {model} damper "
                         f"(known: {', '.join(declared)})")
    missing = [k for k in declared if k not in theta]
    if missing:
        raise TruthError(f"no value for {', '.join(missing)} of the {model} damper")
    for name, value in theta.items():
        if not math.isfinite(value):
            raise TruthError(f"{name} = {value}: not a finite number")
    for name in ("theta13", "theta14"):
        if theta[name] != 0.0:
            raise TruthError(f"{name} = {theta[name]:g}: no damper model uses it (models.md keeps only the number), "
                             "so a nonzero value cannot be simulated")
    positive = {"theta1": "the moving mass", "theta4": "the piston area",
                "theta5": "the gas constant (absolute pressure)"}
    if model == "2dof":
        # With θ16 = 0 the gas is adiabatic: every start temperature is periodic, so the
        # experiment has no steady state to simulate; θ15 divides the energy balance.
        positive |= {"theta15": "the gas heat capacity", "theta16": "the wall heat transfer"}
    for name, what in positive.items():
        if not theta[name] > 0:
            raise TruthError(f"{name} = {theta[name]:g}: {what} must be positive")
    if not theta["theta17"] < 0:
        raise TruthError(f"theta17 = {theta['theta17']:g}: minus the ambient temperature must be negative "
                         "(an absolute temperature above 0 K)")


def stop_force(q: float | np.ndarray) -> np.ndarray:
    """The end stops' contact force at the damper's stroke q [N], positive compressing:
    zero within the stroke, the plant's top-out and bottom-out stops outside it
    (simulator/plant/constants.toml [stops]).  The model tier feels them where its
    stroke is free, in the drop (:func:`drop_test`); an imposed stroke is kept inside
    them by the plan checks (:func:`past_the_stops`, the rig's envelope)."""
    top, bottom, stiffness = _STOPS
    return stiffness * (np.minimum(np.asarray(q) - top, 0.0) + np.maximum(np.asarray(q) - bottom, 0.0))


def past_the_stops(spec: ExperimentSpec) -> str | None:
    """What experiment ``spec`` commands past the end stops, in one phrase (None: nothing)."""
    top, bottom, _ = _STOPS
    low = (spec.static_position_mm - spec.amplitude_mm) * 1e-3
    high = (spec.static_position_mm + spec.amplitude_mm) * 1e-3
    if low <= top:
        return f"commands the stroke to {low * 1e3:.1f} mm, past the damper's full extension at {top * 1e3:.1f} mm"
    if high >= bottom:
        return f"commands the stroke to {high * 1e3:.1f} mm, past the damper's bottom-out at {bottom * 1e3:.1f} mm"
    return None


def _stops() -> tuple[float, float, float]:
    from simulator.plant.constants import load_constants

    k = load_constants()
    return k.stops_top_out_stroke, k.stops_bottom_out_stroke, k.stops_stiffness


_STOPS = _stops()


@dataclass(frozen=True)
class Damper:
    """Damper parameters θ (SI, keyed theta1…theta17) and the model variant.

    Every θ of models.md is honoured: θ1–θ11 in the forces and the gas law, θ12 between
    the damper's q and the measured stroke, θ15–θ17 in the energy balance and ambient
    (2-dof; the 1-dof gas is polytropic and its temperature channel reads ambient −θ17).
    θ13/θ14 occur in no model and must be zero; see :func:`check_truth`.  The drop test
    replaces θ1 and θ2 by the dropped mass and −g, as models.md prescribes."""

    theta: dict[str, float]
    model: str = "2dof"  # or "1dof": polytropic gas, no thermal state

    def __post_init__(self) -> None:
        if self.model not in DECLARATIONS:
            raise ValueError(f"unknown damper model {self.model!r}")
        check_truth(self.theta, self.model)

    def __getattr__(self, name: str) -> float:
        if name.startswith("theta") and name in self.theta:
            value = self.theta[name]
            object.__setattr__(self, name, value)  # cached: the hot path reads θ per block
            return value
        raise AttributeError(name)

    @property
    def ambient_k(self) -> float:
        return -self.theta17

    def measured_stroke(self, q: FloatOrArray) -> FloatOrArray:
        """What the stroke transducer reads at damper stroke ``q``: ŷ = q + θ12 [m]."""
        return q + self.theta12

    def internal_stroke(self, measured_m: FloatOrArray) -> FloatOrArray:
        """The damper's q at a measured stroke [m]."""
        return measured_m - self.theta12

    def pressure(self, q: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Absolute gas pressure [Pa]."""
        if self.model == "1dof":
            return self.theta5 * (1 + self.theta6 * q) ** (-self.theta7) + 0 * T
        return self.theta5 * T / (1 + self.theta6 * q + self.theta7 * T)

    def damper_force(self, q: np.ndarray, v: np.ndarray, T: np.ndarray) -> np.ndarray:
        """F_d = θ3·v|v| + θ4·p + (θ8 + θ9·p)·arctan(θ10·v) + θ11  [N]."""
        p = self.pressure(q, T)
        return (self.theta3 * v * np.abs(v) + self.theta4 * p
                + (self.theta8 + self.theta9 * p) * np.arctan(self.theta10 * v) + self.theta11)

    def axle_force(self, q: np.ndarray, v: np.ndarray, a: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Fe from g1 = 0 (inverse dynamics of the imposed stroke) [N]."""
        return self.theta1 * (a + self.theta2) + self.damper_force(q, v, T)

    def temperature_rate(self, q: np.ndarray, v: np.ndarray, T: np.ndarray) -> np.ndarray:
        """dT/dt from g2 = 0 [K/s]; zero for the 1-dof model."""
        if self.model == "1dof":
            return 0 * T
        p = self.pressure(q, T)
        return (-self.theta16 * (1 + self.theta6 * q) * (T + self.theta17)
                + (self.theta4 * p + self.theta11) * v) / self.theta15


@dataclass(frozen=True)
class Actuator:
    """Servo-hydraulic actuator: second-order tracking, velocity limit (hydraulic flow)."""

    bandwidth_hz: float = 25.0
    damping_ratio: float = 0.7
    velocity_limit_m_s: float = 0.6

    def response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Complex frequency response from commanded to actual stroke."""
        wa = 2 * np.pi * self.bandwidth_hz
        w = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
        return wa**2 / (wa**2 - w**2 + 2j * self.damping_ratio * wa * w)


def waveform_harmonics(waveform: str) -> tuple[np.ndarray, np.ndarray]:
    """Harmonic numbers and sine coefficients of a unit-amplitude periodic waveform."""
    if waveform == "sine":
        return np.array([1]), np.array([1.0])
    if waveform == "triangle":
        k = np.arange(1, 200, 2)
        return k, (8 / np.pi**2) * (-1.0) ** ((k - 1) // 2) / k**2
    raise ValueError(f"unknown waveform {waveform!r} (sine or triangle)")


def steady_stroke(spec: ExperimentSpec, actuator: Actuator, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Actual (measured) stroke, velocity and acceleration in the periodic steady state
    of a commanded waveform (phase zero at t = 0), SI."""
    k, b = waveform_harmonics(spec.waveform)
    amp = spec.amplitude_mm * 1e-3
    w = 2 * np.pi * spec.frequency_hz * k
    h = actuator.response(spec.frequency_hz * k)
    phase = np.outer(t, w) + np.angle(h)
    gain = amp * b * np.abs(h)
    q = spec.static_position_mm * 1e-3 + np.sin(phase) @ gain
    v = np.cos(phase) @ (gain * w)
    a = -np.sin(phase) @ (gain * w**2)
    return q, v, a


@dataclass
class SteadyState:
    """Noise-free signals of a periodic steady state or a drop (SI)."""

    t: np.ndarray
    q: np.ndarray           # the damper's stroke coordinate
    stroke: np.ndarray      # measured stroke q + θ12, what the transducer reads
    velocity: np.ndarray
    acceleration: np.ndarray
    temperature: np.ndarray
    pressure: np.ndarray
    axle_force: np.ndarray


def periodic_steady_state(damper: Damper, actuator: Actuator, spec: ExperimentSpec, t: np.ndarray) -> SteadyState:
    """Signals at times ``t`` once the experiment has reached its periodic steady state.

    The gas temperature's periodic state is found by shooting on T(0) = T(period)
    (the energy balance is nearly linear in T, so a few secant steps suffice); the
    record is then integrated from there with tight tolerances.
    """
    period = spec.period_s

    def rhs(time, T):
        stroke, v, _ = steady_stroke(spec, actuator, np.atleast_1d(time))
        return damper.temperature_rate(damper.internal_stroke(stroke), v, T)

    T = np.full(len(t), damper.ambient_k)
    if damper.model == "2dof":
        def one_period(T0: float) -> float:
            sol = solve_ivp(rhs, (0.0, period), [T0], method="DOP853", rtol=1e-11, atol=1e-10)
            return float(sol.y[0, -1])

        x0 = damper.ambient_k
        f0 = one_period(x0) - x0
        x1 = x0 + 1.0
        for _ in range(30):
            f1 = one_period(x1) - x1
            if abs(f1) < 1e-10:
                break
            x0, x1, f0 = x1, x1 - f1 * (x1 - x0) / (f1 - f0), f1
        t0 = np.floor(t[0] / period) * period
        sol = solve_ivp(rhs, (t0, t[-1]), [x1], method="DOP853", rtol=1e-11, atol=1e-10, dense_output=True)
        T = sol.sol(t)[0]
    stroke, v, a = steady_stroke(spec, actuator, t)
    if np.max(np.abs(v)) > actuator.velocity_limit_m_s:
        raise ValueError(f"experiment {spec.letter}: peak velocity {np.max(np.abs(v)):.3f} m/s exceeds the "
                         f"actuator's limit {actuator.velocity_limit_m_s} m/s")
    q = damper.internal_stroke(stroke)
    volume = 1 + damper.theta6 * q  # relative gas volume; the gas laws mean nothing at or below zero
    if np.min(volume) <= 0:
        raise ValueError(f"experiment {spec.letter}: the gas volume 1 + θ6·q vanishes within the stroke "
                         f"(θ6 = {damper.theta6:g} 1/m, q up to {np.max(q) * 1e3:.1f} mm)")
    return SteadyState(t, q, stroke, v, a, T, damper.pressure(q, T), damper.axle_force(q, v, a, T))


def run_from_rest(damper: Damper, actuator: Actuator, spec: ExperimentSpec, t: np.ndarray,
                  ramp_s: float) -> SteadyState:
    """Signals at times ``t`` (uniform, from RUN at t[0]) of an experiment started at
    rest: the damper held at its static position with the gas at ambient temperature,
    the commanded amplitude ramped up linearly over ``ramp_s`` (the controller's ramp
    time), no waiting for the steady state.  The actuator and gas are those of the
    served rig (:class:`StreamingPlant`)."""
    if damper.model != "2dof":
        raise ValueError("a record from rest needs the 2-dof model's gas temperature")
    dt = float(t[1] - t[0])
    position = spec.static_position_mm * 1e-3
    plant = StreamingPlant(damper, actuator, dt, position)
    k, b = waveform_harmonics(spec.waveform)
    tau = t - t[0]
    envelope = np.clip(tau / max(ramp_s, 1e-9), 0.0, 1.0)
    shape = np.sin(np.outer(tau, 2 * np.pi * spec.frequency_hz * k)) @ b
    stroke, v, a, T = plant.advance(position + spec.amplitude_mm * 1e-3 * envelope * shape)
    if np.max(np.abs(v)) > actuator.velocity_limit_m_s:
        raise ValueError(f"experiment {spec.letter}: peak velocity {np.max(np.abs(v)):.3f} m/s exceeds the "
                         f"actuator's limit {actuator.velocity_limit_m_s} m/s")
    q = damper.internal_stroke(stroke)
    return SteadyState(t, q, stroke, v, a, T, damper.pressure(q, T), damper.axle_force(q, v, a, T))


def drop_test(damper: Damper, mass_kg: float, velocity_m_s: float, t: np.ndarray) -> SteadyState:
    """Drop test of docs/models.md: θ1 = M, θ2 = −g, Fe = 0, released at q = 0, T = ambient;
    the stroke channel reads q + θ12.

    ``axle_force`` is the damper force F_d, which the ground load cell reads."""
    theta = dict(damper.theta, theta1=mass_kg, theta2=-G0)
    d = Damper(theta, damper.model)

    def rhs(_, y):
        q, v, T = y
        a = -d.theta2 - (d.damper_force(q, v, T) + stop_force(q)) / d.theta1
        return [v, a, d.temperature_rate(q, v, T)]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, velocity_m_s, d.ambient_k], method="Radau",
                    rtol=1e-9, atol=[1e-10, 1e-9, 1e-7], dense_output=True, max_step=0.01)
    q, v, T = sol.sol(t)
    a = np.gradient(v, t)
    return SteadyState(t, q, d.measured_stroke(q), v, a, T, d.pressure(q, T), d.damper_force(q, v, T) + stop_force(q))


class ActuatorTrack:
    """The servo-hydraulic actuator's response to a setpoint sampled every ``dt_s``,
    discretised exactly for a first-order hold (so that the acceleration is continuous),
    advanced block by block; both physics tiers drive their damper with it."""

    def __init__(self, actuator: Actuator, dt_s: float, position_m: float) -> None:
        wa, zeta = 2 * np.pi * actuator.bandwidth_hz, actuator.damping_ratio
        self._wa, self._zeta = wa, zeta
        den = [1.0, 2 * zeta * wa, wa**2]
        bq, aq, _ = cont2discrete(([wa**2], den), dt_s, method="foh")
        bv, av, _ = cont2discrete(([wa**2, 0.0], den), dt_s, method="foh")
        self._q_filter = (np.ravel(bq), np.ravel(aq))
        self._v_filter = (np.ravel(bv), np.ravel(av))
        self._zq = lfilter_zi(*self._q_filter) * position_m
        self._zv = lfilter_zi(*self._v_filter) * position_m

    def track(self, setpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
        """Stroke, velocity, acceleration at the setpoint's steps, and the filter state
        after them (for :meth:`keep`)."""
        stroke, zq = lfilter(*self._q_filter, setpoint, zi=self._zq)
        v, zv = lfilter(*self._v_filter, setpoint, zi=self._zv)
        a = self._wa**2 * (setpoint - stroke) - 2 * self._zeta * self._wa * v
        return stroke, v, a, (zq, zv)

    def keep(self, state: tuple) -> None:
        self._zq, self._zv = state


class StreamingPlant:
    """The actuator and damper advanced block by block in simulated time.

    The actuator's stroke, setpoints and ``position_m`` are measured strokes (the
    controller's transducer); the gas sees the damper's q = measured − θ12.

    The actuator is discretised exactly for a first-order-hold setpoint (so that the
    acceleration, which enters the axle force through θ1, is continuous); the gas
    temperature uses an exponential integrator of g2 whose nonlinear pressure term is
    iterated to convergence within each block, so the result does not depend on how
    the time line is cut into blocks.  Everything is vectorised over a block.
    """

    def __init__(self, damper: Damper, actuator: Actuator, dt_s: float, position_m: float) -> None:
        self.damper, self.actuator, self.dt = damper, actuator, dt_s
        self._track = ActuatorTrack(actuator, dt_s, position_m)
        self.temperature_k = damper.ambient_k
        self._last = (position_m, 0.0)  # measured stroke and velocity at the last step taken
        self._pending: tuple = (0, None, None, None, None)

    def advance(self, setpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Measured stroke, velocity, acceleration and temperature at the next
        ``len(setpoint)`` steps, the setpoint being sampled at those steps.  Nothing is
        committed until :meth:`commit` (a block cut short by a trip is recomputed)."""
        stroke, v, a, filters = self._track.track(setpoint)
        T = self._temperature(stroke, v)
        self._pending = (len(setpoint), filters, stroke, v, T)
        return stroke, v, a, T

    def commit(self, n: int) -> None:
        """Keep the first ``n`` steps of the last :meth:`advance`."""
        length, filters, stroke, v, T = self._pending
        if n != length:
            raise ValueError("commit a whole block; recompute a shorter one with advance()")
        self._track.keep(filters)
        self.temperature_k = float(T[-1])
        self._last = (float(stroke[-1]), float(v[-1]))

    def _temperature(self, stroke: np.ndarray, v: np.ndarray) -> np.ndarray:
        d = self.damper
        if d.model == "1dof":
            return np.full(stroke.shape, self.temperature_k)
        # dT/dt = -c·(T - Ta) + w(T), c = θ16(1+θ6q)/θ15, w = (θ4 p(q,T) + θ11)·v/θ15.
        qq = d.internal_stroke(np.concatenate(([self._last[0]], stroke)))
        vv = np.concatenate(([self._last[1]], v))
        c = d.theta16 * (1 + d.theta6 * qq) / d.theta15
        cbar = 0.5 * (c[1:] + c[:-1])
        alpha = np.exp(-cbar * self.dt)
        phi = self.dt * np.where(cbar * self.dt > 1e-12, (1 - alpha) / np.maximum(cbar * self.dt, 1e-300), 1.0)
        T = np.full(len(qq), self.temperature_k)
        for _ in range(20):
            w = (d.theta4 * d.pressure(qq, T) + d.theta11) * vv / d.theta15
            beta = (1 - alpha) * d.ambient_k + phi * 0.5 * (w[1:] + w[:-1])
            # T_{k+1} = alpha_k T_k + beta_k, solved as a scan with cumulative products.
            P = np.cumprod(alpha)
            new = np.empty_like(T)
            new[0] = self.temperature_k
            new[1:] = P * (self.temperature_k + np.cumsum(beta / P))
            change = float(np.max(np.abs(new - T)))
            T = new
            if change < 1e-11:
                break
        return T[1:]
