"""A model integrated over a whole record, transient included: the counterpart of
:mod:`identify.periodic` for records that do not wait for the steady state.

The record's samples t_0 … t_{N−1} (step Δt, no lost samples) carry the data; the model
is solved on ``oversample`` points per sample step (inputs interpolated by a local cubic,
:func:`refinement`).  Time derivatives are the periodic solver's backward stencils (BDF2
for ẋ, its four-point companion for ẍ); before t_0 they reach three ghost points,
extrapolated from the initial state z0 = (x(t_0), ẋ(t_0) of the second-order states) and
x(t_1) by a quadratic (a first-order state: the line through x(t_0) and x(t_1), i.e. one
backward Euler step), so that the stencils keep their order from the first step.

The unknowns are the states at every model point; the equations are x(t_0) = x0 at the
first point and g = 0 at every later one.  That square system is causal, so its Newton
matrix is block lower triangular with three blocks below the diagonal: one band,
factorised by LAPACK's banded LU in O(N) time and memory, the whole record at once, and
the same factorisation gives the sensitivities to θ, to the initial state and to the
inputs (the periodic solver's interface, so :class:`identify.estimator.Estimator` takes
either kind of solution).

The initial state is estimated: for every θ the solver fits z0 to the record by
Gauss–Newton (weights: the channels' noise variances), started from the outputs of the
first samples mapped to states, and returns the sensitivities to θ projected onto the
complement of the initial state's (variable projection, Golub & Pereyra; Kaufman's
Jacobian): dŷ/dθ + dŷ/dz0·dz0*/dθ.  The estimator's normal equations, σ and sandwich are
then those of θ with z0 profiled out, as if z0 were estimated beside it.  The initial
state is never assumed to be at rest or on a steady state, and the measured first
samples are only its start.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from math import comb
from types import SimpleNamespace

import numpy as np
import scipy.sparse as sps
from scipy.linalg import LinAlgWarning, lapack

from identify.dataset import DatasetError, Experiment
from identify.differentiation import BDF2_D1, BDF2_D2, Factorization
from identify.errors import InputError
from identify.model import CompiledModel
from identify.periodic import ConvergenceError, damped_step
from identify.preparation import with_fixed
from identify.start import Measured, rest_state

NEWTON_ITERATIONS = 40
TOLERANCE = 1e-9  # Newton's step, relative to each state's scale
STAGNATION = 1e-6  # a step this small (relative) that no longer lowers the residual is rounding: converged
INITIAL_ITERATIONS = 8  # Gauss-Newton steps on the initial state per solve
MOVE_ATTEMPTS = 3  # halvings of an initial-state step whose trajectory Newton does not reach
# A step of the initial state that would lower χ² by less than this changes nothing the data can tell.
INITIAL_CHI2 = 1e-6
WINDOW = 64  # model points of the marching start's first window
MIN_WINDOW, MAX_WINDOW = 8, 1 << 14  # ... and the range it adapts in
FAST_NEWTON = 5  # a window solved in this many Newton iterations or fewer: the next one is twice as long
INITIAL_SAMPLES = 16  # first samples whose mapped states give the initial state's start (a quadratic fit)
# The initial velocities get a normal prior: the quadratic's estimate from those samples
# with this many of its standard errors.  Without it, a start far from the optimum sent
# the fitted initial velocity to −23 m/s (the orifice damping stops such a jolt within a
# few samples, where it shifted the stroke like an offset) and the fit stalled there.
VELOCITY_PRIOR_WIDTH = 10.0
DIFFERENCE_ORDERS = (1, 2, 3)  # differences whose robust scatter estimates a channel's white noise
TRIM = 0.05  # fraction of the largest differences left out of a noise estimate


# --------------------------------------------------------------------------------------
# The record as the estimator sees it.


class Unfolded:
    """The noise operator of a record taken sample by sample: identity (F = I); the
    folded record's interface (:class:`identify.folding.FoldedRecord`)."""

    def __init__(self, n: int):
        self.n = n
        self.filled_counts = np.ones(n)
        self.grid_factor = 1.0

    @staticmethod
    def noise_factor(z: np.ndarray) -> np.ndarray:
        return z

    @staticmethod
    def noise_factor_t(x: np.ndarray) -> np.ndarray:
        return x


def white_noise_std(values: np.ndarray) -> float:
    """Per-sample standard deviation of a channel's white noise, from the trimmed scatter
    of its k-th differences, the smallest over k = 1…3.

    Differences cancel a smooth signal and keep white noise with variance C(2k, k)·σ²;
    the largest TRIM of them are left out (the samples where a jump, the friction force
    at a velocity reversal, passes through a difference) and the rest's RMS is corrected
    for the normal distribution's trimmed tails.  A median (MAD) would do the same but
    reads the 16-bit steps of a quantised channel: it put the stroke noise 10 % low.  A
    signal that is not smooth on the sample step (broadband up to the Nyquist line) shows
    up as noise: that estimate is an upper bound."""
    from scipy.stats import norm

    z = norm.ppf(0.5 + (1 - TRIM) / 2)
    kept_variance = 1 - 2 * z * norm.pdf(z) / (1 - TRIM)  # of a unit normal within ±z
    best = np.inf
    for k in DIFFERENCE_ORDERS:
        d = np.diff(values, n=k)
        if d.size < 20:
            continue
        d = np.abs(d - np.median(d))
        kept = np.sort(d)[:int(np.ceil((1 - TRIM) * d.size))]
        best = min(best, float(np.sqrt(np.mean(kept**2) / kept_variance / comb(2 * k, k))))
    return best if np.isfinite(best) else float("nan")


