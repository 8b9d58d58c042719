"""Periodic equilibrium of a model driven by a periodic input, and its sensitivities.

The residual equations are collocated on the n-point phase grid of one period; the
resulting n·n_states algebraic equations are solved by Newton's method with step
halving, started from the static equilibrium for the mean input or another start of
:mod:`identify.start` (or warm-started from an earlier solution).  The factorised
Jacobian at the solution gives the parameter sensitivities dz/dθ = −(∂G/∂z)⁻¹·∂G/∂θ at
the cost of back-substitutions only.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from scipy.linalg import LinAlgWarning

from identify.differentiation import BDF2_D1, BDF2_D2, Factorization, Grid
from identify.errors import ComputationError, InputError
from identify.model import CompiledModel
from identify.solution import PeriodicSolution
from identify.start import STARTS, Measured, StartError, rest_state, solve_from_rest

CHORD_SIZE = 1e4  # a full Newton step at most this many tolerances long is confirmed by a chord step
NEWTON_RTOL = 1e-3  # relative accuracy of a matrix-free Newton step (1e-6: 20 % more GMRES iterations in a fit)


def damped_step(at: tuple[np.ndarray, np.ndarray, np.ndarray], step: tuple[np.ndarray, np.ndarray, np.ndarray],
                weights: np.ndarray, merit: float,
                residual: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Newton's step damped by halving (Armijo, down to 1/1024) until the weighted sum of
    squared residuals falls: ``at`` the states and their two derivatives, ``step`` the
    same three of the full step.  Returns the factor and the states, derivatives,
    residual and merit there (the periodic and the whole-record solver both take it)."""
    (X, DX, DDX), (dX, d1, d2) = at, step
    lam = 1.0
    while True:
        Xt, D1, D2 = X + lam * dX, DX + lam * d1, DDX + lam * d2
        Gt = residual(Xt, D1, D2)
        trial = float(np.sum((weights * Gt) ** 2))
        if (np.isfinite(trial) and trial <= (1 - 1e-4 * lam) * merit) or lam < 1.0 / 1024:
            return lam, Xt, D1, D2, Gt, trial
        lam /= 2


class ConvergenceError(ComputationError):
    """Newton's method did not find the periodic (or static) solution."""

    def __init__(self, message: str, label: str = "", iterations: int = 0, residual: float = float("nan")):
        super().__init__(message)
        self.label = label
        self.iterations = iterations
        self.residual = residual


