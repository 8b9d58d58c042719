"""The damper under the stroke the rig imposes: the force it takes (the model's input)
and its states, one period of each experiment on the grid, predicted from the model.

The shaker runs in displacement control, while the model takes the force as its input:
an experiment's information (rig.design) and a characteristic computed at an
experiment's conditions (rig.qc) both need the force that makes the model follow the
commanded stroke."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identify.parameters import Parameters
from identify.plans import ExperimentSpec
from rig.planning.settling import GasThermalModel


def imposed_stroke(params: Parameters, specs: Sequence[ExperimentSpec], n: int) -> tuple[np.ndarray, np.ndarray]:
    """The model's inputs (E, n_inputs, n) and states (E, n_states, n) on the grid when the
    rig imposes each experiment's stroke (measured stroke = q + θ12), at ``params``.

    The gas temperature's periodic state is the fixed point of its one-period map,
    which is nearly affine (rig.planning.settling): two integrations and a secant step, then one
    more period from it on the grid; the force then follows from the force balance
    (the model's first residual, linear in its input)."""
    gas = GasThermalModel(params)
    model, theta = gas.model, gas.theta
    static = np.array([e.static_position_mm * 1e-3 for e in specs]) - theta[model.parameter_index("theta12")]
    amplitude = np.array([e.amplitude_mm * 1e-3 for e in specs])
    omega = 2 * np.pi * np.array([e.frequency_hz for e in specs])
    tau = np.arange(n) / n
    phase = 2 * np.pi * tau[None, :]
    q = static[:, None] + amplitude[:, None] * np.sin(phase)
    v = amplitude[:, None] * omega[:, None] * np.cos(phase)
    a = -amplitude[:, None] * omega[:, None] ** 2 * np.sin(phase)
    E = len(specs)
    T = np.zeros((E, n))
    Tdot = np.zeros((E, n))
    if gas.has_thermal_state:
        period = 2 * np.pi / omega

        def stroke(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            ph = omega * t
            return (static + amplitude * np.sin(ph), amplitude * omega * np.cos(ph),
                    -amplitude * omega**2 * np.sin(ph))

        def one_period(T0: np.ndarray, keep: bool = False) -> np.ndarray:
            h = period / n
            Ts, Tk = [T0], T0
            for k in range(n):      # RK4 on the grid's steps (n per period: far finer than the gas's time constant)
                t = k * h
                k1 = gas.temperature_rate(*stroke(t), Tk)
                k2 = gas.temperature_rate(*stroke(t + h / 2), Tk + h / 2 * k1)
                k3 = gas.temperature_rate(*stroke(t + h / 2), Tk + h / 2 * k2)
                k4 = gas.temperature_rate(*stroke(t + h), Tk + h * k3)
                Tk = Tk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                Ts.append(Tk)
            return np.stack(Ts, axis=1) if keep else Tk

        T0 = np.full(E, gas.ambient_k)
        for _ in range(2):          # secant steps on the nearly affine period map (both ends in one integration)
            F0, F1 = one_period(np.stack([T0, T0 + 1.0]))
            T0 = T0 + (F0 - T0) / (1.0 - (F1 - F0))
        T = one_period(T0, keep=True)[:, :n]
        Tdot = gas.temperature_rate(q, v, a, T)
    ns, nin = model.n_states, len(model.input_names)
    X, DX, DDX = (np.zeros((ns, E, n)) for _ in range(3))
    iq = model.state_names.index("q")
    X[iq], DX[iq], DDX[iq] = q, v, a
    if gas.has_thermal_state:
        iT = model.state_names.index("T")
        X[iT], DX[iT] = T, Tdot
    U = np.zeros((nin, E, n))
    g = model.residual(X, DX, DDX, U, theta)[0]
    gu = model.residual_dinput(X, DX, DDX, U, theta)[0, 0]
    U[0] = -g / gu
    return np.moveaxis(U, 1, 0), np.moveaxis(X, 1, 0)


# Grid of a loop energy: the gas temperature and the force are smooth over the period;
# 200 points are within 2e-5 of 800 and a quarter of the time (the characteristic's σ
# takes ten evaluations).
ENERGY_POINTS = 200


def loop_energy_j(params: Parameters, spec: ExperimentSpec, n: int = ENERGY_POINTS) -> float:
    """Energy the damper dissipates per cycle [J] under the experiment's imposed stroke:
    ∮F dq = ∫ F·q̇ dt over one period (the mass's inertia and weight do no net work)."""
    inputs, states = imposed_stroke(params, [spec], n)
    omega = 2 * np.pi * spec.frequency_hz
    velocity = spec.amplitude_mm * 1e-3 * omega * np.cos(2 * np.pi * np.arange(n) / n)
    return float(np.mean(inputs[0, 0] * velocity) / spec.frequency_hz)