@dataclass
class TransientData:
    """One record fitted as a transient, sample by sample (SI units): the estimator's
    counterpart of :class:`identify.preparation.PeriodicData`."""

    label: str
    frequency_hz: float  # of the excitation, for the report (nan: none declared)
    step_s: float  # sampling interval
    inputs: np.ndarray  # (n_inputs, N)
    measured: np.ndarray  # (n_outputs, N)
    noise_variance: np.ndarray  # (n_outputs,) per sample, SI (nan: unknown)
    input_noise_variance: np.ndarray  # (n_inputs,)
    folded: Unfolded
    oversample: int = 1
    fixed: dict[int, float] = field(default_factory=dict)

    @property
    def grid_variance(self) -> np.ndarray:
        return self.noise_variance * self.folded.grid_factor

    def noise_estimable(self) -> bool:
        return bool(np.all(np.isfinite(self.noise_variance)) and np.all(np.isfinite(self.input_noise_variance))
                    and np.all(self.noise_variance > 0))

    def theta(self, theta: np.ndarray) -> np.ndarray:
        return with_fixed(theta, self.fixed)

    def weights(self) -> np.ndarray:
        """(n_outputs,) weights of the initial state's fit: 1/noise variance, or 1/the
        channel's variance where the noise is unknown."""
        v = self.noise_variance
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            v = np.var(self.measured, axis=1) + 1e-300
        return 1.0 / v


def is_transient(exp: Experiment) -> bool:
    """Whether the dataset says the record was captured from RUN on (``capture = "transient"``)."""
    return exp.meta.get("capture") == "transient"


def prepare_transient(model: CompiledModel, experiments: list[Experiment], outputs: list[str],
                      oversample: int = 1) -> list[TransientData]:
    """Each experiment's input and output columns in SI, sample by sample, with the
    channels' noise from their differences (:func:`white_noise_std`)."""
    d = model.declaration
    if experiments and model.input_derivatives:
        raise InputError(f"model {model.name!r} takes its inputs' derivatives, which a transient fit does not "
                         f"provide yet: fit {experiments[0].label!r} as periodic (--capture steady)")
    out = []
    for exp in experiments:
        if exp.kind == "drop":
            raise DatasetError(f"experiment {exp.label!r} is a drop record; the transient fit takes shaker records")
        if exp.meta.get("lost_samples"):
            raise DatasetError(f"{exp.file}: {exp.meta['lost_samples']} lost samples: a transient fit needs every "
                               f"sample of the record (fit it as periodic, which folds around the holes)")
        assert exp.data is not None
        for ch in list(d.inputs.values()) + [d.outputs[o] for o in outputs]:
            if ch.column not in exp.data.columns:
                raise DatasetError(f"{exp.file}: column {ch.column!r}: missing (model {model.name!r} needs it)")
        t = exp.time_s
        if len(t) < 8:
            raise DatasetError(f"{exp.file}: {len(t)} samples; a transient fit needs at least 8")
        inputs = np.vstack([ch.to_si(exp.column(ch.column)) for ch in d.inputs.values()])
        measured = np.vstack([d.outputs[o].to_si(exp.column(d.outputs[o].column)) for o in outputs])
        yvar = np.array([(white_noise_std(exp.column(d.outputs[o].column)) * d.outputs[o].scale) ** 2
                         for o in outputs])
        uvar = np.array([(white_noise_std(exp.column(ch.column)) * ch.scale) ** 2 for ch in d.inputs.values()])
        frequency = float(exp.meta.get("frequency_Hz", float("nan")))
        out.append(TransientData(exp.label, frequency, (t[-1] - t[0]) / (len(t) - 1), inputs, measured, yvar, uvar,
                                 Unfolded(len(t)), oversample))
    return out


# --------------------------------------------------------------------------------------
# Interpolation from the data's samples to the model's points.


