"""Floquet multipliers of a periodic solution from its variational equation in time.

The spectral grid's solution is a trigonometric polynomial, so it is known between the
grid points too.  Integrating the linearised model along it over one period, from the
identity, gives the monodromy matrix; its eigenvalues are the multipliers.  The
discrete one-period map of a difference scheme (BDF2) is no substitute here: the
spectral differentiation matrix couples every grid point to every other, it is no
recursion, and a stepwise map built from BDF2 stencils on a spectral solution damps
what the spectral grid resolves (a multiplier of 0.0097 came out 3.5e-38).

The linearised residual g_x·δx + g_ẋ·δẋ + g_ẍ·δẍ = 0 is written as a first-order system
in the states of order ≥ 1 and the velocities of the second-order ones; algebraic
states (order 0) are solved for at every instant (an index-1 DAE).  The Jacobians come
from the model's own code at the interpolated solution, so a kink is met where it is,
not smeared by interpolating the Jacobian.  LSODA switches to its stiff (BDF) mode
where the damper models' gas spring calls for it and stays explicit elsewhere: Radau
at this tolerance took 50 times longer on a plain oscillator.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from identify.errors import ComputationError
from identify.model import CompiledModel

RTOL = 1e-10  # of the integration; the monodromy's entries are O(1) in state-scaled units
ATOL = 1e-13


class _Trigonometric:
    """Values of periodic grid signals (…, n) at any phase τ ∈ [0, 1) (band-limited interpolation)."""

    def __init__(self, values: np.ndarray):
        n = values.shape[-1]
        coeff = np.fft.rfft(values, axis=-1) / n
        coeff[..., 1:] *= 2.0
        if n % 2 == 0:
            coeff[..., -1] = coeff[..., -1].real / 2.0  # the Nyquist line is real and counted once
        self._coeff = coeff
        self._k = np.arange(coeff.shape[-1])

    def __call__(self, tau: float) -> np.ndarray:
        return (self._coeff @ np.exp(2j * np.pi * self._k * tau)).real


def monodromy(model: CompiledModel, states: np.ndarray, dstates: np.ndarray, ddstates: np.ndarray,
              inputs: np.ndarray, theta: np.ndarray, frequency_hz: float) -> np.ndarray:
    """The one-period map of the linearised model around the periodic solution given on a
    spectral grid (states scaled by the model's state scales, velocities by scale·2πf)."""
    orders = np.array(model.orders)
    dyn = np.flatnonzero(orders >= 1)  # states with a derivative: position part of the phase space
    second = np.flatnonzero(orders == 2)  # ... and those whose velocity is a state too
    algebraic = np.flatnonzero(orders == 0)
    first = np.flatnonzero(orders == 1)
    p = dyn.size + second.size
    if p == 0:
        return np.zeros((0, 0))
    signals = _Trigonometric(np.concatenate([states, dstates, ddstates, inputs]))
    ns = model.n_states
    scale = np.concatenate([model.state_scales[dyn], model.state_scales[second] * 2 * np.pi * frequency_hz])

    # The rows of A that hold the solved derivatives, and its constant part (d(δx)/dt = δv):
    # built once, not at each of the integrator's tens of thousands of calls.
    row = {j: i for i, j in enumerate(dyn)}
    solved_rows = np.array([row[j] for j in first] + list(range(dyn.size, p)), dtype=int)
    constant = np.zeros((p, p))
    for i, j in enumerate(second):
        constant[row[j], dyn.size + i] = 1.0
    rescale = scale[None, :] / scale[:, None]
    wanted = first.size + second.size

    def system(t: float) -> np.ndarray:
        """A(t) of ż = A(t)·z, z = (δx of dyn, δv of second) in scaled units."""
        v = signals(t * frequency_hz)[:, None]
        gx, gdx, gddx = (j[:, :, 0] for j in model.residual_jacobian(v[:ns], v[ns:2 * ns], v[2 * ns:3 * ns],
                                                                   v[3 * ns:], theta))
        # Unknowns at this instant: δẋ of first-order states, δv̇ of second-order ones, δx of algebraic ones.
        M = np.concatenate([gdx[:, first], gddx[:, second], gx[:, algebraic]], axis=1)
        # What the phase-space variables contribute: g_x·δx (dyn states) and g_ẋ·δv (second-order states).
        R = -np.concatenate([gx[:, dyn], gdx[:, second]], axis=1)
        if M.shape == (1, 1) and M[0, 0] != 0:  # one equation (an oscillator): numpy's solve costs 30x a division
            W = R / M[0, 0]
        else:
            try:
                W = np.linalg.solve(M, R)
            except np.linalg.LinAlgError:
                W = None
        if W is None or M.shape == (1, 1) and M[0, 0] == 0:
            raise ComputationError(f"Floquet multipliers: the model's derivative terms are singular at "
                                   f"t = {t:.4g} s (not an index-1 system there)") from None
        rate = constant.copy()
        rate[solved_rows] = W[:wanted]
        return rate * rescale

    def rhs(t: float, z: np.ndarray) -> np.ndarray:
        return (system(t) @ z.reshape(p, p)).ravel()

    def jac(t: float, z: np.ndarray) -> np.ndarray:
        return np.kron(system(t), np.eye(p))

    period = 1.0 / frequency_hz
    sol = solve_ivp(rhs, (0.0, period), np.eye(p).ravel(), method="LSODA", jac=jac, rtol=RTOL, atol=ATOL)
    if not sol.success:
        raise ComputationError(f"Floquet multipliers: the variational equation could not be integrated "
                               f"({sol.message})")
    return sol.y[:, -1].reshape(p, p)


def multipliers(model: CompiledModel, states: np.ndarray, dstates: np.ndarray, ddstates: np.ndarray,
                inputs: np.ndarray, theta: np.ndarray, frequency_hz: float) -> np.ndarray:
    """Eigenvalues of :func:`monodromy`, largest magnitude first."""
    mu = np.linalg.eigvals(monodromy(model, states, dstates, ddstates, inputs, theta, frequency_hz))
    return mu[np.argsort(-np.abs(mu))]
