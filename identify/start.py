"""Where periodic Newton starts when there is no earlier solution, chosen automatically.

Starts, in the order they are tried:

``measured``
    the fitted outputs as measured, low-passed to their first harmonics and mapped back
    to states point by point.  Only in a fit (where there are measurements), and only
    where those outputs determine every state; Newton then starts in the right phase
    of the motion, which the steep friction of the damper needs: from the static guess
    every velocity is zero, where arctan(θ10·q̇) is steepest, and Newton spends half a
    fit's iterations finding the phase of the friction force.
``static``
    the static equilibrium for the mean input, repeated over the period (the paper's
    start).  First when that equilibrium is isolated (a regular static Jacobian).
``transient``
    a few periods of time integration from rest — the grid's BDF2 recursion marched
    forward, one small Newton solve per step — ending where consecutive periods
    agree; Newton starts from the last period.  First for a continuum of rest states
    (hysteresis: Bouc-Wen's z holds any value at rest), where a constant start leaves
    the periodic Jacobian singular too, and the most robust start for dissipative models.
``linear``
    harmonic balance of the model linearised at rest: one small complex solve per
    harmonic, exact for linear models.
``continuation``
    continuation in the input amplitude, from the linear start at a quarter of it.

Each start is followed by Newton on the periodic equations; when that fails the next
start is tried, and the solution says which one succeeded.  A continuum of static
equilibria (a singular static Jacobian) gets the least-norm solution in state-scaled
variables instead of a failure.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from identify.differentiation import BDF2_D1, BDF2_D2, Grid
from identify.errors import ComputationError
from identify.model import CompiledModel
from identify.solution import PeriodicSolution

STARTS = ("measured", "static", "transient", "linear", "continuation")
RANK_TOLERANCE = 1e-12  # singular values of the scaled static Jacobian below this (relative) span a continuum
TRANSIENT_PERIODS = 4  # at most; integration stops earlier once consecutive periods agree
SETTLED = 1e-3  # period-to-period change of each state, relative to its range over the period
STEP_ITERATIONS = 8  # Newton iterations per time step
# Harmonics of the measured outputs in the measured start (beyond the excited lines): 10
# halve the cold Newton iterations of the standard set (258 -> 117, bench_fit); all 400 of the
# grid carry the noise into the velocities and cost 158.
MEASURED_HARMONICS = 10
INVERSION_ITERATIONS = 20  # point-wise Newton from outputs to states (the damper's needs 3)
INVERSION_TOLERANCE = 1e-3  # of each state's scale: a start, which periodic Newton corrects anyway
# Newton iterations allowed from the measured start before the next start is tried: where
# the parameters cannot reach the measured motion (a gas spring that would collapse at
# the measured stroke), Newton stalls there, and the static start takes at most 30.
MEASURED_NEWTON = 30


class StartError(ComputationError):
    """No start led Newton to the periodic solution."""


@dataclass(frozen=True)
class Measured:
    """Fitted outputs as measured on the data grid: what the measured start maps back."""

    outputs: list[int]  # model output indices
    values: np.ndarray  # (len(outputs), n) SI


@dataclass(frozen=True)
class RestState:
    """The static equilibrium for constant inputs; ``unique`` is false where the static
    Jacobian is singular and ``states`` is the least-norm member of a continuum."""

    states: np.ndarray  # (n_states,)
    unique: bool


def rest_state(model: CompiledModel, inputs: np.ndarray, theta: np.ndarray, tolerance: float) -> RestState | None:
    """Static equilibrium (all derivatives zero) for constant inputs (n_inputs,), or None.

    Newton with step halving from the model's static guess; where the Jacobian is
    singular the step is the least-norm one in state-scaled variables, which stays on
    the continuum's member nearest the guess."""
    x = model.static_guess(theta)
    zero = np.zeros_like(x)
    scales = model.state_scales
    unique = True
    for _ in range(100):
        g = model.residual(x, zero, zero, inputs, theta)
        gx = model.residual_jacobian(x, zero, zero, inputs, theta)[0]
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(gx))):
            return None
        u, s, vt = np.linalg.svd(gx * scales)
        rank = int(np.sum(s > RANK_TOLERANCE * s[0])) if s[0] > 0 else 0
        if rank == len(x):
            dx = -np.linalg.solve(gx, g)
        else:
            unique = False
            dx = -scales * (vt[:rank].T @ ((u[:, :rank].T @ g) / s[:rank]))
        if np.all(np.abs(dx) <= tolerance * scales):
            return RestState(x + dx, unique)
        merit = float(g @ g)
        lam = 1.0
        while lam > 1e-6:
            xt = x + lam * dx
            gt = model.residual(xt, zero, zero, inputs, theta)
            if np.all(np.isfinite(gt)) and float(gt @ gt) < merit:
                break
            lam /= 2
        x = xt
    return None