def refinement(n: int, oversample: int) -> sps.csr_matrix:
    """(M, n) sparse map from samples to model points, M = (n−1)·oversample + 1: Keys'
    cubic convolution (a = −1/2, third order, four samples per point; at the ends the
    samples are extrapolated linearly).  Sparse, so its transpose (for adjoints) is free."""
    m = (n - 1) * oversample + 1
    if oversample == 1:
        return sps.identity(n, format="csr")
    s = np.arange(m) / oversample
    i = np.minimum(np.floor(s).astype(np.intp), n - 2)
    f = s - i
    w = np.stack([((-0.5 * f + 1.0) * f - 0.5) * f,
                  (1.5 * f - 2.5) * f * f + 1.0,
                  ((-1.5 * f + 2.0) * f + 0.5) * f,
                  (0.5 * f - 0.5) * f * f])  # Keys' weights of samples i−1, i, i+1, i+2
    cols = i[None, :] + np.arange(-1, 3)[:, None]
    rows = np.broadcast_to(np.arange(m), cols.shape)
    # Beyond the ends the ghost samples x_{−1} = 2·x_0 − x_1 and x_n = 2·x_{n−1} − x_{n−2}.
    low, high = cols < 0, cols > n - 1
    data = [np.where(low | high, 2.0 * w, w).ravel(), -w[low], -w[high]]
    c = [np.clip(cols, 0, n - 1).ravel(), np.ones(int(low.sum()), np.intp), np.full(int(high.sum()), n - 2)]
    r = [rows.ravel(), rows[low], rows[high]]
    return sps.csr_matrix((np.concatenate(data), (np.concatenate(r), np.concatenate(c))), shape=(m, n))


# --------------------------------------------------------------------------------------
# Differentiation with the initial state's ghost points.


