"""Matrix-free Newton–Krylov solves on the spectral grid, for thousands of harmonics.

The spectral Newton matrix J = A0 + A1·D1 + A2·D2 (A diagonal in time: the model's
∂g/∂x, ∂g/∂ẋ, ∂g/∂ẍ at each grid point; D the dense Fourier differentiation matrices)
costs O(n²) memory and O(n³) to factorise as a dense matrix: 8192 unknowns took
minutes.  Here J is only applied, with FFTs, O(n log n) per product, and J·x = b is
solved by GMRES, preconditioned by the same operator with the coefficients averaged
over the period, M = Ā0 + Ā1·D1 + Ā2·D2, which is diagonal in frequency (one small
n_eq × n_states block per harmonic) and exact for models that are linear in the states.

Scaling: each equation is divided by its size at each instant (R); GMRES runs on
S⁻¹·M⁻¹·R·J·S (S the states' typical sizes, M built from R·J), so its residual is the
error in state-scaled units whatever the equations' units, and on M⁻ᵀ·(R·J)ᵀ for the
transposed system (adjoint sensitivities).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import fft  # a fifth faster than numpy's for these sizes

# Relative accuracy of every solve, Newton's steps and the sensitivities alike: Newton
# checks its own residual, and sensitivities to 1e-6 move a standard deviation by as
# little (1e-8 gave the Bouc-Wen fit the same estimates to 3 digits of a σ, 40 % slower).
RTOL = 1e-6
# Each equation's size at each instant is taken at the frequency of harmonic n/8 (the
# upper band, where GMRES spends its iterations) and floored at a tenth of its mean:
# tuned on the 2-dof damper (friction slopes peaking a thousandfold at reversals: 611
# GMRES iterations unscaled, 59 scaled) and Bouc-Wen (37 unscaled, 62 scaled; at the
# fundamental its z-equation's size vanishes at every reversal and GMRES stalls).
SIZE_HARMONIC = 1.0 / 8
SIZE_FLOOR = 0.1
RESTART = 40  # Krylov vectors kept: orthogonalising against them is most of an iteration's memory traffic
MAX_ITERATIONS = 1000


class KrylovError(np.linalg.LinAlgError):
    """GMRES did not reach the tolerance: an ill-conditioned Newton matrix."""


class KrylovSolver:
    """Solves with the spectral Newton matrix of coefficient blocks (n_eq, n_states, n)
    at frequency f; ``symbols`` are the rfft multipliers of d/dτ and d²/dτ²."""

    def __init__(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray, frequency_hz: float,
                 symbols: tuple[np.ndarray, np.ndarray], state_scales: np.ndarray):
        neq, ns, n = gx.shape
        f = frequency_hz
        self.shape = (neq, ns, n)
        self.s1, self.s2 = symbols[0] * f, symbols[1] * f * f
        self.scales = state_scales[:, None]
        # Each equation divided by its size at each instant: a friction slope that peaks
        # at velocity reversals then varies far less over the period, and the averaged
        # preconditioner fits it far better.
        omega = 2 * np.pi * f * max(1.0, n * SIZE_HARMONIC)
        size = np.einsum("ijn,j->in", np.abs(gx) + omega * np.abs(gdx) + omega**2 * np.abs(gddx), state_scales)
        size = np.maximum(size, SIZE_FLOOR * size.mean(axis=1, keepdims=True))
        self.row_scale = 1.0 / np.maximum(size, 1e-300)  # (neq, n)
        self.blocks = tuple(a * self.row_scale[:, None, :] for a in (gx, gdx, gddx))
        # States whose first / second derivative enters no equation need no inverse FFT for it.
        self.first = np.flatnonzero(np.any(gdx != 0, axis=(0, 2)))
        self.second = np.flatnonzero(np.any(gddx != 0, axis=(0, 2)))
        hx, hdx, hddx = (a.mean(-1) for a in self.blocks)
        P = hx[None] + self.s1[:, None, None] * hdx[None] + self.s2[:, None, None] * hddx[None]  # (harmonics, neq, ns)
        try:
            P_inv = np.linalg.inv(P)
        except np.linalg.LinAlgError:
            # Least squares where a harmonic's block is singular: the mean of a state that
            # only its derivative enters (hysteresis at rest), which J itself fixes.
            P_inv = np.linalg.pinv(P, rcond=1e-13)
        # (ns, neq, harmonics): each block entry contiguous over the harmonics it multiplies
        self.P_inv = np.ascontiguousarray(np.moveaxis(P_inv, 0, -1))
        self.iterations: list[int] = []  # GMRES iterations of every solve, for benchmarks

    # ----------------------------------------------------------------------------------
    def apply(self, x: np.ndarray) -> np.ndarray:
        """R·J·x for x (n_states, n), R the rows' scaling."""
        gx, gdx, gddx = self.blocks
        n = self.shape[2]
        X = fft.rfft(x, axis=-1)
        out = np.einsum("ijn,jn->in", gx, x)
        for states, symbol, coefficients in ((self.first, self.s1, gdx), (self.second, self.s2, gddx)):
            if states.size:
                d = fft.irfft(symbol * X[states], n=n, axis=-1)
                out += np.einsum("ijn,jn->in", coefficients[:, states], d)
        return out

    def apply_transposed(self, w: np.ndarray) -> np.ndarray:
        """(R·J)ᵀ·w for w (n_eq, n): D1ᵀ and D2ᵀ have the conjugate symbols."""
        gx, gdx, gddx = self.blocks
        n = self.shape[2]
        spectrum = np.zeros((self.shape[1], self.s1.size), complex)
        for states, symbol, coefficients in ((self.first, self.s1, gdx), (self.second, self.s2, gddx)):
            if states.size:
                spectrum[states] += np.conj(symbol) * fft.rfft(np.einsum("ijn,in->jn", coefficients[:, states], w),
                                                                  axis=-1)
        return np.einsum("ijn,in->jn", gx, w) + fft.irfft(spectrum, n=n, axis=-1)

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """M⁻¹·r for r (n_eq, n)."""
        R = fft.rfft(r, axis=-1)
        return fft.irfft((self.P_inv * R[None]).sum(axis=1), n=self.shape[2], axis=-1)

    def precondition_transposed(self, r: np.ndarray) -> np.ndarray:
        """M⁻ᵀ·r for r (n_states, n): the blocks' conjugate transposes per harmonic."""
        R = fft.rfft(r, axis=-1)
        return fft.irfft((np.conj(self.P_inv) * R[:, None]).sum(axis=0), n=self.shape[2], axis=-1)

    # ----------------------------------------------------------------------------------
    def _gmres(self, matvec: Callable[[np.ndarray], np.ndarray], rhs: np.ndarray, rtol: float | None,
               guess: np.ndarray | None = None) -> np.ndarray:
        x, iterations = gmres(matvec, rhs, RTOL if rtol is None else rtol, guess)
        self.iterations.append(iterations)
        return x

    def solve(self, rhs: np.ndarray, rtol: float | None = None, guess: np.ndarray | None = None) -> np.ndarray:
        """J⁻¹·rhs for rhs (N,) or (N, k), unknowns ordered state by state (to RTOL unless
        told), GMRES started from ``guess`` (shaped like the solution) where given."""
        neq, ns, n = self.shape
        S = self.scales

        def matvec(v: np.ndarray) -> np.ndarray:
            return (self.precondition(self.apply(S * v.reshape(ns, n))) / S).ravel()

        cols = rhs.reshape(neq * n, -1)
        starts = None if guess is None else guess.reshape(ns, n, -1)
        out = np.empty((ns * n, cols.shape[1]))
        for c in range(cols.shape[1]):  # a Krylov space per right-hand side
            b = (self.precondition(self.row_scale * cols[:, c].reshape(neq, n)) / S).ravel()
            x0 = None if starts is None else (starts[:, :, c] / S).ravel()
            out[:, c] = (S * self._gmres(matvec, b, rtol, x0).reshape(ns, n)).ravel()
        return out.reshape(rhs.shape)

    def solve_transposed(self, rhs: np.ndarray, rtol: float | None = None) -> np.ndarray:
        """J⁻ᵀ·rhs for rhs (N,) or (N, k): (R·J)ᵀ·ν = rhs, then R·ν."""
        neq, ns, n = self.shape

        def matvec(v: np.ndarray) -> np.ndarray:
            return self.precondition_transposed(self.apply_transposed(v.reshape(neq, n))).ravel()

        cols = rhs.reshape(ns * n, -1)
        out = np.empty((neq * n, cols.shape[1]))
        for c in range(cols.shape[1]):
            b = self.precondition_transposed(cols[:, c].reshape(ns, n)).ravel()
            out[:, c] = (self.row_scale * self._gmres(matvec, b, rtol).reshape(neq, n)).ravel()
        return out.reshape(rhs.shape)


