"""Differentiation on the periodic grid of one period, and the Newton Jacobian built on it.

One period is cut into ``n`` equidistant phases τ_μ = μ/n.  Time derivatives are phase
derivatives times f_e (d/dt = f_e·d/dτ).  Two schemes:

``bdf2``
    the paper's second-order backward differences with periodic wrap-around; sparse
    circulant operators, banded LU of the Newton Jacobian.
``spectral``
    Fourier differentiation, exact for band-limited periodic signals (multisine data);
    dense operators and dense LU up to DENSE_LIMIT unknowns, above it the matrix-free
    Newton–Krylov solver of :mod:`identify.spectral` (FFT products, O(n log n)).

Unknowns (and right-hand sides) are ordered state by state: z = (x1_1 … x1_n, x2_1 … x2_n, …).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack

from identify.errors import InputError

if TYPE_CHECKING:
    from identify.spectral import KrylovSolver

SCHEMES = ("bdf2", "spectral")
LINEAR_SOLVERS = ("auto", "dense", "krylov")
# Unknowns (n·n_states) above which the spectral scheme goes matrix-free.  Already at
# 2048 GMRES wins (Bouc-Wen fit 0.9 s against 14 s dense, benchmarks/bench_spectral.py),
# and at 1024 too (Silverbox 0.7 s against 5 s, the same estimates to 7 digits); up to
# 1024 the dense LU stays, so that Silverbox-sized fits keep their exact numbers.
DENSE_LIMIT = 1024

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
    (Jᵀ x = b, for adjoint sensitivities) take (N,) or (N, k) right-hand sides.
    ``krylov`` is the matrix-free solver behind them, if any (its iteration counts)."""

    _solve: object
    _solve_transposed: object
    krylov: KrylovSolver | None = None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._solve(rhs)  # type: ignore[operator]

    def solve_transposed(self, rhs: np.ndarray) -> np.ndarray:
        return self._solve_transposed(rhs)  # type: ignore[operator]