def transient_start(model: CompiledModel, grid: Grid, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray,
                    rest: np.ndarray) -> np.ndarray:
    """States over the last of a few periods integrated from ``rest`` (n_states, n).

    The grid's BDF2 stencils marched forward in time (step 1/(f·n)): A-stable, so stiff
    friction laws do not limit the step, and strongly damped at the grid's highest
    frequencies, which only the following Newton solve needs to get right."""
    m, n, f = model, grid.points, frequency_hz
    ns = m.n_states
    h = 1.0 / n
    c1, c2 = BDF2_D1 * f / h, BDF2_D2 * f * f / h**2
    scales = m.state_scales
    X = np.empty((ns, n))
    history = np.repeat(rest[:, None], 3, axis=1)  # x(τ_{μ-1}), x(τ_{μ-2}), x(τ_{μ-3})
    previous_end = None
    for _ in range(TRANSIENT_PERIODS):
        for mu in range(n):  # a recursion: each step needs the last (not a hot path: once per start)
            x1, x2, x3 = history[:, 0], history[:, 1], history[:, 2]
            past1 = c1[1] * x1 + c1[2] * x2
            past2 = c2[1] * x1 + c2[2] * x2 + c2[3] * x3
            x = 2 * x1 - x2  # linear extrapolation
            u = inputs[:, mu]
            for _ in range(STEP_ITERATIONS):
                dx, ddx = c1[0] * x + past1, c2[0] * x + past2
                g = m.residual(x, dx, ddx, u, theta)
                gx, gdx, gddx = m.residual_jacobian(x, dx, ddx, u, theta)
                step = np.linalg.solve(gx + c1[0] * gdx + c2[0] * gddx, g)
                x = x - step
                if not np.all(np.isfinite(x)):
                    raise StartError(f"time integration from rest diverged at τ = {mu / n:.3f} of a period")
                if np.all(np.abs(step) <= 1e-10 * scales):
                    break
            X[:, mu] = x
            history = np.column_stack([x, x1, x2])
        end = X[:, -1].copy()
        span = np.ptp(X, axis=1) + 1e-12 * scales
        if previous_end is not None and np.all(np.abs(end - previous_end) <= SETTLED * span):
            break
        previous_end = end
    return X


def linear_start(model: CompiledModel, grid: Grid, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray,
                 rest: np.ndarray) -> np.ndarray:
    """Periodic response of the model linearised at ``rest`` (n_states, n): per harmonic
    (∂g/∂x + D1·∂g/∂ẋ + D2·∂g/∂ẍ)·X_k = −∂g/∂u·U_k with the grid's own derivative symbols,
    least-norm where that matrix is singular (the mean of a continuum)."""
    m, n = model, grid.points
    mean = inputs.mean(axis=1)
    zero = np.zeros_like(rest)
    gx, gdx, gddx = m.residual_jacobian(rest, zero, zero, mean, theta)
    gu = m.residual_dinput(rest, zero, zero, mean, theta)
    impulse = np.zeros(n)
    impulse[0] = 1.0
    s1, s2 = (np.fft.rfft(d) for d in grid.derivatives(impulse, frequency_hz))  # the grid's symbols
    A = gx[None] + s1[:, None, None] * gdx[None] + s2[:, None, None] * gddx[None]  # (harmonics, neq, ns)
    rhs = np.fft.rfft(inputs - mean[:, None], axis=1).T @ gu.T  # (harmonics, neq)
    scaled = np.linalg.pinv(A * m.state_scales, rcond=RANK_TOLERANCE)  # least norm in scaled variables
    Xk = -m.state_scales * np.einsum("kje,ke->kj", scaled, rhs)
    return rest[:, None] + np.fft.irfft(Xk.T, n=n, axis=1)


