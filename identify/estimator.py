"""The modified Bayesian Gauss–Newton estimator over periodic experiments (paper eq. 16–20).

Residuals e = y − ŷ(θ) of all experiments α, grid points μ and fitted channels β share
one parameter vector.  The step solves

    (SᵀWS + diag(1/w)) Δθ = SᵀW e,    W = diag(1/v_αβ)

where the normal prior N(θ_k, diag(w)) is reset to the current estimate at every
iteration: a damped, scale-aware Gauss–Newton.  Where the full step does not lower the
objective, it is halved.  Periodic solutions are warm-started from the last ones, and
sensitivities come from the Jacobian factorisation of each converged solution.

The weights are the paper's channel variances with a known shape across experiments:
v_αβ = λ_β·e_αβ, where e_αβ is the variance of one grid value that the measurement noise
explains (the folded output noise plus the force input's noise propagated through the
damper, both from the period-to-period scatter of the record) and λ_β the channel's
factor, re-estimated from the pooled residuals at every iteration with the bias
correction for the estimated parameters.  The shape differs by a factor ten and more
between a 0.04 Hz and a 2 Hz record.  Variances estimated per experiment from its own
residuals would rest on a few degrees of freedom: the force noise reaches the stroke
through the stiff gas spring as a low-pass signal (the mean force error alone shifts
the static stroke of a low-pressure record by several µm), so such weights follow the
noise realisation, and the sandwich below, which holds the weights fixed, then
overstated σ by 1.3–1.8× (Monte-Carlo, docs/uncertainty.md).  Where a record's noise
cannot be estimated, each (experiment, channel) falls back to its residual variance.

Standard deviations come from a sandwich covariance A⁻¹·B·A⁻¹: the measured force is
the model's input, and its noise reaches the outputs filtered by the damper's dynamics,
so the residuals are coloured and the white-noise formula A⁻¹ alone would misstate the
uncertainty.  B takes the noise covariance of the folded grid exactly (fold operator F:
interpolated grid values share samples) for the outputs and, through dŷ/du from the
same Jacobian factorisation, for the input.  The standard deviations are those of the
measurement noise; residuals beyond it (model error) are flagged, not hidden in σ.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from identify.differentiation import Grid
from identify.errors import ComputationError, InputError
from identify.fit_warnings import FitWarning, WarningCode
from identify.folding import FoldedRecord
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.periodic import ConvergenceError, PeriodicSolver
from identify.preparation import MULTISINE_LINES, PeriodicData, excited_lines
from identify.result import ExperimentFit, FitResult
from identify.solution import PeriodicSolution
from identify.start import MEASURED_NEWTON, Measured, measured_start
from identify.trajectory import TrajectorySolver, TransientData, Unfolded

DEFAULT_PRIOR_FRACTION = 0.5  # prior std as a fraction of |θ| where none is given
MODEL_ERROR_RATIO = 2.0  # residual RMS over what the noise explains, above which a warning is given
RANK = 8  # random responses whose span is taken as the dominant part of the input-noise response
PROBES = 8  # random probes estimating the rest of it
NOISE_REFRESH = 0.02  # the noise model follows θ once it has moved by this many prior standard deviations
# ... and once the Gauss-Newton steps have become shorter than this many prior standard
# deviations: the weights matter where the fit converges, not on the way there (the
# standard set's first steps move 0.9, 0.6 and 0.1; two refreshes instead of four).
NOISE_SETTLED = 0.05
# A trial this many prior standard deviations from the last solutions starts Newton from
# the measurements instead of them (identify.start's measured start): the standard set's
# first trial takes 75 Newton iterations so against 137 from the moved last solutions.
# 0.25 restarted the 3-5 experiment sessions of bench_batch half as often again for 3 %
# fewer factorisations, which the inversions cost back.
MEASURED_RESTART = 0.5
LINE_PULL_FLOOR = 1e-12  # a frequency line pulling less than this (relative) carries no residual: not a unit
INPUT_NOISE_NOTE = 0.25  # a share of the residual variance above which the input noise's part is reported
CHI2_TOLERANCE = 0.1  # a Gauss-Newton step promising less χ² decrease than this changes nothing that matters
# Iterations that each lower the objective by less than CREEP_DECREASE (about χ² units),
# CREEP_ITERATIONS or more of them before the fit stops: a creep along a nearly flat
# direction, which the message then names.
CREEP_DECREASE = 1.0
CREEP_ITERATIONS = 4



class RecordSolver(Protocol):
    """What the estimator asks of a record's solver: :class:`PeriodicSolver` for a
    periodic record folded onto one period, :class:`identify.trajectory.TrajectorySolver`
    for a record fitted as a transient.  Solutions are the solver's own."""

    grid: Any  # .n: the record's grid values per channel (propagated noise is a mean over them)
    starts_used: dict[str, str]

    def solve(self, inputs: np.ndarray, frequency_hz: float, theta: np.ndarray, start: np.ndarray | None = None,
              label: str = "", measured: Measured | None = None, max_iterations: int | None = None) -> Any: ...

    def outputs(self, sol: Any, theta: np.ndarray, outputs: list[int]) -> np.ndarray: ...

    def sensitivities(self, sol: Any, theta: np.ndarray, indices: list[int],
                      outputs: list[int]) -> tuple[np.ndarray, np.ndarray]: ...

    def input_response(self, sol: Any, theta: np.ndarray, outputs: list[int], du: np.ndarray) -> np.ndarray: ...

    def input_adjoint(self, sol: Any, theta: np.ndarray, outputs: list[int], w: np.ndarray) -> np.ndarray: ...