@dataclass(frozen=True)
class _BandLayout:
    """The BDF2 Newton matrix of a periodic grid as one band, for LAPACK's banded LU.

    The periodic wrap-around couples the first three time points to the last three;
    with the time points in the folded order τ_0, τ_{n-1}, τ_1, τ_{n-2}, … every point
    sits within six places of the points its stencil reaches, wrap-around included, so
    the whole matrix is a band (of width 13·n_states) with no low-rank correction to
    solve for.  Unknowns of one time point are adjacent (interleaved states)."""

    kl: int
    ku: int
    rows: int  # of the band storage: 2·kl + ku + 1
    entries: np.ndarray  # flat position in the (N, rows) band array of each coefficient (k, i, j, μ)
    to_band: np.ndarray  # band order of the unknowns, as indices into the state-major order
    from_band: np.ndarray  # the inverse permutation

    @staticmethod
    def build(neq: int, ns: int, n: int) -> _BandLayout:
        order = np.empty(n, dtype=np.intp)
        order[0::2] = np.arange((n + 1) // 2)
        order[1::2] = n - 1 - np.arange(n // 2)
        place = np.empty(n, dtype=np.intp)
        place[order] = np.arange(n)
        k, i, j, mu = np.meshgrid(np.arange(4), np.arange(neq), np.arange(ns), np.arange(n), indexing="ij")
        row = place[mu] * ns + i
        col = place[(mu - k) % n] * ns + j
        kl, ku = int(np.max(row - col)), int(np.max(col - row))
        rows = 2 * kl + ku + 1
        entries = (col * rows + kl + ku + row - col).ravel()  # J[r, c] at ab[kl + ku + r - c, c]
        state_major = (np.arange(ns)[None, :] * n + np.arange(n)[:, None])  # (time, state) -> index
        to_band = state_major[order].ravel()
        from_band = np.empty_like(to_band)
        from_band[to_band] = np.arange(to_band.size)
        return _BandLayout(kl, ku, rows, entries, to_band, from_band)


class Grid:
    """The phase grid of one period with its differentiation scheme.

    ``n`` points carry the data (inputs in, outputs out); the model is solved on
    ``points`` = n·``oversample`` of them.  Oversampling is for models with kinks
    (|ẋ|, hysteresis): their periodic solutions have jumps in a derivative, which every
    scheme resolves only to second order in the step, so a model grid finer than the
    data keeps that error below the noise.  Inputs are refined to the model grid by
    trigonometric interpolation (exact for band-limited excitation), and outputs are
    its every ``oversample``-th point."""

    def __init__(self, n: int, scheme: str = "bdf2", linear_solver: str = "auto", oversample: int = 1):
        if scheme not in SCHEMES:
            raise InputError(f"unknown scheme {scheme!r}: use one of {', '.join(SCHEMES)}")
        if linear_solver not in LINEAR_SOLVERS:
            raise InputError(f"unknown linear solver {linear_solver!r}: use one of {', '.join(LINEAR_SOLVERS)}")
        if linear_solver == "krylov" and scheme != "spectral":
            raise InputError("the matrix-free (krylov) solver is for the spectral scheme")
        if n < 8:
            raise InputError(f"n = {n} points per period is too few (at least 8)")
        if oversample < 1:
            raise InputError(f"oversample = {oversample}: the model grid cannot be coarser than the data's")
        self.n = n
        self.scheme = scheme
        self.linear_solver = linear_solver
        self.oversample = oversample
        self.points = n * oversample
        self.tau = np.arange(n) / n
        h = 1.0 / self.points
        if scheme == "bdf2":
            self._c1 = BDF2_D1 / h
            self._c2 = BDF2_D2 / h**2
            self._layouts: dict[tuple[int, int], _BandLayout] = {}
        else:
            self._s1, self._s2 = _spectral_symbols(self.points)
            self._dense: tuple[np.ndarray, np.ndarray] | None = None  # D1, D2, built on first dense use

    def base(self) -> Grid:
        """The same grid without oversampling (the model solved on the data's points)."""
        return Grid(self.n, self.scheme, self.linear_solver)

    def krylov(self, n_states: int) -> bool:
        """Whether Newton matrices with this many states are solved matrix-free."""
        if self.scheme != "spectral":
            return False
        return self.linear_solver == "krylov" or (self.linear_solver == "auto"
                                                  and self.points * n_states > DENSE_LIMIT)

    # ----------------------------------------------------------------------------------
    def refine(self, x: np.ndarray, axis: int = -1) -> np.ndarray:
        """Data-grid values (… n …) on the model grid: trigonometric interpolation."""
        if self.oversample == 1:
            return x
        X = np.fft.rfft(x, axis=axis)
        if self.n % 2 == 0:  # the data's Nyquist line becomes an ordinary one: half of it each side
            nyquist = [slice(None)] * X.ndim
            nyquist[axis] = slice(self.n // 2, None)
            X[tuple(nyquist)] *= 0.5
        return np.fft.irfft(X, n=self.points, axis=axis) * self.oversample

    def refine_transposed(self, w: np.ndarray, axis: int = -1) -> np.ndarray:
        """The transpose of :meth:`refine`: model-grid weights onto the data grid."""
        if self.oversample == 1:
            return w
        W = np.fft.rfft(w, axis=axis)
        keep = [slice(None)] * W.ndim
        keep[axis] = slice(0, self.n // 2 + 1)
        return np.fft.irfft(W[tuple(keep)], n=self.n, axis=axis)

    def sample(self, y: np.ndarray, axis: int = -1) -> np.ndarray:
        """Model-grid values at the data's points."""
        if self.oversample == 1:
            return y
        return np.take(y, np.arange(0, self.points, self.oversample), axis=axis)

    def sample_transposed(self, w: np.ndarray, axis: int = -1) -> np.ndarray:
        """The transpose of :meth:`sample`: data-grid weights at their model-grid points."""
        if self.oversample == 1:
            return w
        shape = list(w.shape)
        shape[axis] = self.points
        out = np.zeros(shape)
        index = [slice(None)] * out.ndim
        index[axis] = slice(None, None, self.oversample)
        out[tuple(index)] = w
        return out

    # ----------------------------------------------------------------------------------
    def derivatives(self, x: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """First and second time derivatives of x (…, points) on the model grid."""
        f = frequency_hz
        if self.scheme == "bdf2":
            x0, x1, x2, x3 = _shifts(x, -1)
            c1, c2 = self._c1, self._c2
            dx = f * (c1[0] * x0 + c1[1] * x1 + c1[2] * x2)
            ddx = f * f * (c2[0] * x0 + c2[1] * x1 + c2[2] * x2 + c2[3] * x3)
            return dx, ddx
        X = np.fft.rfft(x, axis=-1)
        dx = np.fft.irfft(X * (f * self._s1), n=self.points, axis=-1)
        ddx = np.fft.irfft(X * (f * f * self._s2), n=self.points, axis=-1)
        return dx, ddx

    def derivatives_transposed(self, w1: np.ndarray, w2: np.ndarray,
                               frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """D1ᵀ·w1 and D2ᵀ·w2 along the last axis (the adjoints of :meth:`derivatives`);
        one operator each, as an adjoint needs, not both of each (half the work)."""
        f = frequency_hz
        if self.scheme == "bdf2":
            c1, c2 = self._c1, self._c2
            a0, a1, a2, _ = _shifts(w1, +1)
            b0, b1, b2, b3 = _shifts(w2, +1)
            return (f * (c1[0] * a0 + c1[1] * a1 + c1[2] * a2),
                    f * f * (c2[0] * b0 + c2[1] * b1 + c2[2] * b2 + c2[3] * b3))
        W1, W2 = np.fft.rfft(w1, axis=-1), np.fft.rfft(w2, axis=-1)
        return (np.fft.irfft(W1 * (f * np.conj(self._s1)), n=self.points, axis=-1),
                np.fft.irfft(W2 * (f * f * np.conj(self._s2)), n=self.points, axis=-1))

    def apply_derivative_operators(self, dz: np.ndarray, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of a stack of state perturbations dz with shape (n_states, n, k)."""
        moved = np.moveaxis(dz, 1, -1)
        d1, d2 = self.derivatives(moved, frequency_hz)
        return np.moveaxis(d1, -1, 1), np.moveaxis(d2, -1, 1)

    # ----------------------------------------------------------------------------------
    def factorize(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray, frequency_hz: float,
                  state_scales: np.ndarray | None = None) -> Factorization:
        """Factorise ∂G/∂z for residual blocks (n_eq, n_states, n) of ∂g/∂x, ∂g/∂ẋ, ∂g/∂ẍ
        (matrix-free: prepare its solves; ``state_scales`` sets their accuracy's units)."""
        neq, ns, n = gx.shape
        f = frequency_hz
        if self.scheme == "bdf2":
            return self._factorize_banded(gx, gdx, gddx, f)
        if self.krylov(ns):
            from identify.spectral import KrylovSolver

            scales = np.ones(ns) if state_scales is None else state_scales
            krylov = KrylovSolver(gx, gdx, gddx, f, (self._s1, self._s2), scales)
            return Factorization(krylov.solve, krylov.solve_transposed, krylov)
        if self._dense is None:
            eye = np.eye(n)
            self._dense = (np.fft.irfft(self._s1[:, None] * np.fft.rfft(eye, axis=0), n=n, axis=0),
                           np.fft.irfft(self._s2[:, None] * np.fft.rfft(eye, axis=0), n=n, axis=0))
        D1, D2 = self._dense
        J = np.empty((neq * n, ns * n))
        for i in range(neq):
            for j in range(ns):
                block = (f * gdx[i, j][:, None]) * D1 + (f * f * gddx[i, j][:, None]) * D2
                block[np.diag_indices(n)] += gx[i, j]
                J[i * n:(i + 1) * n, j * n:(j + 1) * n] = block
        lu = sla.lu_factor(J, check_finite=False)
        return Factorization(lambda rhs: sla.lu_solve(lu, rhs, check_finite=False),
                             lambda rhs: sla.lu_solve(lu, rhs, trans=1, check_finite=False))

    def _band_layout(self, neq: int, ns: int) -> _BandLayout:
        """Where each BDF2 Jacobian coefficient sits in LAPACK band storage, for this grid
        and model size (computed once, then every factorisation is one scatter)."""
        key = (neq, ns)
        if key not in self._layouts:
            self._layouts[key] = _BandLayout.build(neq, ns, self.points)
        return self._layouts[key]

    def _factorize_banded(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray, f: float) -> Factorization:
        """Banded LU of the BDF2 Jacobian, periodic wrap-around included (see _BandLayout)."""
        neq, ns, n = gx.shape
        layout = self._band_layout(neq, ns)
        c1, c2 = self._c1 * f, self._c2 * f * f
        data = c1[:, None, None, None] * gdx[None] + c2[:, None, None, None] * gddx[None]
        data[0] += gx  # (offset k, i, j, μ): coefficient of x_j(τ_{μ-k}) in g_i(τ_μ)
        N, kl, ku, rows = ns * n, layout.kl, layout.ku, layout.rows
        ab = np.zeros(rows * N)
        ab[layout.entries] = data.ravel()
        lu, piv, info = lapack.dgbtrf(ab.reshape(N, rows).T, kl, ku, overwrite_ab=1)  # a Fortran-ordered view
        if info != 0:
            raise np.linalg.LinAlgError(f"singular periodic Jacobian (banded LU pivot {info})")

        def solver(trans: int):
            def solve(rhs: np.ndarray) -> np.ndarray:
                x, _ = lapack.dgbtrs(lu, kl, ku, rhs.reshape(N, -1)[layout.to_band], piv, trans=trans)
                return x[layout.from_band].reshape(rhs.shape)
            return solve

        return Factorization(solver(0), solver(1))

    def interpolate(self, values: np.ndarray, phase: np.ndarray) -> np.ndarray:
        """Values (…, n) on the data grid or (…, points) on the model grid evaluated at
        arbitrary phases (periodic).

        Spectral grids interpolate trigonometrically, BDF2 grids with periodic cubic splines.
        """
        phase = np.mod(phase, 1.0)
        size = values.shape[-1]
        position = phase * size
        on_grid = np.rint(position)
        if np.all(np.abs(position - on_grid) < 1e-6):  # records with whole samples per period: no interpolation
            return values[..., on_grid.astype(np.int64) % size]
        if self.scheme == "spectral":
            coeffs = np.fft.rfft(values, axis=-1) / size
            k = np.arange(coeffs.shape[-1])
            weight = np.full(k.shape, 2.0)
            weight[0] = 1.0
            if size % 2 == 0:
                weight[-1] = 1.0
            weighted = coeffs * weight
            out = np.empty(values.shape[:-1] + phase.shape)
            step = max(1, 2**22 // k.size)  # phases per chunk: bounded memory for long records and fine grids
            for start in range(0, phase.size, step):
                chunk = phase[start:start + step]
                out[..., start:start + step] = np.real(weighted @ np.exp(2j * np.pi * np.outer(k, chunk)))
            return out
        from scipy.interpolate import CubicSpline

        tau = np.append(np.arange(size) / size, 1.0)
        closed = np.concatenate([values, values[..., :1]], axis=-1)
        return CubicSpline(tau, closed, axis=-1, bc_type="periodic")(phase)


def periodic_derivative(x: np.ndarray, frequency_hz: float, order: int, axis: int = -1,
                        transposed: bool = False) -> np.ndarray:
    """The order-th time derivative of one period's samples along ``axis``, spectrally
    (exact for a band-limited periodic signal on its own grid); ``transposed``: the
    operator's transpose (conjugate multipliers), for adjoints."""
    n = x.shape[axis]
    s = _spectral_symbols(n)[order - 1] * frequency_hz**order
    shape = [1] * x.ndim
    shape[axis] = s.size
    s = (np.conj(s) if transposed else s).reshape(shape)
    return np.fft.irfft(np.fft.rfft(x, axis=axis) * s, n=n, axis=axis)