class PeriodicSolver:
    """Newton solver for periodic equilibria of one model on one grid."""

    def __init__(self, model: CompiledModel, grid: Grid, max_iterations: int = 60, tolerance: float = 1e-9,
                 starts: tuple[str, ...] | None = None):
        unknown = set(starts or ()) - set(STARTS)
        if unknown:
            raise InputError(f"unknown periodic starts {', '.join(sorted(unknown))}: use {', '.join(STARTS)}")
        self.model = model
        self.grid = grid
        self.max_iterations = max_iterations
        self.tolerance = tolerance
        self.starts = starts  # order of the starts tried; None: chosen from the rest state
        self.starts_used: dict[str, str] = {}  # label -> start of its last solve from rest
        self._last_sensitivities: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}

    # ----------------------------------------------------------------------------------
    def static_equilibrium(self, inputs: np.ndarray, theta: np.ndarray, label: str = "") -> np.ndarray:
        """States at rest (all derivatives zero) for constant inputs (n_inputs,); the
        least-norm one where rest states form a continuum."""
        rest = rest_state(self.model, inputs, theta, self.tolerance)
        if rest is None:
            raise ConvergenceError(f"{label or 'experiment'}: no static equilibrium found for the mean input {inputs}",
                                   label)
        return rest.states

    # ----------------------------------------------------------------------------------
    def _equation_weights(self, jac: tuple[np.ndarray, np.ndarray, np.ndarray], f: float) -> np.ndarray:
        gx, gdx, gddx = jac
        w = 2 * np.pi * f
        size = ((np.abs(gx).mean(-1) + w * np.abs(gdx).mean(-1) + w * w * np.abs(gddx).mean(-1))
                @ self.model.state_scales)
        return 1.0 / np.maximum(size, 1e-300)

    def solve(self, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray,
              start: np.ndarray | None = None, label: str = "", measured: Measured | None = None,
              max_iterations: int | None = None) -> PeriodicSolution:
        """Periodic solution for data-grid inputs (n_inputs, n) at the given frequency.

        ``start`` (n_states, points) warm-starts Newton; otherwise the starts of
        :mod:`identify.start` are tried in turn (the ``measured`` outputs mapped to
        states where given, then the static equilibrium for the mean input where it is
        unique), the one that worked is recorded in the
        solution and in ``starts_used[label]``.  On an oversampled grid the start is
        the solution on the data's grid, refined.  ``max_iterations`` bounds Newton from
        a given ``start`` (default the solver's).  Raises :class:`ConvergenceError`
        naming ``label``.  The solution's arrays are on the model grid.
        """
        # Unphysical trial parameters (a line-search step too far) give NaNs or singular
        # Jacobians; they end in ConvergenceError, which the caller handles, so numpy's
        # and scipy's warnings about them would only be noise.
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", LinAlgWarning)
            refined = self.grid.refine(inputs)
            if start is not None:
                return self._solve(refined, frequency_hz, theta, start, label, max_iterations)
            if self.grid.oversample > 1:
                coarse = PeriodicSolver(self.model, self.grid.base(), self.max_iterations, self.tolerance,
                                        self.starts).solve(inputs, frequency_hz, theta, label=label,
                                                           measured=measured)
                sol = self._solve(refined, frequency_hz, theta, self.grid.refine(coarse.states), label)
                name = coarse.start
            else:
                try:
                    sol, name = solve_from_rest(
                        self.model, self.grid,
                        lambda u, x, most=None: self._solve(u, frequency_hz, theta, x, label, most), refined,
                        frequency_hz, theta, self.tolerance, self.starts, measured)
                except StartError as exc:
                    raise ConvergenceError(f"{label or 'experiment'}: no periodic solution from any start ({exc})",
                                           label) from exc
            sol.start = name
            self.starts_used[label] = name
            return sol

    def _solve(self, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray,
               start: np.ndarray, label: str, max_iterations: int | None = None) -> PeriodicSolution:
        m, grid, f = self.model, self.grid, frequency_hz
        ns, n = m.n_states, grid.points
        X = np.array(start, dtype=float, copy=True)
        tol = self.tolerance * m.state_scales[:, None]
        DX, DDX = grid.derivatives(X, f)
        G = m.residual(X, DX, DDX, inputs, theta)
        weights = None
        merit = np.inf
        last_full_step = np.nan  # scaled size of the previous step, when it was a full one
        most = self.max_iterations if max_iterations is None else max_iterations

        def converged(dX: np.ndarray, dD1: np.ndarray, dD2: np.ndarray, fac: Factorization) -> PeriodicSolution:
            """The solution one last (Newton or chord) step on, with the factorisation it keeps."""
            Xc, DXc, DDXc = X + dX, DX + dD1, DDX + dD2
            rms = float(np.sqrt(np.mean((weights * m.residual(Xc, DXc, DDXc, inputs, theta)) ** 2)))
            return PeriodicSolution(label, f, inputs, Xc, DXc, DDXc, it + 1, rms, fac)

        for it in range(most + 1):
            jac = m.residual_jacobian(X, DX, DDX, inputs, theta)
            if weights is None:
                weights = self._equation_weights(jac, f)[:, None]
                merit = float(np.sum((weights * G) ** 2))
            if not np.isfinite(merit):
                break
            try:
                fac = grid.factorize(*jac, f, m.state_scales)
                # Newton judges its own convergence: a matrix-free step solved roughly costs a
                # little contraction per iteration, far less than the Krylov iterations saved.
                step = fac.krylov.solve(G.ravel(), NEWTON_RTOL) if fac.krylov else fac.solve(G.ravel())
                dX = -step.reshape(ns, n)
            except np.linalg.LinAlgError:  # a singular Newton matrix (banded LU) or GMRES stalled
                break
            if not np.all(np.isfinite(dX)):
                break
            # Differentiation is linear: the trial points' derivatives are combinations.
            dD1, dD2 = grid.derivatives(dX, f)
            # Converged when the step is below the tolerance, or when the contraction Θ of
            # two full steps says the error left after this one, Θ·|dX|, is (Deuflhard's
            # a-posteriori estimate): that saves the last factorisation, which would only
            # confirm it.
            size = float(np.max(np.abs(dX) / tol))
            contraction = size / last_full_step  # nan (no estimate) after a damped or no step
            if size <= 1.0 or (contraction < 0.5 and contraction * size <= 1.0):
                return converged(dX, dD1, dD2, fac)
            if it == most:
                break
            lam, Xt, D1, D2, Gt, trial = damped_step((X, DX, DDX), (dX, dD1, dD2), weights, merit,
                                                     lambda X, D1, D2: m.residual(X, D1, D2, inputs, theta))
            if not np.isfinite(trial):
                break
            last_full_step = size if lam == 1.0 else np.nan
            X, DX, DDX, G, merit = Xt, D1, D2, Gt, trial
            if lam == 1.0 and size <= CHORD_SIZE and fac.krylov is None:
                # After a small full step the error left is about its square: a step with the
                # same factorisation (a chord step) usually shows it below the tolerance, for
                # a back-substitution instead of the factorisation a Newton step would cost.
                # The solution then keeps a Jacobian one small step old, which changes its
                # sensitivities by about CHORD_SIZE·tolerance, relatively.
                chord = -fac.solve(G.ravel()).reshape(ns, n)
                if np.all(np.isfinite(chord)) and float(np.max(np.abs(chord) / tol)) <= 1.0:
                    return converged(chord, *grid.derivatives(chord, f), fac)
        rms = float(np.sqrt(merit / (ns * n))) if np.isfinite(merit) else float("nan")
        raise ConvergenceError(
            f"{label or 'experiment'}: periodic solution did not converge in {it} Newton iterations "
            f"(scaled residual {rms:.3g}, f = {f:g} Hz, n = {n}, scheme {grid.scheme})",
            label, it, rms,
        )

    # ----------------------------------------------------------------------------------
    def state_sensitivities(self, sol: PeriodicSolution, theta: np.ndarray, indices: list[int]) -> np.ndarray:
        """dX/dθ_k for the listed parameter indices: (n_states, points, k), model grid."""
        m, n = self.model, self.grid.points
        gth = m.residual_dtheta(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)[:, indices, :]
        rhs = np.transpose(gth, (0, 2, 1)).reshape(-1, len(indices))
        krylov = sol.factorization.krylov
        if krylov is None:
            return -sol.factorization.solve(rhs).reshape(m.n_states, n, len(indices))
        # The last sensitivities of this experiment start GMRES: between a fit's iterations
        # they change by the step, and the solve needs that much fewer iterations.
        key = (sol.label, tuple(indices))
        solution = krylov.solve(rhs, guess=self._last_sensitivities.get(key))
        self._last_sensitivities[key] = solution
        return -solution.reshape(m.n_states, n, len(indices))

    def floquet_multipliers(self, sol: PeriodicSolution, theta: np.ndarray) -> np.ndarray:
        """Floquet multipliers of the periodic solution, largest magnitude first (|μ| < 1
        for all: stable; Newton can also land on an unstable orbit).  On the bdf2 grid the
        eigenvalues of the one-period map of the linearised BDF2 recursion around it.

        The recursion A0·x_μ + A1·x_{μ-1} + A2·x_{μ-2} + A3·x_{μ-3} = 0 has 3·n_states
        roots; the stencils' parasitic roots (1/3 and 1/2 per step) vanish over a period,
        so the Σ orders largest are the physical multipliers.  The spectral scheme has no
        such recursion: its multipliers come from the variational equation integrated in
        time along the solution (:mod:`identify.floquet`)."""
        m, grid, f = self.model, self.grid, sol.frequency_hz
        if grid.scheme == "spectral":
            from identify import floquet  # scipy's integrators: only when asked for

            return floquet.multipliers(m, sol.states, sol.dstates, sol.ddstates, sol.inputs, theta, f)
        gx, gdx, gddx = m.residual_jacobian(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        h = 1.0 / grid.points
        c1 = BDF2_D1 / h * f
        c2 = BDF2_D2 / h**2 * f * f
        A = c1[:, None, None, None] * gdx[None] + c2[:, None, None, None] * gddx[None]  # (4, neq, ns, n)
        A[0] += gx
        ns = m.n_states
        blocks = np.moveaxis(A, -1, 0)  # (n, 4, neq, ns)
        # x_μ = -A0⁻¹ (A1 x_{μ-1} + A2 x_{μ-2} + A3 x_{μ-3}), all steps solved at once.
        top = -np.linalg.solve(blocks[:, 0], np.concatenate([blocks[:, 1], blocks[:, 2], blocks[:, 3]], axis=2))
        step = np.zeros((grid.points, 3 * ns, 3 * ns))
        step[:, :ns] = top
        step[:, ns:2 * ns, :ns] = np.eye(ns)
        step[:, 2 * ns:, ns:2 * ns] = np.eye(ns)
        monodromy = np.eye(3 * ns)
        for mat in step:  # n small matrix products: not a hot path (once per experiment, on request)
            monodromy = mat @ monodromy
        mu = np.linalg.eigvals(monodromy)
        mu = mu[np.argsort(-np.abs(mu))]
        return mu[:sum(m.orders)]

    def input_response(self, sol: PeriodicSolution, theta: np.ndarray, outputs: list[int],
                       du: np.ndarray) -> np.ndarray:
        """Output perturbations (len(outputs), n, k) caused by input perturbations du
        (n_inputs, n, k), data grid: dŷ/du applied to k vectors (how input noise reaches
        the outputs).  An input's derivatives that the model uses move with it."""
        m, grid = self.model, self.grid
        du = grid.refine(m.expand_inputs(du, sol.frequency_hz, axis=1), axis=1)
        args = (sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        gu = m.residual_dinput(*args)  # (neq, nin, n): each input sample enters its own equations
        rhs = np.einsum("ijn,jnk->ink", gu, du)
        k = du.shape[2]
        dX = -sol.factorization.solve(rhs.reshape(-1, k)).reshape(m.n_states, grid.points, k)
        hu = m.output_dinput(*args)[outputs]  # (nout, nin, n)
        return grid.sample(self._output_response(sol, theta, dX, outputs) + np.einsum("ojn,jnk->onk", hu, du), axis=1)

    def input_adjoint(self, sol: PeriodicSolution, theta: np.ndarray, outputs: list[int], w: np.ndarray) -> np.ndarray:
        """(dŷ/du)ᵀ applied to output weights w (len(outputs), n, k): (n_inputs, n, k),
        data grid.

        One transposed solve with k right-hand sides instead of n per input."""
        m, f = self.model, sol.frequency_hz
        w = self.grid.sample_transposed(w, axis=1)
        args = (sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        hx, hdx, hddx = m.output_jacobian(*args)
        wk = np.moveaxis(w, 1, -1)  # (nout, k, n)
        lam = np.einsum("ojn,okn->jkn", hx[outputs], wk)
        d1, d2 = self.grid.derivatives_transposed(np.einsum("ojn,okn->jkn", hdx[outputs], wk),
                                                  np.einsum("ojn,okn->jkn", hddx[outputs], wk), f)
        lam = np.moveaxis(lam + d1 + d2, -1, 1)  # (n_states, n, k)
        k = w.shape[2]
        mu = sol.factorization.solve_transposed(lam.reshape(-1, k)).reshape(m.n_states, self.grid.points, k)
        gu = m.residual_dinput(*args)
        hu = m.output_dinput(*args)[outputs]
        adjoint = -np.einsum("ijn,ink->jnk", gu, mu) + np.einsum("ojn,onk->jnk", hu, w)
        return m.collapse_inputs(self.grid.refine_transposed(adjoint, axis=1), f, axis=1)

    def _output_response(self, sol: PeriodicSolution, theta: np.ndarray, dX: np.ndarray,
                         outputs: list[int]) -> np.ndarray:
        """Output perturbations (len(outputs), points, k) caused by state perturbations dX
        (n_states, points, k), model grid."""
        dDX, dDDX = self.grid.apply_derivative_operators(dX, sol.frequency_hz)
        hx, hdx, hddx = self.model.output_jacobian(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        return (np.einsum("ojn,jnk->onk", hx[outputs], dX)
                + np.einsum("ojn,jnk->onk", hdx[outputs], dDX)
                + np.einsum("ojn,jnk->onk", hddx[outputs], dDDX))

    def outputs(self, sol: PeriodicSolution, theta: np.ndarray, outputs: list[int]) -> np.ndarray:
        """Model outputs on the data grid (len(outputs), n), SI."""
        y = self.model.output(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        return self.grid.sample(y[outputs])

    def sensitivities(self, sol: PeriodicSolution, theta: np.ndarray, indices: list[int],
                      outputs: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """dX/dθ_k (n_states, points, k) on the model grid and dŷ/dθ_k (len(outputs), n, k)
        on the data grid."""
        dX = self.state_sensitivities(sol, theta, indices)
        hth = self.model.output_dtheta(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        dY = self._output_response(sol, theta, dX, outputs) + np.transpose(hth[outputs][:, indices, :], (0, 2, 1))
        return dX, self.grid.sample(dY, axis=1)

    def output_sensitivities(self, sol: PeriodicSolution, theta: np.ndarray, indices: list[int],
                             outputs: list[int]) -> np.ndarray:
        """dŷ/dθ_k on the data grid: (len(outputs), n, k)."""
        return self.sensitivities(sol, theta, indices, outputs)[1]
