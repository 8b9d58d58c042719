"""Time integration of a declared model: drop-test prediction and long-interval runs.

The residual equations g(x, ẋ, ẍ, u, θ) = 0 are solved at each right-hand-side call for
each state's highest derivative (Newton on the generated Jacobian; one step when g is
linear in them, as in the damper models), which turns the model into a first-order ODE
for a stiff-capable integrator (Radau by default: the friction law is steep).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from identify.errors import ComputationError
from identify.model import CompiledModel

G0 = 9.81


class IntegrationError(ComputationError):
    """The time integration failed."""


@dataclass
class Trajectory:
    """States, their derivatives, inputs and outputs at the requested times (SI)."""

    t: np.ndarray
    states: np.ndarray  # (n_states, N)
    dstates: np.ndarray
    ddstates: np.ndarray
    inputs: np.ndarray  # (n_inputs, N)
    outputs: np.ndarray  # (n_outputs, N), in model.output_names order


class TransientSimulator:
    """First-order ODE form of a declared model."""

    def __init__(self, model: CompiledModel, theta: np.ndarray):
        self.model = model
        self.theta = np.asarray(theta, dtype=float)
        if any(o == 0 for o in model.orders):
            raise IntegrationError(f"model {model.name!r} has an algebraic state; time integration needs ODEs")
        # Position of each state and of its first derivative in the ODE vector.
        self.slots: list[tuple[int, int | None]] = []
        k = 0
        for order in model.orders:
            self.slots.append((k, k + 1 if order == 2 else None))
            k += order
        self.size = k

    def _split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ns = self.model.n_states
        X = np.empty((ns,) + y.shape[1:])
        DX = np.zeros((ns,) + y.shape[1:])
        for j, (ix, idx) in enumerate(self.slots):
            X[j] = y[ix]
            if idx is not None:
                DX[j] = y[idx]
        return X, DX

    def highest_derivatives(self, X: np.ndarray, DX: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Solve g = 0 for ẍ (order-2 states) and ẋ (order-1 states); returns (DX, DDX)."""
        m, th = self.model, self.theta
        DX = DX.copy()
        DDX = np.zeros_like(X)
        for _ in range(8):
            g = m.residual(X, DX, DDX, U, th)
            _, gdx, gddx = m.residual_jacobian(X, DX, DDX, U, th)
            J = np.stack([gddx[:, j] if o == 2 else gdx[:, j] for j, o in enumerate(m.orders)], axis=1)
            # (n_eq, n_states[, N]) -> batched solve over the time axis when there is one.
            step = np.moveaxis(np.linalg.solve(np.moveaxis(J, (0, 1), (-2, -1)),
                                               np.moveaxis(-g, 0, -1)[..., None])[..., 0], -1, 0)
            for j, o in enumerate(m.orders):
                (DDX if o == 2 else DX)[j] += step[j]
            if np.all(np.abs(step) <= 1e-12 * (1 + np.abs(DDX + DX))):
                break
        return DX, DDX

    def rhs(self, y: np.ndarray, U: np.ndarray) -> np.ndarray:
        X, DX = self._split(y)
        DX, DDX = self.highest_derivatives(X, DX, U)
        dy = np.empty_like(y)
        for j, (ix, idx) in enumerate(self.slots):
            if idx is None:
                dy[ix] = DX[j]
            else:
                dy[ix] = DX[j]
                dy[idx] = DDX[j]
        return dy

    def run(self, x0: np.ndarray, dx0: np.ndarray, inputs: Callable[[float | np.ndarray], np.ndarray], t: np.ndarray,
            method: str = "Radau", rtol: float = 1e-8) -> Trajectory:
        """Integrate from states ``x0`` and first derivatives ``dx0`` (used for order-2
        states) and sample at times ``t`` (starting at t[0]).  ``inputs(t)`` takes a time
        or an array of times and returns (n_inputs,) or (n_inputs, len(t))."""
        m = self.model
        y0 = np.empty(self.size)
        for j, (ix, idx) in enumerate(self.slots):
            y0[ix] = x0[j]
            if idx is not None:
                y0[idx] = dx0[j]
        atol = np.empty(self.size)
        for j, (ix, idx) in enumerate(self.slots):
            atol[ix] = 1e-6 * m.state_scales[j]
            if idx is not None:
                atol[idx] = 1e-5 * m.state_scales[j]
        from scipy.integrate import solve_ivp  # only prediction needs it; fit's start-up stays short

        sol = solve_ivp(lambda tt, y: self.rhs(y, inputs(tt)), (t[0], t[-1]), y0, method=method,
                        rtol=rtol, atol=atol, dense_output=True)
        if not sol.success:
            raise IntegrationError(f"time integration of model {m.name!r} failed at t = {sol.t[-1]:.4g} s: "
                                   f"{sol.message}")
        Y = sol.sol(t)
        X, DX = self._split(Y)
        U = np.broadcast_to(np.asarray(inputs(t), dtype=float).reshape(len(m.input_names), -1),
                            (len(m.input_names), len(t)))
        DX, DDX = self.highest_derivatives(X, DX, U)
        out = m.output(X, DX, DDX, U, self.theta)
        return Trajectory(t, X, DX, DDX, U, out)


def drop_test(model: CompiledModel, theta: np.ndarray, mass_kg: float, velocity_m_s: float,
              t: np.ndarray) -> Trajectory:
    """The drop test of docs/models.md: θ1 = M, θ2 = −9.81, Fe = 0, released at q = 0 with
    velocity v0, gas at ambient temperature (the model's static guess)."""
    names = model.parameter_names
    if "theta1" not in names or "theta2" not in names:
        raise IntegrationError(f"model {model.name!r} is not a damper model (no theta1/theta2): no drop test")
    th = np.array(theta, dtype=float)
    th[names.index("theta1")] = mass_kg
    th[names.index("theta2")] = -G0
    sim = TransientSimulator(model, th)
    x0 = model.static_guess(th)
    x0[0] = 0.0
    dx0 = np.zeros_like(x0)
    dx0[0] = velocity_m_s
    n_in = len(model.input_names)
    return sim.run(x0, dx0, lambda tt: np.zeros((n_in,) + np.shape(tt)), t)
