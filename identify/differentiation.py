"""Differentiation on the periodic grid of one period, and the Newton Jacobian built on it.

One period is cut into ``n`` equidistant phases τ_μ = μ/n.  Time derivatives are phase
derivatives times f_e (d/dt = f_e·d/dτ).  Two schemes:

``bdf2``
    the paper's second-order backward differences with periodic wrap-around; sparse
    circulant operators, sparse LU of the Newton Jacobian.
``spectral``
    Fourier differentiation, exact for band-limited periodic signals (multisine data);
    dense operators, dense LU.

Unknowns (and right-hand sides) are ordered state by state: z = (x1_1 … x1_n, x2_1 … x2_n, …).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack

from identify.errors import InputError

SCHEMES = ("bdf2", "spectral")

# Backward stencils on offsets 0, -1, -2, -3 (in units of Δτ and Δτ²).
BDF2_D1 = np.array([3.0, -4.0, 1.0, 0.0]) / 2.0
BDF2_D2 = np.array([2.0, -5.0, 4.0, -1.0])


def _spectral_symbols(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Fourier multipliers of d/dτ and d²/dτ² for rfft of length n."""
    k = np.fft.rfftfreq(n, d=1.0 / n)
    d1 = 2j * np.pi * k
    if n % 2 == 0:
        d1[-1] = 0.0  # the Nyquist mode has no well-defined odd derivative
    d2 = -(2 * np.pi * k) ** 2
    return d1, d2


def _shifts(x: np.ndarray, step: int) -> tuple[np.ndarray, ...]:
    """x(τ_μ), x(τ_{μ+step}), x(τ_{μ+2·step}), x(τ_{μ+3·step}) along the last axis, periodic,
    as views of one padded copy (three np.roll calls would copy three times); step ±1."""
    n = x.shape[-1]
    if step < 0:
        padded = np.concatenate((x[..., -3:], x), axis=-1)
        return x, padded[..., 2:n + 2], padded[..., 1:n + 1], padded[..., :n]
    padded = np.concatenate((x, x[..., :3]), axis=-1)
    return x, padded[..., 1:n + 1], padded[..., 2:n + 2], padded[..., 3:n + 3]


@dataclass
class Factorization:
    """A factorised Newton Jacobian J; ``solve`` (J x = b) and ``solve_transposed``
    (Jᵀ x = b, for adjoint sensitivities) take (N,) or (N, k) right-hand sides."""

    _solve: object
    _solve_transposed: object

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._solve(rhs)  # type: ignore[operator]

    def solve_transposed(self, rhs: np.ndarray) -> np.ndarray:
        return self._solve_transposed(rhs)  # type: ignore[operator]