Record = PeriodicData | TransientData


def scaled_pinv(A: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a normal matrix whose parameters differ in scale by many decades
    (θ3 ≈ 5e3 beside θ9 ≈ 4e-5 spans ~17 in AᵀA): pinv's relative cut-off would drop the
    large parameter's direction and report a σ of 1e-16.  Inverting the unit-diagonal
    matrix D·A·D, D = diag(A)^-1/2, and scaling back keeps every direction the data hold."""
    d = np.sqrt(np.abs(np.diag(A)))
    d = np.where(d > 0, 1 / np.where(d > 0, d, 1.0), 0.0)
    return d[:, None] * np.linalg.pinv(d[:, None] * A * d[None, :]) * d[None, :]


def _line_pulls(Sw: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(lines, k) shares of the pull Σ_outputs Sw·r (Sw (n_out, n, k), r (n_out, n)) of
    each frequency line of one period, summing to it (Parseval for real signals)."""
    n = r.shape[1]
    share = np.full(n // 2 + 1, 2.0 / n)
    share[0] = 1.0 / n
    if n % 2 == 0:
        share[-1] = 1.0 / n
    cross = np.conj(np.fft.rfft(Sw, axis=1)) * np.fft.rfft(r, axis=1)[:, :, None]  # (n_out, lines, k)
    return cross.real.sum(axis=0) * share[:, None]



def input_draws(folded: FoldedRecord | Unfolded, input_noise_variance: np.ndarray) -> np.ndarray:
    """F·σu applied to fixed unit draws (seed 0), RANK then PROBES of them:
    (n_inputs, n, RANK + PROBES), for :func:`propagated_variance`."""
    rng = np.random.default_rng(0)
    n_in, m = len(input_noise_variance), len(folded.filled_counts)
    su = np.sqrt(input_noise_variance)[:, None, None]
    z = [su * folded.noise_factor(rng.standard_normal((n_in, m, k))) for k in (RANK, PROBES)]
    return np.concatenate(z, axis=2)


def propagated_variance(solver: RecordSolver, sol: Any, theta: np.ndarray, output_idx: list[int],
                        folded: FoldedRecord | Unfolded, input_noise_variance: np.ndarray,
                        draws: np.ndarray) -> np.ndarray:
    """(n_outputs,) mean over the grid of diag(H·Σu·Hᵀ): the output variance that the
    folded input noise Σu = F·diag(σu²)·Fᵀ causes, H = dŷ/du, i.e. ‖H·F·σu‖²_F / n.

    Hutch++ (Meyer, Musco, Musco & Woodruff 2021): the response is low-pass, a few
    directions carry most of it (a gas spring passes the mean force error and a few
    harmonics), which plain random probes estimate poorly.  Their span, found from
    RANK random responses, is taken exactly through the adjoint; probes estimate the
    rest.  The ``draws`` (:func:`input_draws`) are fixed, so the result is a
    deterministic function of θ."""
    n_in, m, n_out = len(input_noise_variance), len(folded.filled_counts), len(output_idx)
    su = np.sqrt(input_noise_variance)[:, None, None]
    # H·F·σu applied to the RANK span draws and the PROBES probes in one solve: (n_out, n, RANK + PROBES)
    responses = solver.input_response(sol, theta, output_idx, draws)
    Q = np.linalg.qr(responses[:, :, :RANK])[0]  # an orthonormal basis per output: (n_out, n, RANK)
    basis = np.einsum("onr,op->onpr", Q, np.eye(n_out)).reshape(n_out, Q.shape[1], n_out * RANK)
    exact = su * folded.noise_factor_t(solver.input_adjoint(sol, theta, output_idx, basis))
    exact = np.sum(exact.reshape(n_in, m, n_out, RANK) ** 2, axis=(0, 1, 3))
    G = responses[:, :, RANK:]
    rest = G - Q @ (np.swapaxes(Q, 1, 2) @ G)  # BLAS; einsum's loop over the grid took 30x longer
    return (exact + np.sum(rest**2, axis=(1, 2)) / PROBES) / solver.grid.n


def noise_meat(solver: RecordSolver, sol: Any, theta: np.ndarray, output_idx: list[int],
               folded: FoldedRecord | Unfolded, noise_variance: np.ndarray, input_noise_variance: np.ndarray,
               Sw: np.ndarray) -> np.ndarray:
    """(k, k) SᵀW·Cov·WS of one experiment (Sw = W·S, (n_out, n, k)): the folded output
    noise and the folded input noise through the adjoint (Hᵀ·W·S), each with the fold's
    exact grid covariance σ²·F·Fᵀ; the middle of the sandwich covariance."""
    Fy = folded.noise_factor_t(Sw)
    B = np.einsum("omk,o,oml->kl", Fy, noise_variance, Fy)
    Fu = folded.noise_factor_t(solver.input_adjoint(sol, theta, output_idx, Sw))
    return B + np.einsum("jmk,j,jml->kl", Fu, input_noise_variance, Fu)


class EstimationError(ComputationError):
    """The fit cannot start (e.g. no periodic solution at the starting parameters)."""


class PriorError(InputError):
    """An estimated parameter whose prior cannot be sized (start and nominal 0, no prior_std)."""


@dataclass
class _Evaluation:
    theta: np.ndarray
    solutions: list[Any]  # PeriodicSolution or TrajectorySolution, as each record's solver gives
    predicted: list[np.ndarray]  # (n_outputs, n) per experiment
    residuals: list[np.ndarray]
    sensitivities: list[np.ndarray] = field(default_factory=list)  # dŷ/dθ (n_outputs, n, k)
    state_sensitivities: list[np.ndarray] = field(default_factory=list)  # dX/dθ (n_states, n, k)
    noise: np.ndarray | None = None  # (n_experiments, n_outputs) grid variance the noise explains; None: unknown
    input_noise: np.ndarray | None = None  # the part of ``noise`` the folded input noise causes (errors in variables)


class Estimator:
    """Joint estimation of the varying parameters over a set of experiments: periodic
    records on the grid of one period, transient records sample by sample
    (:class:`TransientData`), each with its own solver and the same objective, weights and σ."""

    def __init__(self, model: CompiledModel, data: list[Record], params: Parameters, grid: Grid,
                 outputs: list[str], max_iterations: int = 40, step_tolerance: float = 0.05,
                 progress: Callable[[int, float, np.ndarray], None] | None = None, stability: bool = False,
                 time_limit_s: float | None = None, announce: Callable[[str], None] | None = None):
        if not data:
            raise EstimationError("no periodic experiment to fit")
        if not params.varying():
            raise EstimationError("no parameter to estimate")
        self.model = model
        self.data = data
        self.params = params
        self.grid = grid
        self.solver = PeriodicSolver(model, grid)
        self.outputs = outputs
        self.output_idx = [model.output_index(o) for o in outputs]
        self.solvers: dict[str, RecordSolver] = {
            d.label: TrajectorySolver(model, d, self.output_idx) if isinstance(d, TransientData) else self.solver
            for d in data}
        self.index = [params.index(nm) for nm in params.varying()]
        self.max_iterations = max_iterations
        self.step_tolerance = step_tolerance
        self.progress = progress
        self.stability = stability  # Floquet multipliers of each solution in the result
        self.announce = announce  # told of slow steps after the iterations (Floquet multipliers)
        self._noise_at: _Evaluation | None = None  # where the noise model was last computed
        self._draws: dict[str, np.ndarray] = {}  # label -> folded input-noise draws (_input_draws)
        self._inverted: dict[str, np.ndarray] = {}  # label -> states of its last measured start
        self.time_limit_s = time_limit_s  # no new iteration starts after this long
        self.residual_units: tuple[str, float, float] | None = None  # of the last residual-based covariance
        self.lower, self.upper = (b[self.index] for b in params.bounds())
        self.start = params.vector()  # sizes the prior of a parameter whose value and nominal are 0

    # ----------------------------------------------------------------------------------
    def _evaluate(self, theta: np.ndarray, start: _Evaluation | None) -> _Evaluation:
        """The periodic solutions, outputs and residuals at θ (sensitivities and the noise
        model are added once it is accepted: :meth:`_add_sensitivities`)."""
        ev = _Evaluation(theta, [], [], [])
        far = start is not None and bool(np.max(np.abs(theta - start.theta)[self.index]
                                                / self._prior_std(start.theta)) > MEASURED_RESTART)
        for a, d in enumerate(self.data):
            th = d.theta(theta)
            measured = Measured(self.output_idx, d.measured)
            solver = self.solvers[d.label]
            # A transient record's solver starts from the record's own first samples.
            sol = self._from_measurements(d, th, measured) if far and isinstance(d, PeriodicData) else None
            if sol is None:
                sol = solver.solve(d.inputs, d.frequency_hz, th, start=self._predicted_states(start, a, theta),
                                   label=d.label, measured=measured)
            y = solver.outputs(sol, th, self.output_idx)
            ev.solutions.append(sol)
            ev.predicted.append(y)
            ev.residuals.append(d.measured - y)
        return ev

    def _from_measurements(self, d: PeriodicData, theta: np.ndarray, measured: Measured) -> PeriodicSolution | None:
        """The periodic solution started from the measurements, or None where that start
        cannot be made or Newton does not converge from it."""
        try:
            X = measured_start(self.model, self.grid, d.inputs, theta, measured, self._inverted.get(d.label))
            self._inverted[d.label] = X
            return self.solver.solve(d.inputs, d.frequency_hz, theta, start=X, label=d.label,
                                     max_iterations=MEASURED_NEWTON)
        except (ComputationError, np.linalg.LinAlgError):
            return None

    def _predicted_states(self, start: _Evaluation | None, a: int, theta: np.ndarray) -> np.ndarray | None:
        """Newton's warm start for experiment a at θ: the solution at the earlier θ moved
        along its sensitivities (first order), which saves Newton iterations per solve."""
        if start is None:
            return None
        states = start.solutions[a].states
        if not start.state_sensitivities:
            return states
        return states + start.state_sensitivities[a] @ (theta - start.theta)[self.index]

    def _add_sensitivities(self, ev: _Evaluation, settled: bool) -> bool:
        """What an accepted evaluation needs beyond the solutions: sensitivities and the
        noise model (:meth:`_update_noise`); whether the noise model was recomputed."""
        for sol, d in zip(ev.solutions, self.data, strict=True):
            dX, dY = self.solvers[d.label].sensitivities(sol, d.theta(ev.theta), self.index, self.output_idx)
            ev.state_sensitivities.append(dX)
            ev.sensitivities.append(dY)
        return self._update_noise(ev, settled)

    def _update_noise(self, ev: _Evaluation, settled: bool) -> bool:
        """The grid variance the measurement noise explains at ev (ev.noise), recomputed
        only once the steps have ``settled``; whether it was.  Until the first such
        computation the output noise alone shapes the weights: the force noise
        propagated through the model costs about half an evaluation and depends on θ,
        so it is not worth computing on the way to the optimum."""
        if not all(d.noise_estimable() for d in self.data):
            return False
        last = self._noise_at
        if last is None and not settled:
            noise = np.array([d.grid_variance for d in self.data])
            ev.noise = noise if np.all(noise > 0) else None
            return False
        # The propagated noise changes with θ as the gas stiffness does: it is reused while
        # θ stays within a percent or so.
        if last is not None and (not settled or np.all(np.abs(ev.theta - last.theta)[self.index]
                                                       <= NOISE_REFRESH * self._prior_std(ev.theta))):
            ev.noise, ev.input_noise = last.noise, last.input_noise
            return False
        propagated = np.array([self._propagated_variance(d, sol, d.theta(ev.theta))
                               for d, sol in zip(self.data, ev.solutions, strict=True)])
        noise = np.array([d.grid_variance for d in self.data]) + propagated
        # A channel with no noise at all (a noise-free simulation) gives no weight shape.
        ev.noise = noise if np.all(noise > 0) else None
        ev.input_noise = propagated
        self._noise_at = ev
        return True

    def _propagated_variance(self, d: Record, sol: Any, theta: np.ndarray) -> np.ndarray:
        """(n_outputs,) the grid variance the folded input noise causes (:func:`propagated_variance`)."""
        return propagated_variance(self.solvers[d.label], sol, theta, self.output_idx, d.folded, d.input_noise_variance,
                                   self._input_draws(d))

    def _input_draws(self, d: Record) -> np.ndarray:
        """:func:`input_draws` of an experiment: they do not depend on θ, so each
        experiment's are drawn and folded once per fit, not at every noise refresh."""
        if d.label not in self._draws:
            self._draws[d.label] = input_draws(d.folded, d.input_noise_variance)
        return self._draws[d.label]

    def _residual_variances(self, ev: _Evaluation) -> np.ndarray:
        """(n_experiments, n_outputs) residual variance of each experiment and channel with
        the bias correction for the estimated parameters (their degrees of freedom shared
        by all residuals)."""
        n_total = sum(r.size for r in ev.residuals)
        out = np.empty((len(ev.residuals), len(self.outputs)))
        for a, r in enumerate(ev.residuals):
            dof = r.shape[1] - len(self.index) * r.shape[1] / n_total
            out[a] = np.sum(r**2, axis=1) / dof
        return np.maximum(out, 1e-300)

    def _variances(self, ev: _Evaluation) -> np.ndarray:
        """(n_experiments, n_outputs) weights v_αβ = λ_β·e_αβ (see the module docstring);
        the residual variances where the noise is not known."""
        if ev.noise is None:
            return self._residual_variances(ev)
        n_total = sum(r.size for r in ev.residuals)
        n_channel = n_total / len(self.outputs)
        dof = n_channel - len(self.index) * n_channel / n_total
        scaled = sum(np.sum(r**2, axis=1) / ev.noise[a] for a, r in enumerate(ev.residuals))
        return np.maximum(ev.noise * (scaled / dof), 1e-300)

    def _weigh(self, ev: _Evaluation) -> np.ndarray:
        """:meth:`_variances` at ev, also handed to the transient records' solvers: their
        initial states are fitted with these weights, so that the projected sensitivities
        are those of this objective (with other weights the Gauss–Newton steps stalled
        13σ from the optimum, where the channels' factors differed threefold)."""
        v = self._variances(ev)
        for a, d in enumerate(self.data):
            solver = self.solvers[d.label]
            if isinstance(solver, TrajectorySolver):
                solver.weights = 1.0 / v[a]
        return v

    @staticmethod
    def _objective(ev: _Evaluation, v: np.ndarray) -> float:
        return float(sum(np.sum(np.sum(r**2, axis=1) / v[a]) for a, r in enumerate(ev.residuals)))

    @staticmethod
    def _log_likelihood_objective(ev: _Evaluation, v: np.ndarray) -> float:
        """Σ N·log v: the objective with the variances concentrated out; it falls as the fit improves."""
        return float(sum(r.shape[1] * np.sum(np.log(v[a])) for a, r in enumerate(ev.residuals)))

    def _normal_equations(self, ev: _Evaluation, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = len(self.index)
        A = np.zeros((k, k))
        g = np.zeros(k)
        for a, (S, r) in enumerate(zip(ev.sensitivities, ev.residuals, strict=True)):
            wa = 1.0 / v[a]  # (n_outputs,)
            Sw = S * wa[:, None, None]
            A += np.einsum("onk,onl->kl", Sw, S)
            g += np.einsum("onk,on->k", Sw, r)
        return A, g

    def _variance_coupling(self, ev: _Evaluation, v: np.ndarray) -> np.ndarray:
        """Curvature that the re-estimated variances remove from the objective.

        With the variances concentrated out, the objective is Σ N·log v(θ); its
        Gauss–Newton Hessian is the weighted AᵀA minus Σ (2/N)·(Sᵀr/v)(Sᵀr/v)ᵀ over each
        set of residuals that shares one estimated variance (a channel over all
        experiments; an experiment's channel where the noise is not known).  Without
        this term the iteration between θ and v converges only linearly when channels
        compete (model error, offsets)."""
        pairs = zip(ev.sensitivities, ev.residuals, strict=True)
        # (n_exp, n_out, k)
        b = np.array([np.einsum("onk,on->ok", S, r) / v[a][:, None] for a, (S, r) in enumerate(pairs)])
        n = np.array([r.shape[1] for r in ev.residuals], dtype=float)
        if ev.noise is not None:
            b, n = b.sum(axis=0, keepdims=True), n.sum(keepdims=True)
        return np.einsum("a,aok,aol->kl", 2.0 / n, b, b)

    def _prior_std(self, theta: np.ndarray) -> np.ndarray:
        """Prior standard deviations of the varying parameters: as given, or a fraction of
        the parameter's size (its current, nominal or start value; :meth:`_check_priors`
        refuses a parameter for which all three are zero)."""
        out = np.empty(len(self.index))
        nominal = self.model.nominal_vector()
        names = self.params.names()
        for i, j in enumerate(self.index):
            std = self.params[names[j]].prior_std
            if std is None:
                std = DEFAULT_PRIOR_FRACTION * max(abs(theta[j]), abs(nominal[j]), abs(self.start[j]))
            out[i] = std
        return out

    def _check_priors(self, ev: _Evaluation) -> None:
        """Refuses varying parameters without prior_std whose start and nominal are both 0:
        there is no size to scale their steps by.  A fixed 1 in SI units was used before,
        and a cubic stiffness of 1e10 N/m³ then crept by ones and "converged" where it
        started.  The message suggests the change that moves the fitted outputs by their
        RMS (to first order, from the sensitivities at the start) as an upper guide."""
        unscaled, names = [], []
        for i, j in enumerate(self.index):
            p = self.params[self.params.names()[j]]
            if p.prior_std is not None or self._prior_std(ev.theta)[i] > 0:
                continue
            signal = sensitivity = 0.0
            for d, S in zip(self.data, ev.sensitivities, strict=True):
                size = np.maximum(np.sqrt(np.mean(d.measured**2, axis=1)), 1e-300)  # outputs in their own sizes
                signal += float(np.sum((d.measured / size[:, None]) ** 2))
                sensitivity += float(np.sum((S[:, :, i] / size[:, None]) ** 2))
            guide = (f"{np.sqrt(signal / sensitivity):.2g} {p.unit} would move the fitted outputs by their RMS"
                     if sensitivity > 0 else "the fitted outputs do not depend on it at the start")
            unscaled.append(f"{p.name} ({p.alias}: here {guide})")
            names.append(p.name)
        if unscaled:
            raise PriorError(f"no prior std for {'; '.join(unscaled)}: start and nominal are 0, so nothing sets the "
                             f"size of the steps; give each a prior_std in the START file, "
                             f'{{"{names[0]}": {{"value": 0, "prior_std": ...}}}}, '
                             f"a size the term may plausibly reach")

    # ----------------------------------------------------------------------------------
    def fit(self) -> FitResult:
        """Run Gauss–Newton to convergence and return the result with uncertainties.

        Stopped by the iteration cap, the time limit or Ctrl-C (KeyboardInterrupt, once
        the start is evaluated), the result holds the last accepted iterate, not
        converged, so that a fit started from it goes on from there."""
        t0 = time.perf_counter()
        theta = self.params.vector()
        try:
            ev = self._evaluate(theta, None)
            self._add_sensitivities(ev, settled=False)
            self._check_priors(ev)
        except ConvergenceError as exc:
            raise EstimationError(f"no periodic solution at the starting parameters: {exc}") from exc
        v = self._weigh(ev)
        objective = self._objective(ev, v)
        history = [self._log_likelihood_objective(ev, v)]
        self._last: tuple[_Evaluation, int] = (ev, 0)  # the last complete iterate and its number
        interrupted = False
        try:
            converged, iterations, message, ev = self._iterate(ev, v, objective, history, t0)
        except KeyboardInterrupt:
            (ev, iterations), converged, interrupted = self._last, False, True
            message = f"interrupted (Ctrl-C) after {iterations} iterations: the last iterate, not converged"
        self._update_noise(ev, settled=True)  # weights and σ at the result's θ, where the fit stopped early too
        v = self._weigh(ev)
        result = self._result(ev, v, converged, iterations, message, history, time.perf_counter() - t0)
        result.interrupted = interrupted
        return result

    def _iterate(self, ev: _Evaluation, v: np.ndarray, objective: float, history: list[float],
                 t0: float) -> tuple[bool, int, str, _Evaluation]:
        """Gauss–Newton from ev: (converged, the steps taken, message, last accepted evaluation)."""
        theta = ev.theta
        converged = False
        message = f"stopped after {self.max_iterations} iterations without meeting the step tolerance"
        iterations = 0
        for it in range(1, self.max_iterations + 1):
            if self.time_limit_s is not None and time.perf_counter() - t0 > self.time_limit_s:
                message = (f"stopped at the time limit ({self.time_limit_s:g} s) after {iterations} iterations "
                           f"without meeting the step tolerance")
                break
            iterations = it
            A, g = self._normal_equations(ev, v)
            A_coupled = A - self._variance_coupling(ev, v)
            # Far from the optimum the correction would make the step uphill.
            coupled = np.min(np.linalg.eigvals(np.linalg.solve(A, A_coupled)).real) >= 0.1
            scale = self._prior_std(theta)  # solve in prior-std units: well scaled, zeros included
            sigma = np.sqrt(np.abs(np.diag(scaled_pinv(A))))
            for A_step in ((A_coupled, A) if coupled else (A,)):
                As = A_step * np.outer(scale, scale) + np.eye(len(scale))
                step = self._bounded_step(theta[self.index], As, g * scale, scale)
                small = bool(np.all(np.abs(step) <= self.step_tolerance * np.maximum(sigma, 1e-300)))
                predicted = float(g @ step - 0.5 * step @ A @ step)
                # A step below the tolerance, or one that would lower χ² by less than the data
                # can tell apart, is converged already: not worth the evaluation it would cost.
                negligible = small or 0.0 <= predicted < CHI2_TOLERANCE
                accepted, lam = (None, 0.0) if negligible else self._line_search(ev, step, v, objective)
                # The line search judges χ² at fixed variances, the plain Gauss–Newton
                # model; where the coupled step fails it (and is not a converged one),
                # the plain step is tried.
                if accepted is not None or negligible:
                    break
            if accepted is None:
                # The objective is Σ r²/v (χ² units); a step that would lower it by less
                # than CHI2_TOLERANCE is beyond what the data can tell apart, and the line
                # search then only sees the periodic solutions' numerical noise.
                iterations = it - 1  # the steps taken, as many as the progress reported
                converged = negligible
                flat = self.params.names()[self.index[int(np.argmax(np.abs(step) / np.maximum(sigma, 1e-300)))]]
                message = ("converged (the remaining step is below the tolerance)" if small else
                           f"converged (the remaining step would lower χ² by {predicted:.2g} < {CHI2_TOLERANCE:g}: "
                           f"the objective is nearly flat along it, mostly {flat}{self._creep(history)})"
                           if converged else
                           f"line search failed: no decrease of the objective along the Gauss–Newton step "
                           f"(predicted χ² decrease {predicted:.3g})")
                break
            theta = accepted.theta
            ev = accepted
            refreshed = self._add_sensitivities(ev, settled=bool(np.all(np.abs(lam * step) <= NOISE_SETTLED * scale)))
            v = self._weigh(ev)
            objective = self._objective(ev, v)
            history.append(self._log_likelihood_objective(ev, v))
            self._last = (ev, it)  # complete (sensitivities, weights): what an interrupted fit reports
            if self.progress:
                self.progress(it, history[-1], theta[self.index])
            if refreshed:
                continue  # new weights, a new optimum: the next step says whether θ is at it
            if np.all(np.abs(lam * step) <= self.step_tolerance * np.maximum(sigma, 1e-300)):
                converged = True
                message = f"converged (last step below {self.step_tolerance:g} standard deviations)"
                break
        return converged, iterations, message, ev

    @staticmethod
    def _creep(history: list[float]) -> str:
        """Where the last iterations each lowered the objective by less than CREEP_DECREASE:
        a clause saying how long the fit crept, else "".  Stopping such a creep earlier was
        tried and refused: a two-mode fit crept so for five iterations before it found the
        optimum, 370 lower (a step far below the residual-based σ there is no sign of
        arrival, since that σ is large wherever the fit is poor)."""
        drops = -np.diff(history)
        slow = 0
        while slow < drops.size and drops[drops.size - 1 - slow] < CREEP_DECREASE:
            slow += 1
        if slow < CREEP_ITERATIONS:
            return ""
        return (f"; the last {slow} iterations lowered the objective by {np.sum(drops[-slow:]):.2g} in all, a slow "
                f"creep: this optimum is shallow, and another start may end elsewhere")

    def _bounded_step(self, x: np.ndarray, As: np.ndarray, gs: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """The Gauss–Newton step from x (solved in prior-std units) for projected
        Gauss–Newton: a parameter on a bound that the step would push beyond it is held
        there and the step re-solved for the others (clipping alone would keep their
        share of the pull towards it); the line search then follows the step projected
        onto the bounds, which goes downhill for small enough fractions (a step clipped
        once and shortened after would not).  A transformation (log, logit) was not
        taken: it would change the prior's shape and σ's meaning for every estimate, not
        only at a bound."""
        free = np.ones(x.size, bool)
        step = np.zeros(x.size)
        while free.any():
            step[:] = 0.0
            step[free] = scale[free] * np.linalg.solve(As[np.ix_(free, free)], gs[free])
            held = free & (((x <= self.lower) & (step < 0)) | ((x >= self.upper) & (step > 0)))
            if not held.any():
                break
            free &= ~held
        if not free.any():
            step[:] = 0.0
        return step

    def _line_search(self, ev: _Evaluation, step: np.ndarray, v: np.ndarray,
                     objective: float) -> tuple[_Evaluation | None, float]:
        """Backtracking along ``step`` from ev.theta, projected onto the bounds, until χ²
        (at the variances v) does not rise: (the accepted evaluation or None, its step fraction)."""
        lam = 1.0
        while lam >= 1.0 / 64:
            trial = ev.theta.copy()
            trial[self.index] = np.clip(trial[self.index] + lam * step, self.lower, self.upper)
            try:
                ev_t = self._evaluate(trial, ev)
            except ConvergenceError:
                lam /= 2
                continue
            if self._objective(ev_t, v) <= objective:
                return ev_t, lam
            lam /= 2
        return None, lam

    def _covariance(self, ev: _Evaluation, v: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, list[FitWarning]]:
        """Sandwich covariance A⁻¹·B·A⁻¹ of the estimates under the measurement noise:
        the folded output noise and the folded input noise propagated through the model
        (Hᵀ·W·S by the adjoint), each with the fold's exact grid covariance σ²·F·Fᵀ.
        Residuals well above what that noise explains mean systematic model error, which
        that covariance does not cover: they are reported as a warning, and the
        residual-based covariance is returned beside it (None otherwise).  Falls back to
        A⁻¹ (white residuals of the observed size) where the noise of a record cannot be
        estimated."""
        A, _ = self._normal_equations(ev, v)
        A_inv = scaled_pinv(A)
        notes = []
        if ev.noise is None:
            notes.append(FitWarning(WarningCode.NOISE_NOT_ESTIMABLE))
            return A_inv, None, notes
        k = len(self.index)
        B = np.zeros((k, k))
        for a, (d, sol, S) in enumerate(zip(self.data, ev.solutions, ev.sensitivities, strict=True)):
            B += noise_meat(self.solvers[d.label], sol, d.theta(ev.theta), self.output_idx, d.folded, d.noise_variance,
                            d.input_noise_variance, S / v[a][:, None, None])
        excess = self._residual_variances(ev) / ev.noise  # (n_experiments, n_outputs)
        flagged = []
        for b, o in enumerate(self.outputs):
            x = float(np.sqrt(excess[:, b].max()))
            if x > MODEL_ERROR_RATIO:
                flagged.append((o, x, self.data[int(np.argmax(excess[:, b]))].label))
        residual_cov, self.residual_units = self._residual_covariance(ev, v, A_inv) if flagged else (None, None)
        for o, x, worst in flagged:
            notes.append(FitWarning(WarningCode.MODEL_ERROR, {
                "output": o, "ratio": x, "worst": worst, "input_share": self._input_share(ev, o, worst),
                "residual_based": residual_cov is not None, "experiments": len(self.data), "parameters": k}))
        for b, o in enumerate(self.outputs):
            share = self._input_shares(ev, b)
            a = int(np.argmax(share))
            if self.model.input_derivatives and o not in {f[0] for f in flagged} and share[a] > INPUT_NOISE_NOTE:
                notes.append(FitWarning(WarningCode.INPUT_NOISE, {"output": o, "percent": float(100 * share[a]),
                                                                  "record": self.data[a].label}))
        return A_inv @ B @ A_inv, residual_cov, notes

    def _input_shares(self, ev: _Evaluation, b: int) -> np.ndarray:
        """(n_experiments,) the share of output b's residual variance that the folded input
        noise explains, per experiment."""
        if ev.input_noise is None:
            return np.zeros(len(self.data))
        return ev.input_noise[:, b] / self._residual_variances(ev)[:, b]

    def _input_share(self, ev: _Evaluation, output: str, label: str) -> float | None:
        """The share of a record's residual variance the inputs' folded noise explains
        (errors in variables), for the model-error warning of a model that takes an
        input's derivatives (whose folding noise it amplifies); None where there is none
        worth saying."""
        if not self.model.input_derivatives:  # the input itself, as always, not its folded derivative
            return None
        a = [d.label for d in self.data].index(label)
        share = float(self._input_shares(ev, self.outputs.index(output))[a])
        return share if share >= 0.005 else None

    def _residual_covariance(self, ev: _Evaluation, v: np.ndarray,
                             A_inv: np.ndarray) -> tuple[np.ndarray | None, tuple[str, float, float] | None]:
        """Cluster sandwich A⁻¹·(E/(E−k))·Σ_α g_α·g_αᵀ·A⁻¹ over E independent units, with
        g_α = S_αᵀ·W·r_α the pull of unit α's residuals on θ, whatever caused them; and
        the units (what they are, their effective number).

        Model error is systematic within an experiment but differs between experiments
        (another frequency, another stroke range), so experiments are the units where
        there are more of them than parameters.  Otherwise the frequency lines of the
        records are (Parseval splits each pull line by line): under a random-phase
        multisine the misfit of a wrong model structure varies with the phases from line
        to line like noise (Pintelon & Schoukens, the best linear approximation's
        stochastic distortions), so a second realisation moves θ by about what the
        scatter of the line pulls says.  E is then the number of lines that pull at all
        (no more of them than parameters: None).  Where a few lines carry most of the
        misfit (an unmodelled resonance), the estimate rests on few draws; the effective
        number returned beside E (the participation ratio of the lines' pulls in σ units)
        says how few, and the report quotes σ's own uncertainty from it."""
        E, k = len(self.data), len(self.index)
        pairs = list(zip(ev.sensitivities, ev.residuals, strict=True))
        if E > k:
            g = np.array([np.einsum("onk,on->k", S / v[a][:, None, None], r) for a, (S, r) in enumerate(pairs)])
            return A_inv @ (g.T @ g * E / (E - k)) @ A_inv, ("experiments", float(E), float(E))
        g = np.concatenate([self._unit_lines(d, _line_pulls(S / v[a][:, None, None], r))
                            for a, (d, (S, r)) in enumerate(zip(self.data, pairs, strict=True))])
        q = np.sum((g * np.sqrt(np.abs(np.diag(A_inv)))) ** 2, axis=1)  # each line's pull in σ² units
        lines = int(np.count_nonzero(q > LINE_PULL_FLOOR * q.max()))
        if lines <= k:
            return None, None
        what = "excited frequency lines" if all(self._broadband(d) for d in self.data) else "frequency lines"
        return A_inv @ (g.T @ g * lines / (lines - k)) @ A_inv, (what, float(lines),
                                                                  float(np.sum(q) ** 2 / np.sum(q**2)))

    @staticmethod
    def _broadband(d: Record) -> bool:
        return excited_lines(d.inputs).size >= MULTISINE_LINES

    def _unit_lines(self, d: Record, pulls: np.ndarray) -> np.ndarray:
        """The lines of a record that are units of the residual-based covariance: of a
        multisine its excited lines, whose misfit varies with the random phases like
        noise (the lines between them carry distortion and noise, not draws of the
        excitation: counting them gave 921 lines where 267 were excited); of a sine
        record every line (its harmonics)."""
        return pulls[excited_lines(d.inputs)] if self._broadband(d) else pulls

    # ----------------------------------------------------------------------------------
    def _result(self, ev: _Evaluation, v: np.ndarray, converged: bool, iterations: int, message: str,
                history: list[float], elapsed: float) -> FitResult:
        cov, residual_cov, notes = self._covariance(ev, v)
        std = np.sqrt(np.abs(np.diag(cov)))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = cov / np.outer(std, std)
        params = self.params.copy()
        params.set_vector(ev.theta)
        d = self.model.declaration
        chans = [d.outputs[o] for o in self.outputs]
        experiments = []
        for a, dat in enumerate(self.data):
            floquet = None
            if self.stability and isinstance(dat, PeriodicData):  # a transient record has no periodic orbit
                # Integrating the variational equation over a long multisine period takes
                # far longer than a fit step: say what the wait is for.
                t0 = time.perf_counter()
                if self.announce:
                    self.announce(f"Floquet multipliers of {dat.label} ({a + 1} of {len(self.data)}) ...")
                floquet = self.solver.floquet_multipliers(ev.solutions[a], dat.theta(ev.theta))
                if self.announce:
                    self.announce(f"Floquet multipliers of {dat.label}: largest |μ| {np.abs(floquet[0]):.4g}, "
                                  f"{time.perf_counter() - t0:.1f} s")
            experiments.append(ExperimentFit(
                label=dat.label, frequency_hz=dat.frequency_hz,
                measured={c.column: c.from_si(dat.measured[b]) for b, c in enumerate(chans)},
                predicted={c.column: c.from_si(ev.predicted[a][b]) for b, c in enumerate(chans)},
                newton_iterations=ev.solutions[a].iterations,
                floquet=floquet,
            ))
        unstable = [e.label for e in experiments if e.floquet is not None and np.abs(e.floquet[0]) >= 1.0]
        if unstable:
            notes.append(FitWarning(WarningCode.UNSTABLE_ORBIT, {"records": unstable}))
        # Weighted, parameter-scaled sensitivities for the identifiability check.
        blocks = []
        for a, S in enumerate(ev.sensitivities):
            w = np.sqrt(1.0 / v[a])
            blocks.append((S * w[:, None, None]).reshape(-1, len(self.index)))
        Sw = np.vstack(blocks) * self._prior_std(ev.theta)
        singular = np.linalg.svd(Sw, compute_uv=False) if Sw.size else np.array([])
        return FitResult.build(
            model=self.model, params=params, estimated=[self.params.names()[j] for j in self.index],
            std=std, correlation=corr, covariance=cov, outputs=self.outputs,
            experiments=experiments, converged=converged, iterations=iterations, message=message,
            objective_history=history, elapsed_s=elapsed, n_grid=self.grid.n, scheme=self.grid.scheme,
            singular_values=singular, sensitivity_matrix=Sw, notes=notes,
            # Never below the noise-only σ: residuals above the noise cannot make an estimate
            # surer than the noise alone does (a per-record offset read 0.028* against 0.155).
            std_residual=None if residual_cov is None else np.maximum(np.sqrt(np.abs(np.diag(residual_cov))), std),
            covariance_residual=residual_cov, residual_units=self.residual_units,
        )