def measured_start(model: CompiledModel, grid: Grid, inputs: np.ndarray, theta: np.ndarray, measured: Measured,
                   first: np.ndarray | None = None) -> np.ndarray:
    """States whose outputs are the measured ones (n_states, points): the measurements
    low-passed to their first MEASURED_HARMONICS harmonics and the excited lines, then
    inverted point by point with Newton, all points at once, to INVERSION_TOLERANCE.
    Newton starts from ``first``: the states of an earlier inversion (n_states, points),
    which saves the checks, or a rest state (n_states,); default the model's static guess.
    Raises :class:`StartError` where the outputs do not determine every state (a
    Bouc-Wen z, a 1-output fit of a 2-state model) or depend on the states' derivatives."""
    from identify.preparation import excited_lines

    m, n = model, grid.points
    spectrum = np.fft.rfft(grid.refine(measured.values), axis=1)
    keep = max(MEASURED_HARMONICS, int(excited_lines(inputs).max(initial=0)))
    inputs = grid.refine(inputs)  # data grid -> model grid, where the states are (an oversampled grid)
    spectrum[:, keep + 1:] = 0.0
    target = np.fft.irfft(spectrum, n=n, axis=1)
    # Outputs in their own sizes (m beside Pa) and states in theirs: the rank test and the
    # steps then see every output and state alike.
    weights = 1.0 / np.maximum(np.sqrt(np.mean(target**2, axis=1)), 1e-300)
    first = model.static_guess(theta) if first is None else first
    checked = first.ndim == 2
    X = first if checked else np.repeat(first[:, None], n, axis=1)
    zero = np.zeros_like(X)
    scales = m.state_scales
    for _ in range(INVERSION_ITERATIONS):
        hx, hdx, hddx = (h[measured.outputs] for h in m.output_jacobian(X, zero, zero, inputs, theta))
        H = np.moveaxis(weights[:, None, None] * hx * scales[None, :, None], -1, 0)  # (points, outputs, states)
        if not checked:
            if np.any(hdx) or np.any(hddx):
                raise StartError("the fitted outputs depend on the states' derivatives")
            lam = np.linalg.eigvalsh(np.swapaxes(H, 1, 2) @ H)  # squared singular values, ascending
            if H.shape[1] < H.shape[2] or np.any(lam[:, 0] <= RANK_TOLERANCE * lam[:, -1]):
                raise StartError("the fitted outputs do not determine every state")
            checked = True
        r = np.moveaxis(weights[:, None] * (target - m.output(X, zero, zero, inputs, theta)[measured.outputs]), -1, 0)
        if H.shape[1] == H.shape[2]:
            dz = np.linalg.solve(H, r[..., None])[..., 0]  # (points, states)
        else:  # more outputs than states: least squares
            HT = np.swapaxes(H, 1, 2)
            dz = np.linalg.solve(HT @ H, HT @ r[..., None])[..., 0]
        dX = dz.T * scales[:, None]
        X = X + dX
        if not np.all(np.isfinite(X)):
            break
        if np.all(np.abs(dX) <= INVERSION_TOLERANCE * scales[:, None]):
            return X
    raise StartError(f"the measured outputs could not be mapped to states in {INVERSION_ITERATIONS} iterations")


Newton = Callable[..., PeriodicSolution]  # (inputs, start states[, most iterations]) -> solution


def continuation(newton: Newton, inputs: np.ndarray,
                 first_guess: Callable[[np.ndarray], np.ndarray]) -> PeriodicSolution:
    """Newton along the inputs mean + s·(inputs − mean), s from 1/4 to 1, each solve
    started from the last; the step in s halves on failure, down to 1/64."""
    mean = inputs.mean(axis=1, keepdims=True)
    s, ds = 0.0, 0.25
    states: np.ndarray | None = None
    while True:
        trial = min(1.0, s + ds)
        scaled = mean + trial * (inputs - mean)
        try:
            sol = newton(scaled, first_guess(scaled) if states is None else states)
        except (ComputationError, np.linalg.LinAlgError) as exc:
            ds /= 2
            if ds < 1.0 / 64:
                raise StartError(f"amplitude continuation stalled at {s:.3g} of the input") from exc
            continue
        if trial == 1.0:
            return sol
        s, states, ds = trial, sol.states, min(2 * ds, 0.5)


def solve_from_rest(model: CompiledModel, grid: Grid, newton: Newton, inputs: np.ndarray, frequency_hz: float,
                    theta: np.ndarray, tolerance: float, order: tuple[str, ...] | None = None,
                    measured: Measured | None = None) -> tuple[PeriodicSolution, str]:
    """The periodic solution from the first start (in ``order``, else chosen from the
    rest state and whether there are ``measured`` outputs) that Newton converges from;
    and that start's name.  Raises :class:`StartError` listing what each start did."""
    rest = rest_state(model, inputs.mean(axis=1), theta, tolerance)
    failures = []
    if order is None:
        order = STARTS if rest is not None and rest.unique else ("measured", "transient", "linear", "continuation")
        if measured is None:  # not a fit: nothing measured to start from
            order = tuple(name for name in order if name != "measured")
    elif measured is None and "measured" in order:
        failures.append("measured start: no measured outputs (only a fit has them)")
        order = tuple(name for name in order if name != "measured")
    if rest is None:
        # Time integration and the linearisation need a state to start from, not an equilibrium.
        failures.append(f"static start: no static equilibrium found for the mean input {inputs.mean(axis=1)}")
        order = tuple(name for name in order if name != "static")
        x0 = model.static_guess(theta)
    else:
        x0 = rest.states
    f = frequency_hz

    def from_measured() -> PeriodicSolution:
        assert measured is not None  # left out of the order above otherwise
        return newton(inputs, measured_start(model, grid, inputs, theta, measured, x0), MEASURED_NEWTON)

    makers: dict[str, Callable[[], PeriodicSolution]] = {
        "measured": from_measured,
        "static": lambda: newton(inputs, np.repeat(x0[:, None], grid.points, axis=1)),
        "transient": lambda: newton(inputs, transient_start(model, grid, inputs, f, theta, x0)),
        "linear": lambda: newton(inputs, linear_start(model, grid, inputs, f, theta, x0)),
        "continuation": lambda: continuation(newton, inputs, lambda u: linear_start(model, grid, u, f, theta, x0)),
    }
    for name in order:
        try:
            return makers[name](), name
        except (ComputationError, np.linalg.LinAlgError) as exc:
            failures.append(f"{name} start: {exc}")
    raise StartError("; ".join(failures))