class Grid:
    """The phase grid of one period with its differentiation scheme."""

    def __init__(self, n: int, scheme: str = "bdf2"):
        if scheme not in SCHEMES:
            raise InputError(f"unknown scheme {scheme!r}: use one of {', '.join(SCHEMES)}")
        if n < 8:
            raise InputError(f"n = {n} points per period is too few (at least 8)")
        self.n = n
        self.scheme = scheme
        self.tau = np.arange(n) / n
        h = 1.0 / n
        if scheme == "bdf2":
            self._c1 = BDF2_D1 / h
            self._c2 = BDF2_D2 / h**2
        else:
            self._s1, self._s2 = _spectral_symbols(n)
            eye = np.eye(n)
            self._D1 = np.fft.irfft(self._s1[:, None] * np.fft.rfft(eye, axis=0), n=n, axis=0)
            self._D2 = np.fft.irfft(self._s2[:, None] * np.fft.rfft(eye, axis=0), n=n, axis=0)

    # ----------------------------------------------------------------------------------
    def derivatives(self, x: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """First and second time derivatives of x (…, n) on the grid."""
        f = frequency_hz
        if self.scheme == "bdf2":
            x0, x1, x2, x3 = _shifts(x, -1)
            c1, c2 = self._c1, self._c2
            dx = f * (c1[0] * x0 + c1[1] * x1 + c1[2] * x2)
            ddx = f * f * (c2[0] * x0 + c2[1] * x1 + c2[2] * x2 + c2[3] * x3)
            return dx, ddx
        X = np.fft.rfft(x, axis=-1)
        dx = np.fft.irfft(X * (f * self._s1), n=self.n, axis=-1)
        ddx = np.fft.irfft(X * (f * f * self._s2), n=self.n, axis=-1)
        return dx, ddx

    def derivatives_transposed(self, w: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """D1ᵀ·w and D2ᵀ·w along the last axis (the adjoints of :meth:`derivatives`)."""
        f = frequency_hz
        if self.scheme == "bdf2":
            w0, w1, w2, w3 = _shifts(w, +1)
            c1, c2 = self._c1, self._c2
            return (f * (c1[0] * w0 + c1[1] * w1 + c1[2] * w2),
                    f * f * (c2[0] * w0 + c2[1] * w1 + c2[2] * w2 + c2[3] * w3))
        W = np.fft.rfft(w, axis=-1)
        return (np.fft.irfft(W * (f * np.conj(self._s1)), n=self.n, axis=-1),
                np.fft.irfft(W * (f * f * np.conj(self._s2)), n=self.n, axis=-1))

    def apply_derivative_operators(self, dz: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of a stack of state perturbations dz with shape (n_states, n, k)."""
        moved = np.moveaxis(dz, 1, -1)
        d1, d2 = self.derivatives(moved, frequency_hz)
        return np.moveaxis(d1, -1, 1), np.moveaxis(d2, -1, 1)

    # ----------------------------------------------------------------------------------
    def factorize(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray, frequency_hz: float) -> Factorization:
        """Factorise ∂G/∂z for residual blocks (n_eq, n_states, n) of ∂g/∂x, ∂g/∂ẋ, ∂g/∂ẍ."""
        neq, ns, n = gx.shape
        f = frequency_hz
        if self.scheme == "bdf2":
            return self._factorize_banded(gx, gdx, gddx, f)
        J = np.empty((neq * n, ns * n))
        for i in range(neq):
            for j in range(ns):
                block = (f * gdx[i, j][:, None]) * self._D1 + (f * f * gddx[i, j][:, None]) * self._D2
                block[np.diag_indices(n)] += gx[i, j]
                J[i * n:(i + 1) * n, j * n:(j + 1) * n] = block
        lu = sla.lu_factor(J, check_finite=False)
        return Factorization(lambda rhs: sla.lu_solve(lu, rhs, check_finite=False),
                             lambda rhs: sla.lu_solve(lu, rhs, trans=1, check_finite=False))

    def _factorize_banded(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray, f: float) -> Factorization:
        """Banded LU of the BDF2 Jacobian, with the periodic wrap-around as a low-rank
        (Woodbury) correction.

        Unknowns are interleaved in time (x_1(τ_0), x_2(τ_0), x_1(τ_1), …), which makes the
        non-periodic part a band of width 4·n_states; the wrap-around couples the first
        three time points to the last three, a rank-3·n_states corner.
        """
        neq, ns, n = gx.shape
        N = n * ns
        c1, c2 = self._c1 * f, self._c2 * f * f
        data = c1[:, None, None, None] * gdx[None] + c2[:, None, None, None] * gddx[None]
        data[0] += gx  # (offset k, i, j, μ): coefficient of x_j(τ_{μ-k}) in g_i(τ_μ)
        kl, ku = 4 * ns - 1, ns - 1
        rc = 3 * ns
        # Band storage: J[r, c] sits at ab[kl + ku + r - c, c]; for x_j(τ_{μ-k}) in g_i(τ_μ)
        # r - c = k·ns + i - j, so each (k, i, j) fills a strided slice of one band row.
        ab = np.zeros((2 * kl + ku + 1, N))
        for k in range(4):
            for i in range(neq):
                for j in range(ns):
                    ab[kl + ku + k * ns + i - j, j:N - k * ns:ns] = data[k, i, j, k:]
        # The wrap-around: g(τ_μ), μ < k, reaches back to τ_{n+μ-k}, among the last 3 points.
        corner = np.zeros((rc, rc))
        blocks = corner.reshape(3, ns, 3, ns)
        for k in range(1, 4):
            for mu in range(k):
                blocks[mu, :, mu + 3 - k, :] = data[k, :, :, mu]
        lu, piv, info = lapack.dgbtrf(ab, kl, ku)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular periodic Jacobian (banded LU pivot {info})")

        def band_solve(b: np.ndarray, trans: int = 0) -> np.ndarray:
            x, info_ = lapack.dgbtrs(lu, kl, ku, b, piv, trans=trans)
            return x

        # Equations the wrap-around does not reach (a first-order state's row at τ_2, say)
        # need no column of W: one band solve fewer each.
        live = np.flatnonzero(np.any(corner != 0.0, axis=1))
        corner = corner[live]  # (r, rc): J = B + P[:, live]·corner·Qᵀ
        P = np.zeros((N, live.size))
        P[live, np.arange(live.size)] = 1.0
        W = band_solve(P)
        K = np.eye(live.size) + corner @ W[N - rc:]
        K_lu = sla.lu_factor(K, check_finite=False)
        # Jᵀ = Bᵀ + Q·cornerᵀ·Pᵀ (P: first rc rows, Q: last rc columns): the same
        # Woodbury identity with the roles of P and Q exchanged, built on first use.
        adjoint: list = []

        def interleave(rhs: np.ndarray) -> np.ndarray:
            return rhs.reshape(ns, n, -1).transpose(1, 0, 2).reshape(N, -1)

        def deinterleave(y: np.ndarray, shape: tuple) -> np.ndarray:
            return y.reshape(n, ns, -1).transpose(1, 0, 2).reshape(shape)

        def solve(rhs: np.ndarray) -> np.ndarray:
            y = band_solve(interleave(rhs))
            y -= W @ sla.lu_solve(K_lu, corner @ y[N - rc:], check_finite=False)
            return deinterleave(y, rhs.shape)

        def solve_transposed(rhs: np.ndarray) -> np.ndarray:
            if not adjoint:
                last = np.zeros((N, rc))
                last[N - rc + np.arange(rc), np.arange(rc)] = 1.0
                Wt = band_solve(last, trans=1)
                adjoint.extend([Wt, sla.lu_factor(np.eye(rc) + corner.T @ Wt[live], check_finite=False)])
            Wt, Kt_lu = adjoint
            y = band_solve(interleave(rhs), trans=1)
            y -= Wt @ sla.lu_solve(Kt_lu, corner.T @ y[live], check_finite=False)
            return deinterleave(y, rhs.shape)

        return Factorization(solve, solve_transposed)

    def interpolate(self, values: np.ndarray, phase: np.ndarray) -> np.ndarray:
        """Values (…, n) on the grid evaluated at arbitrary phases (periodic).

        Spectral grids interpolate trigonometrically, BDF2 grids with periodic cubic splines.
        """
        phase = np.mod(phase, 1.0)
        if self.scheme == "spectral":
            coeffs = np.fft.rfft(values, axis=-1) / self.n
            k = np.arange(coeffs.shape[-1])
            weight = np.full(k.shape, 2.0)
            weight[0] = 1.0
            if self.n % 2 == 0:
                weight[-1] = 1.0
            weighted = coeffs * weight
            out = np.empty(values.shape[:-1] + phase.shape)
            for start in range(0, phase.size, 4096):  # bounded memory for long records
                chunk = phase[start:start + 4096]
                out[..., start:start + 4096] = np.real(weighted @ np.exp(2j * np.pi * np.outer(k, chunk)))
            return out
        from scipy.interpolate import CubicSpline

        tau = np.append(self.tau, 1.0)
        closed = np.concatenate([values, values[..., :1]], axis=-1)
        return CubicSpline(tau, closed, axis=-1, bc_type="periodic")(phase)