class Stencils:
    """Time derivatives on the model points of a record, with the ghost points of the
    initial state (module docstring); linear in (X, v0) jointly."""

    def __init__(self, orders: tuple[int, ...], h: float, points: int):
        self.h = h
        self.points = points
        self.second = np.array([o == 2 for o in orders])
        self.c1 = BDF2_D1 / h
        self.c2 = BDF2_D2 / h**2
        # Jacobian coefficients of x_{μ−k} (k = 0…3) in ẋ_μ and ẍ_μ, per state: the
        # standard stencils from μ = 3 on, the ghosts' substitutions before.
        ns = len(orders)
        probe = min(points, 8)
        self.head1 = np.zeros((ns, 4, 4))  # (state, k, μ) for μ = 0…3
        self.head2 = np.zeros((ns, 4, 4))
        for col in range(probe):
            e = np.zeros((ns, probe))
            e[:, col] = 1.0
            d1, d2 = self._apply(e, np.zeros(ns), probe)
            for mu in range(min(4, probe)):
                k = mu - col
                if 0 <= k <= 3:
                    self.head1[:, k, mu] = d1[:, mu]
                    self.head2[:, k, mu] = d2[:, mu]
        d1, d2 = self._apply(np.zeros((ns, probe)), np.ones(ns), probe)
        self.v1 = d1[:, :4]  # coefficients of v0 in ẋ_μ, ẍ_μ (μ = 0…3; zero after)
        self.v2 = d2[:, :4]

    def _ghosts(self, X: np.ndarray, V0: np.ndarray) -> np.ndarray:
        """x_{−3}, x_{−2}, x_{−1}: (ns, 3, …)."""
        x0, x1 = X[:, 0], X[:, 1]
        sel = self.second.reshape((-1,) + (1,) * (x0.ndim - 1))
        hv = np.where(sel, self.h * V0, x1 - x0)
        bend = x1 - x0 - hv  # a·h²/2 of the quadratic through x0 (slope v0) and x1
        k = np.array([3.0, 2.0, 1.0]).reshape((1, 3) + (1,) * (x0.ndim - 1))
        return x0[:, None] - k * hv[:, None] + k * k * bend[:, None]

    def _apply(self, X: np.ndarray, V0: np.ndarray, points: int,
               history: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = np.concatenate([self._ghosts(X, V0) if history is None else history, X], axis=1)
        c1, c2 = self.c1, self.c2
        n = points
        d1 = c1[0] * p[:, 3:3 + n] + c1[1] * p[:, 2:2 + n] + c1[2] * p[:, 1:1 + n]
        d2 = c2[0] * p[:, 3:3 + n] + c2[1] * p[:, 2:2 + n] + c2[2] * p[:, 1:1 + n] + c2[3] * p[:, 0:n]
        return d1, d2

    def derivatives(self, X: np.ndarray, V0: np.ndarray,
                    history: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """ẋ and ẍ of X (ns, points, …) with initial velocities V0 (ns, …) (used for the
        second-order states only); or, given the ``history`` (ns, 3: x_{−3}, x_{−2},
        x_{−1}) of a window that continues a solved one, the plain stencils over it."""
        return self._apply(X, V0, X.shape[1], history)

    def derivatives_transposed(self, w1: np.ndarray, w2: np.ndarray) -> np.ndarray:
        """D1ᵀ·w1 + D2ᵀ·w2 with respect to X (the v0 part is not needed: it is no unknown
        of the trajectory), for w (ns, points, …)."""
        ns, n = w1.shape[:2]
        tail = w1.shape[2:]
        pw = np.zeros((ns, n + 3) + tail)
        c1, c2 = self.c1, self.c2
        for k in range(3):
            pw[:, 3 - k:3 - k + n] += c1[k] * w1
        for k in range(4):
            pw[:, 3 - k:3 - k + n] += c2[k] * w2
        out = pw[:, 3:].copy()
        # Ghost x_{−k} (pw[:, 3 − k]) = x0·a_k + x1·b_k.
        sel = self.second.reshape((-1,) + (1,) * len(tail))
        for k in (1, 2, 3):
            g = pw[:, 3 - k]
            a = np.where(sel, 1.0 - k * k, 1.0 + k)
            b = np.where(sel, float(k * k), -float(k))
            out[:, 0] += a * g
            out[:, 1] += b * g
        return out


# --------------------------------------------------------------------------------------
# The solver.


@dataclass
class TrajectorySolution:
    """The model over a whole record from its fitted initial state (model points, SI)."""

    label: str
    frequency_hz: float
    inputs: np.ndarray  # (n_inputs, M)
    states: np.ndarray  # (n_states, M)
    dstates: np.ndarray
    ddstates: np.ndarray
    initial: np.ndarray  # z0: x(t_0) of every state, then ẋ(t_0) of the second-order ones
    iterations: int  # Newton iterations of the last trajectory solve
    residual_norm: float
    factorization: Factorization = field(repr=False)
    initial_states: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  # dX/dz0 (ns, M, nz)
    initial_outputs: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  # dŷ/dz0 (nout, N, nz)
    start: str = "given"


class TrajectorySolver:
    """Newton over a whole record, one banded system; the estimator's solver for one
    transient record (the periodic solver's interface)."""

    def __init__(self, model: CompiledModel, data: TransientData, output_idx: list[int]):
        self.model = model
        self.data = data
        self.output_idx = list(output_idx)
        n = data.inputs.shape[1]
        self.oversample = data.oversample
        self.points = (n - 1) * self.oversample + 1
        self.h = data.step_s / self.oversample
        self.stencils = Stencils(model.orders, self.h, self.points)
        self.refine = refinement(n, self.oversample)
        self.grid = SimpleNamespace(n=n, points=self.points, scheme="bdf2-transient")
        self.second = [j for j, o in enumerate(model.orders) if o == 2]
        self.nz = model.n_states + len(self.second)
        self.weights = data.weights()
        self.starts_used: dict[str, str] = {}
        self._refined_inputs = self._refine(data.inputs)
        # The last fitted initial state, the θ it was fitted at and dz0*/dθ there: the
        # next solve's prediction.
        self._last: tuple[np.ndarray, np.ndarray, list[int], np.ndarray] | None = None
        self._prior: tuple[np.ndarray, np.ndarray] | None = None  # initial state: mean, precision (nz, nz)

    # ----------------------------------------------------------------------------------
    def _refine(self, u: np.ndarray) -> np.ndarray:
        """Sample values (…, n[, k]) along axis 1 (or the last for 2-D) at the model points."""
        if self.oversample == 1:
            return u
        if u.ndim == 2:
            return np.asarray((self.refine @ u.T).T)
        a, n, k = u.shape
        return np.asarray(self.refine @ np.moveaxis(u, 1, 0).reshape(n, a * k)).reshape(-1, a, k).transpose(1, 0, 2)

    def _refine_t(self, w: np.ndarray) -> np.ndarray:
        """Transpose of :meth:`_refine` for (…, M, k)."""
        if self.oversample == 1:
            return w
        a, m, k = w.shape
        return np.asarray(self.refine.T @ np.moveaxis(w, 1, 0).reshape(m, a * k)).reshape(-1, a, k).transpose(1, 0, 2)

    def _sample(self, y: np.ndarray) -> np.ndarray:
        return y[:, ::self.oversample]

    def _sample_t(self, w: np.ndarray) -> np.ndarray:
        out = np.zeros((w.shape[0], self.points) + w.shape[2:])
        out[:, ::self.oversample] = w
        return out

    def _split(self, z0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ns = self.model.n_states
        v0 = np.zeros(ns)
        v0[self.second] = z0[ns:]
        return z0[:ns], v0

    # ----------------------------------------------------------------------------------
    def _factorize(self, gx: np.ndarray, gdx: np.ndarray, gddx: np.ndarray,
                   continued: bool = False) -> Factorization:
        """Banded LU of the record's Newton matrix (first point: the initial-state rows;
        ``continued``: a window with a fixed history, the model's equations everywhere)."""
        st = self.stencils
        neq, ns, m = gx.shape
        kl, ku = 4 * ns - 1, ns - 1
        rows = 2 * kl + ku + 1
        N = ns * m
        c1 = np.broadcast_to(st.c1[None, :, None], (ns, 4, m)).copy()
        c2 = np.broadcast_to(st.c2[None, :, None], (ns, 4, m)).copy()
        head = min(4, m)
        if not continued:
            c1[:, :, :head] = st.head1[:, :, :head]
            c2[:, :, :head] = st.head2[:, :, :head]
        abT = np.zeros((m, ns, rows))  # column (ν, j), band row kl + ku + r − c
        for k in range(4):
            if k >= m:
                break
            for i in range(neq):
                for j in range(ns):
                    coef = c1[j, k] * gdx[i, j] + c2[j, k] * gddx[i, j]
                    if k == 0:
                        coef = coef + gx[i, j]
                    coef = coef[k:].copy()  # rows μ = k…m−1, columns ν = μ − k
                    if not continued:
                        coef[:max(0, 1 - k)] = 0.0  # row μ = 0 holds the initial-state equation instead
                    abT[:m - k, j, kl + ku + k * ns + i - j] = coef
        if not continued:
            abT[0, np.arange(ns), kl + ku] = 1.0  # x(t_0) − x0 = 0
        lu, piv, info = lapack.dgbtrf(abT.reshape(N, rows).T, kl, ku, overwrite_ab=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular record Jacobian (banded LU pivot {info})")

        def solver(trans: int):
            def solve(rhs: np.ndarray) -> np.ndarray:
                x, info = lapack.dgbtrs(lu, kl, ku, rhs.reshape(N, -1), piv, trans=trans)
                return x.reshape(rhs.shape)
            return solve

        return Factorization(solver(0), solver(1))

    def _residual(self, X: np.ndarray, DX: np.ndarray, DDX: np.ndarray, U: np.ndarray, theta: np.ndarray,
                  x0: np.ndarray | None) -> np.ndarray:
        G = self.model.residual(X, DX, DDX, U, theta)
        if x0 is not None:
            G[:, 0] = X[:, 0] - x0
        return G

    def _newton(self, U: np.ndarray, theta: np.ndarray, z0: np.ndarray, X: np.ndarray, label: str,
                history: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, Factorization]:
        """The trajectory from z0 (states at every model point of U), Newton from X; or,
        given the ``history`` of the three points before U, the continuation of it."""
        m, st = self.model, self.stencils
        ns = m.n_states
        first, v0 = self._split(z0)
        X = X.copy()
        x0: np.ndarray | None = None  # the initial-state equation's x(t_0), where there is one
        if history is None:
            X[:, 0] = x0 = first
        still = None if history is None else np.zeros_like(history)  # a step leaves the history alone
        tol = TOLERANCE * m.state_scales[:, None]
        DX, DDX = st.derivatives(X, v0, history)
        G = self._residual(X, DX, DDX, U, theta, x0)
        jac = m.residual_jacobian(X, DX, DDX, U, theta)
        gx, gdx, gddx = jac
        size = (np.abs(gx).mean(-1) + np.abs(gdx).mean(-1) / self.h + np.abs(gddx).mean(-1) / self.h**2) \
            @ m.state_scales
        weights = (1.0 / np.maximum(size, 1e-300))[:, None] * np.ones((1, X.shape[1]))
        if history is None:
            weights[:, 0] = 1.0 / m.state_scales
        merit = float(np.sum((weights * G) ** 2))
        for it in range(NEWTON_ITERATIONS + 1):
            if it:
                jac = m.residual_jacobian(X, DX, DDX, U, theta)
            if not np.isfinite(merit):
                break
            try:
                fac = self._factorize(*jac, continued=history is not None)
            except np.linalg.LinAlgError:
                break
            dX = -fac.solve(np.ascontiguousarray(G.T).ravel()).reshape(-1, ns).T
            if not np.all(np.isfinite(dX)):
                break
            d1, d2 = st.derivatives(dX, np.zeros(ns), still)
            if float(np.max(np.abs(dX) / tol)) <= 1.0:
                return X + dX, DX + d1, DDX + d2, it + 1, fac
            if it == NEWTON_ITERATIONS:
                break
            lam, Xt, D1, D2, Gt, trial = damped_step((X, DX, DDX), (dX, d1, d2), weights, merit,
                                                     lambda X, D1, D2: self._residual(X, D1, D2, U, theta, x0))
            if not np.isfinite(trial):
                break
            if lam < 1.0 / 1024 and float(np.max(np.abs(dX) / m.state_scales[:, None])) <= STAGNATION:
                # Rounding: over a long record the residual's last digits no longer fall;
                # the step left is far below what any output resolves.
                return X, DX, DDX, it + 1, fac
            X, DX, DDX, G, merit = Xt, D1, D2, Gt, trial
        rms = float(np.sqrt(merit / G.size)) if np.isfinite(merit) else float("nan")
        raise ConvergenceError(f"{label or 'record'}: the trajectory over the record did not converge in {it} Newton "
                               f"iterations (scaled residual {rms:.3g}, {X.shape[1]} points)", label, it, rms)

    def _march(self, U: np.ndarray, theta: np.ndarray, z0: np.ndarray, label: str) -> np.ndarray:
        """A start for the whole record: windows solved in turn, each continuing the last
        one's stencils exactly (its last three points as history), so that together they
        are the whole record's solution.  Windows double while Newton converges in a few
        iterations from a constant guess and halve where it does not (a loop over
        windows, not over time points: tens of them for 10⁵ points)."""
        m = self.model
        ns = m.n_states
        total = U.shape[1]
        X = np.empty((ns, total))
        begin, size = 0, WINDOW
        while begin < total:
            end = min(total, begin + size)
            if total - end < 4:  # a tail too short for the stencils joins this window
                end = total
            if begin == 0:
                guess = np.repeat(z0[:ns, None], end, axis=1)
            else:  # the last point moved on along the last step
                slope = X[:, begin - 1] - X[:, begin - 2]
                guess = X[:, begin - 1, None] + slope[:, None] * np.arange(1, end - begin + 1)
            try:
                if begin == 0:
                    Xw, _, _, its, _ = self._newton(U[:, :end], theta, z0, guess, label)
                else:
                    Xw, _, _, its, _ = self._newton(U[:, begin:end], theta, z0, guess, label, X[:, begin - 3:begin])
            except ConvergenceError:
                if size <= MIN_WINDOW:
                    raise
                size //= 2
                continue
            X[:, begin:end] = Xw
            begin = end
            size = min(2 * size, MAX_WINDOW) if its <= FAST_NEWTON else size
        return X

    # ----------------------------------------------------------------------------------
    def initial_guess(self, theta: np.ndarray, measured: Measured | None) -> np.ndarray:
        """z0 from the first INITIAL_SAMPLES samples: the measured outputs mapped to states
        (least squares, least norm in state-scaled units where they do not determine every
        state, from the rest state for the first input), a quadratic through them in time
        for x(t_0) and ẋ(t_0)."""
        m = self.model
        u0 = self.data.inputs[:, 0]
        rest = rest_state(m, u0, theta, 1e-9)
        x = m.static_guess(theta) if rest is None else rest.states
        ns = m.n_states
        if measured is None:
            return np.concatenate([x, np.zeros(len(self.second))])
        k = min(INITIAL_SAMPLES, measured.values.shape[1])
        X = np.repeat(x[:, None], k, axis=1)
        U = self.data.inputs[:, :k]
        zero = np.zeros_like(X)
        scales = m.state_scales
        w = np.sqrt(self.weights)
        for _ in range(20):
            y = m.output(X, zero, zero, U, theta)[measured.outputs]
            hx = m.output_jacobian(X, zero, zero, U, theta)[0][measured.outputs]
            H = np.moveaxis(w[:, None, None] * hx * scales[None, :, None], -1, 0)  # (k, outputs, states)
            r = np.moveaxis(w[:, None] * (measured.values[:, :k] - y), -1, 0)
            dz = np.stack([np.linalg.lstsq(H[i], r[i], rcond=1e-10)[0] for i in range(k)])  # k ≤ 16 points
            X = X + dz.T * scales[:, None]
            if not np.all(np.isfinite(X)):
                X = np.repeat(x[:, None], k, axis=1)
                break
            if np.all(np.abs(dz) <= 1e-6):
                break
        t = np.arange(k) * self.data.step_s
        degree = min(2, k - 1)
        fit, extra = np.polynomial.polynomial.polyfit(t, X.T, degree, full=True)  # (deg + 1, ns)
        x0 = fit[0]
        v0 = fit[1] if fit.shape[0] > 1 else np.zeros(ns)
        if self._prior is None and degree == 2 and k > 3:
            # The initial velocities' prior: their standard error from these samples, widened.
            scatter = np.sqrt(np.asarray(extra[0], dtype=float).reshape(-1)[:ns] / (k - 3)) if len(extra[0]) else \
                np.zeros(ns)
            V = np.vander(t, 3, increasing=True)
            se = scatter * np.sqrt(np.linalg.inv(V.T @ V)[1, 1]) * VELOCITY_PRIOR_WIDTH
            precision = np.zeros(self.nz)
            for c, j in enumerate(self.second):
                if se[j] > 0:
                    precision[ns + c] = 1.0 / se[j] ** 2
            self._prior = (np.concatenate([x0, v0[self.second]]), np.diag(precision))
        return np.concatenate([x0, v0[self.second]])

    def _initial_sensitivities(self, sol_states: tuple[np.ndarray, np.ndarray, np.ndarray], theta: np.ndarray,
                               fac: Factorization) -> tuple[np.ndarray, np.ndarray]:
        """dX/dz0 (ns, M, nz) and dŷ/dz0 (nout, N, nz) of the fitted outputs."""
        m, st = self.model, self.stencils
        ns, M = m.n_states, self.points
        X, DX, DDX = sol_states
        U = self._refined_inputs
        _, gdx, gddx = m.residual_jacobian(X[:, :4], DX[:, :4], DDX[:, :4], U[:, :4], theta)
        rhs = np.zeros((M, ns, self.nz))
        rhs[0, np.arange(ns), np.arange(ns)] = 1.0  # −∂G/∂x0 of x(t_0) − x0
        head = min(4, M)
        for c, j in enumerate(self.second):
            # −∂g_μ/∂v0_j = −(∂g/∂ẋ_j·∂ẋ_j/∂v0 + ∂g/∂ẍ_j·∂ẍ_j/∂v0), rows μ = 1…3
            col = -(gdx[:, j, :head] * st.v1[j, :head] + gddx[:, j, :head] * st.v2[j, :head])
            col[:, 0] = 0.0
            rhs[:head, :, ns + c] = col.T
        dX = fac.solve(rhs.reshape(M * ns, self.nz)).reshape(M, ns, self.nz).transpose(1, 0, 2)
        dV0 = np.zeros((ns, self.nz))
        for c, j in enumerate(self.second):
            dV0[j, ns + c] = 1.0
        return dX, self._output_response(X, DX, DDX, theta, dX, dV0)

    def _output_response(self, X: np.ndarray, DX: np.ndarray, DDX: np.ndarray, theta: np.ndarray, dX: np.ndarray,
                         dV0: np.ndarray) -> np.ndarray:
        """Output perturbations (nout, N, k) of state perturbations dX (ns, M, k) with
        initial velocity perturbations dV0 (ns, k); data points."""
        d1, d2 = self.stencils.derivatives(dX, dV0)
        hx, hdx, hddx = self.model.output_jacobian(X, DX, DDX, self._refined_inputs, theta)
        o = self.output_idx
        dY = (np.einsum("ojn,jnk->onk", hx[o], dX) + np.einsum("ojn,jnk->onk", hdx[o], d1)
              + np.einsum("ojn,jnk->onk", hddx[o], d2))
        return self._sample(dY)

    # ----------------------------------------------------------------------------------
    def solve(self, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray, start: np.ndarray | None = None,
              label: str = "", measured: Measured | None = None,
              max_iterations: int | None = None) -> TrajectorySolution:
        """The trajectory at θ from the initial state fitted to the ``measured`` outputs
        (module docstring); ``start`` (states at the model points) warm-starts Newton, the
        initial state then predicted from the last fit's dz0*/dθ."""
        del inputs, max_iterations  # the record's own inputs; the solver's own iteration limit
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", LinAlgWarning)
            return self._solve(frequency_hz, theta, start, label, measured)

    def _solve(self, frequency_hz: float, theta: np.ndarray, start: np.ndarray | None, label: str,
               measured: Measured | None) -> TrajectorySolution:
        U = self._refined_inputs
        how = "given"
        if start is not None and self._last is not None:
            z_last, th_last, idx, dz = self._last
            z0 = z_last + dz @ (theta - th_last)[idx]
            X = start
        else:
            z0 = self.initial_guess(theta, measured)
            try:
                X = self._march(U, theta, z0, label)
            except np.linalg.LinAlgError as exc:
                raise ConvergenceError(f"{label}: marching start failed ({exc})", label) from exc
            how = "march"
        w = self.weights
        X, DX, DDX, its, fac = self._newton(U, theta, z0, X, label)
        dXz, Sz = self._initial_sensitivities((X, DX, DDX), theta, fac)
        for _ in range(INITIAL_ITERATIONS if measured is not None else 0):
            y = self._sample(self.model.output(X, DX, DDX, U, theta)[self.output_idx])
            assert measured is not None
            r = measured.values - y
            prior_mean, precision = self._prior_terms()
            A = np.einsum("onk,o,onl->kl", Sz, w, Sz) + precision
            g = np.einsum("onk,o,on->k", Sz, w, r) - precision @ (z0 - prior_mean)
            dz = _scaled_solve(A, g)
            if float(dz @ g) <= INITIAL_CHI2:
                break
            X, DX, DDX, its, fac, z0 = self._moved(U, theta, z0, dz, X, dXz, label)
            dXz, Sz = self._initial_sensitivities((X, DX, DDX), theta, fac)
        G = self._residual(X, DX, DDX, U, theta, self._split(z0)[0])
        sol = TrajectorySolution(label, frequency_hz, U, X, DX, DDX, z0, its,
                                 float(np.sqrt(np.mean((G / self.model.state_scales[:, None]) ** 2))), fac,
                                 dXz, Sz, how)
        if how == "march":
            self.starts_used[label] = "initial state from the first samples, marched"
        if self._last is None:
            self._last = (z0, theta.copy(), [], np.zeros((self.nz, 0)))
        return sol

    def _moved(self, U: np.ndarray, theta: np.ndarray, z0: np.ndarray, dz: np.ndarray, X: np.ndarray, dXz: np.ndarray,
               label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, Factorization, np.ndarray]:
        """The trajectory from the initial state moved by dz: Newton from the first-order
        prediction, else from a new march; a step neither reaches is halved (a far
        initial state's transient is where Newton from the old trajectory stalls)."""
        for attempt in range(MOVE_ATTEMPTS):
            trial = z0 + dz
            try:
                return (*self._newton(U, theta, trial, X + dXz @ dz, label), trial)
            except ConvergenceError:
                try:
                    return (*self._newton(U, theta, trial, self._march(U, theta, trial, label), label), trial)
                except ConvergenceError:
                    if attempt == MOVE_ATTEMPTS - 1:
                        raise
            dz = dz / 2
        raise AssertionError("unreachable")

    def _prior_terms(self) -> tuple[np.ndarray, np.ndarray]:
        if self._prior is None:
            return np.zeros(self.nz), np.zeros((self.nz, self.nz))
        return self._prior

    # ----------------------------------------------------------------------------------
    def outputs(self, sol: TrajectorySolution, theta: np.ndarray, outputs: list[int]) -> np.ndarray:
        y = self.model.output(sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        return self._sample(y[outputs])

    def sensitivities(self, sol: TrajectorySolution, theta: np.ndarray, indices: list[int],
                      outputs: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """dX/dθ (ns, M, k) and dŷ/dθ (nout, N, k) with the initial state refitted:
        projected onto the complement of dŷ/dz0 (variable projection)."""
        if list(outputs) != self.output_idx:
            raise ValueError("a trajectory solver's sensitivities are for the outputs it fits")
        m = self.model
        ns, M = m.n_states, self.points
        args = (sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        gth = m.residual_dtheta(*args)[:, indices, :]  # (neq, k, M)
        gth[:, :, 0] = 0.0  # the initial-state rows do not depend on θ
        rhs = np.transpose(gth, (2, 0, 1)).reshape(M * ns, len(indices))
        dX = -sol.factorization.solve(rhs).reshape(M, ns, len(indices)).transpose(1, 0, 2)
        hth = m.output_dtheta(*args)[outputs][:, indices, :]
        dY = self._output_response(sol.states, sol.dstates, sol.ddstates, theta, dX, np.zeros((ns, len(indices))))
        dY = dY + self._sample(np.transpose(hth, (0, 2, 1)))
        Sz, w = sol.initial_outputs, self.weights
        A = np.einsum("onk,o,onl->kl", Sz, w, Sz) + self._prior_terms()[1]
        B = np.einsum("onk,o,onl->kl", Sz, w, dY)
        dz = -_scaled_solve(A, B)  # dz0*/dθ (nz, k)
        self._last = (sol.initial, theta.copy(), list(indices), dz)
        return dX + sol.initial_states @ dz, dY + Sz @ dz

    def output_sensitivities(self, sol: TrajectorySolution, theta: np.ndarray, indices: list[int],
                             outputs: list[int]) -> np.ndarray:
        return self.sensitivities(sol, theta, indices, outputs)[1]

    def input_response(self, sol: TrajectorySolution, theta: np.ndarray, outputs: list[int],
                       du: np.ndarray) -> np.ndarray:
        """dŷ/du applied to k input perturbations du (n_inputs, N, k): (nout, N, k), at
        the fitted initial state (the estimate's own response to them is the projection,
        which S̃ᵀW already applies)."""
        m = self.model
        ns, M = m.n_states, self.points
        du = self._refine(du)
        args = (sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        gu = m.residual_dinput(*args)
        rhs = np.einsum("ijn,jnk->nik", gu, du)
        rhs[0] = 0.0
        k = du.shape[2]
        dX = -sol.factorization.solve(rhs.reshape(M * ns, k)).reshape(M, ns, k).transpose(1, 0, 2)
        hu = m.output_dinput(*args)[outputs]
        return (self._output_response(sol.states, sol.dstates, sol.ddstates, theta, dX, np.zeros((ns, k)))
                + self._sample(np.einsum("ojn,jnk->onk", hu, du)))

    def input_adjoint(self, sol: TrajectorySolution, theta: np.ndarray, outputs: list[int],
                      w: np.ndarray) -> np.ndarray:
        """(dŷ/du)ᵀ applied to output weights w (nout, N, k): (n_inputs, N, k)."""
        m = self.model
        ns, M = m.n_states, self.points
        k = w.shape[2]
        wf = self._sample_t(w)
        args = (sol.states, sol.dstates, sol.ddstates, sol.inputs, theta)
        hx, hdx, hddx = (h[outputs] for h in m.output_jacobian(*args))
        lam = np.einsum("ojn,onk->jnk", hx, wf) + self.stencils.derivatives_transposed(
            np.einsum("ojn,onk->jnk", hdx, wf), np.einsum("ojn,onk->jnk", hddx, wf))
        rhs = np.ascontiguousarray(lam.transpose(1, 0, 2)).reshape(M * ns, k)
        mu = sol.factorization.solve_transposed(rhs).reshape(M, ns, k).transpose(1, 0, 2)
        mu[:, 0] = 0.0  # the initial-state rows: no input there
        gu = m.residual_dinput(*args)
        hu = m.output_dinput(*args)[outputs]
        adjoint = -np.einsum("ijn,ink->jnk", gu, mu) + np.einsum("ojn,onk->jnk", hu, wf)
        return self._refine_t(adjoint)


def _scaled_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A⁻¹·b for a normal matrix whose unknowns differ in scale by decades (m beside
    m/s beside K), least norm in unit-diagonal scaling where A is singular (a state the
    outputs do not see)."""
    d = np.sqrt(np.abs(np.diag(A)))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
    scaled = np.linalg.pinv(d[:, None] * A * d[None, :], rcond=1e-12)
    return (d[:, None] * scaled * d[None, :]) @ b