def _norm(v: np.ndarray) -> float:
    # einsum, not BLAS: a threaded dot product stalls for milliseconds on a loaded machine
    return math.sqrt(float(np.einsum("i,i->", v, v)))


def gmres(matvec: Callable[[np.ndarray], np.ndarray], b: np.ndarray, rtol: float, x0: np.ndarray | None = None,
          restart: int = RESTART, max_iterations: int = MAX_ITERATIONS) -> tuple[np.ndarray, int]:
    """x with |b − A·x| <= rtol·|b| by restarted GMRES from x0 (else zero; classical
    Gram–Schmidt, repeated where it cancelled; Givens rotations), and the number of
    products with A it took.  Raises :class:`KrylovError` past ``max_iterations``."""
    target = rtol * _norm(b)
    total = 0
    if x0 is None:
        x, r = np.zeros_like(b), b.copy()
    else:
        x, r = x0.copy(), b - matvec(x0)
    while True:
        beta = _norm(r)
        if beta <= target or beta == 0.0:
            return x, total
        m = min(restart, b.size)
        V = np.empty((m + 1, b.size))
        V[0] = r / beta
        H = np.zeros((m + 1, m))
        cs, sn = np.zeros(m), np.zeros(m)
        g = np.zeros(m + 1)
        g[0] = beta
        k = 0
        for j in range(m):
            w = matvec(V[j])
            before = _norm(w)
            h = np.einsum("ij,j->i", V[:j + 1], w)
            w -= np.einsum("i,ij->j", h, V[:j + 1])
            after = _norm(w)
            if after < 0.7 * before:  # cancellation: a second pass restores the orthogonality rounding lost
                h2 = np.einsum("ij,j->i", V[:j + 1], w)
                w -= np.einsum("i,ij->j", h2, V[:j + 1])
                h += h2
                after = _norm(w)
            H[:j + 1, j] = h
            H[j + 1, j] = after
            if H[j + 1, j] > 0:
                V[j + 1] = w / H[j + 1, j]
            for i in range(j):  # the rotations so far, on the new column
                H[i, j], H[i + 1, j] = cs[i] * H[i, j] + sn[i] * H[i + 1, j], -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
            rho = math.hypot(H[j, j], H[j + 1, j])
            cs[j], sn[j] = (H[j, j] / rho, H[j + 1, j] / rho) if rho > 0 else (1.0, 0.0)
            H[j, j], H[j + 1, j] = rho, 0.0
            g[j], g[j + 1] = cs[j] * g[j], -sn[j] * g[j]
            total += 1
            k = j + 1
            if abs(g[j + 1]) <= target or H[j, j] == 0.0 or total >= max_iterations:
                break
        y = np.linalg.solve(np.triu(H[:k, :k]), g[:k]) if k else np.zeros(0)
        x += np.einsum("i,ij->j", y, V[:k])
        if not np.all(np.isfinite(x)):
            raise KrylovError("GMRES produced non-finite values")
        if abs(g[k]) <= target:
            return x, total
        if total >= max_iterations:
            raise KrylovError(f"GMRES did not converge in {total} iterations (residual {abs(g[k]) / _norm(b):.2g} "
                              f"of the right-hand side)")
        r = b - matvec(x)
