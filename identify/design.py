"""Optimal design of periodic experiments: which experiments, and how many periods of
each, identify the quantities asked for to a given precision at the least cost.

Information.  A candidate periodic experiment is one period of the model's inputs on
the grid (what the rig will impose, predicted at a prior parameter set).  Its
sensitivities dŷ/dθ at that parameter set give what the estimator (identify.estimator)
will compute from its data: the normal matrix A = SᵀWS with the estimator's weights
W = 1/v (the folded output noise plus the input noise propagated through the model),
and the meat of its sandwich covariance B = SᵀW·Cov·WS, with Cov the fold's exact grid
covariance of the output noise and of the input noise through dŷ/du.  Both grow with
the number of captured periods in proportion (W and 1/Cov alike), so they are computed
per period once per candidate and a plan's covariance is

    C = (Σ p_α·A_α + P)⁻¹ (Σ p_α·B_α + P) (Σ p_α·A_α + P)⁻¹

with P the prior precision (the prior covariance's inverse; zero for the estimator's
σ, which its prior, reset at every iteration, does not enter).  Where B = A (white
noise, exact weights) this is the Fisher information's inverse.

Quantities.  The criteria are taken on chosen parameters or on derived quantities
(a QC characteristic: a function of θ), whose covariance is J·C·Jᵀ with J their
derivatives by the estimated parameters (the linear propagation of the fit's own σ).

Criteria.  D: log det(J·C·Jᵀ) per quantity (the geometric mean variance; scale-free);
A: Σ (σ_i/scale_i)²; σ: max σ_i/target_i, at most 1 where every quantity meets its
target.

Optimiser.  Greedy on information per cost, then pruning: starting from an empty plan
(or the experiments a caller requires), it adds the move — a new experiment with a
number of periods, or more periods of one already chosen — that lowers the criterion
most per second of cost, until the targets hold (or the budget is spent), then removes
or shortens what the result does not need.  The cost of a plan is a callable the
caller supplies (the rig's predicted seconds, which depend on the order: each
experiment starts from where the one before left the damper), evaluated only for a
shortlist of the moves the information ranks best, because it is what takes time.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from identify.differentiation import Grid
from identify.errors import InputError
from identify.estimator import input_draws, noise_meat, propagated_variance, scaled_pinv
from identify.folding import fold
from identify.model import CompiledModel
from identify.periodic import PeriodicSolver


class Criterion(StrEnum):
    """What a design optimises: ``SIGMA`` the least cost for a σ per quantity;
    ``D`` (the determinant) or ``A`` (the scaled trace) of the quantities' covariance
    within a budget."""

    SIGMA = "sigma"
    D = "D"
    A = "A"
SHORTLIST = 6           # moves per greedy step whose cost is evaluated (each a call of the caller's cost)
DERIVATIVE_STEP = 1e-5  # relative step of the central differences of a derived quantity
REFERENCE_PERIODS = 4   # the fold whose grid covariance scales to one period (see experiment_information)


class DesignError(InputError):
    """A design problem that cannot be posed (no candidate, targets of the wrong size, ...)."""


@dataclass(frozen=True)
class Candidate:
    """One periodic experiment that could be run: one period of the model's inputs on the
    grid (``inputs`` (n_inputs, n), SI) at ``frequency_hz``, sampled at ``sample_rate_hz``.
    ``states``: the periodic states (n_states, n) where the caller knows them (a start for
    Newton); ``settings``: what the caller needs to run it (opaque here)."""

    label: str
    frequency_hz: float
    inputs: np.ndarray
    sample_rate_hz: float
    states: np.ndarray | None = None
    settings: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Noise:
    """Per-sample standard deviations (SI) of the fitted outputs and of the inputs."""

    outputs: np.ndarray
    inputs: np.ndarray


@dataclass(frozen=True)
class Information:
    """What one captured period of a candidate adds to the estimator's normal matrix
    (``A``) and to its sandwich's meat (``B``), over the estimated parameters."""

    label: str
    A: np.ndarray
    B: np.ndarray


@dataclass(frozen=True)
class Quantities:
    """Named quantities judged by a criterion: their derivatives (q, k) by the estimated
    parameters."""

    names: tuple[str, ...]
    jacobian: np.ndarray


def experiment_information(model: CompiledModel, candidate: Candidate, theta: np.ndarray, estimate: Sequence[str],
                           outputs: Sequence[str], noise: Noise, n: int = 800, scheme: str = "bdf2") -> Information:
    """The information of one captured period of ``candidate`` at the parameter vector
    ``theta`` (full, SI) on the estimated parameters, as the estimator weighs it.

    The fold of the capture is that of REFERENCE_PERIODS periods at the candidate's sample
    rate, divided by their number: with a whole number of samples per period the bins'
    counts grow with the periods exactly, otherwise to within a sample."""
    index = [model.parameter_index(p) for p in estimate]
    out_idx = [model.output_index(o) for o in outputs]
    solver = PeriodicSolver(model, Grid(n, scheme))
    sol = solver.solve(candidate.inputs, candidate.frequency_hz, theta, start=candidate.states, label=candidate.label)
    _, S = solver.sensitivities(sol, theta, index, out_idx)                       # (n_out, n, k)
    per_period = candidate.sample_rate_hz / candidate.frequency_hz
    t = np.arange(int(math.ceil(REFERENCE_PERIODS * per_period))) / candidate.sample_rate_hz
    folded = fold(candidate.label, t, {}, candidate.frequency_hz, n, candidate.sample_rate_hz)
    yvar, uvar = np.asarray(noise.outputs, float) ** 2, np.asarray(noise.inputs, float) ** 2
    # The estimator's weights: each output's grid variance from its own noise and,
    # through dŷ/du, from the inputs'.
    v = yvar * folded.grid_factor + propagated_variance(solver, sol, theta, out_idx, folded, uvar,
                                                        input_draws(folded, uvar))
    Sw = S / v[:, None, None]
    A = np.einsum("onk,onl->kl", Sw, S)
    B = noise_meat(solver, sol, theta, out_idx, folded, yvar, uvar, Sw)
    periods = len(t) / per_period
    return Information(candidate.label, A / periods, B / periods)


def parameter_quantities(estimate: Sequence[str], chosen: Sequence[str]) -> Quantities:
    """The chosen estimated parameters themselves."""
    unknown = [c for c in chosen if c not in estimate]
    if unknown:
        raise DesignError(f"{', '.join(unknown)}: not among the estimated parameters ({', '.join(estimate)})")
    return Quantities(tuple(chosen), np.eye(len(estimate))[[list(estimate).index(c) for c in chosen]])


def derived_quantities(functions: Mapping[str, Callable[[np.ndarray], float]], theta: np.ndarray,
                       index: Sequence[int]) -> Quantities:
    """Quantities computed from the whole parameter vector (SI): their derivatives by the
    estimated parameters (at positions ``index`` of θ), by central differences."""
    J = np.empty((len(functions), len(index)))
    for row, f in enumerate(functions.values()):
        for col, i in enumerate(index):
            h = DERIVATIVE_STEP * (abs(theta[i]) or 1.0)
            up, down = theta.copy(), theta.copy()
            up[i] += h
            down[i] -= h
            J[row, col] = (f(up) - f(down)) / (2 * h)
    return Quantities(tuple(functions), J)


def covariance(terms: Sequence[tuple[Information, float]], prior_precision: np.ndarray | None = None) -> np.ndarray:
    """Predicted covariance of the estimates from (information per period, periods) pairs:
    the estimator's sandwich, with the prior as one more unbiased source."""
    if not terms:
        raise DesignError("no experiment: nothing to predict a covariance from")
    A = sum(p * i.A for i, p in terms)
    B = sum(p * i.B for i, p in terms)
    if prior_precision is not None:
        A, B = A + prior_precision, B + prior_precision
    A_inv = scaled_pinv(np.asarray(A))
    return A_inv @ B @ A_inv


def sigmas(cov: np.ndarray, quantities: Quantities) -> np.ndarray:
    """Standard deviations of the quantities."""
    J = quantities.jacobian
    return np.sqrt(np.abs(np.einsum("qk,kl,ql->q", J, cov, J)))


def d_criterion(cov: np.ndarray, quantities: Quantities) -> float:
    """log det of the quantities' covariance per quantity (lower is better; −inf never:
    a degenerate plan gives +inf through its huge σ)."""
    J = quantities.jacobian
    sign, logdet = np.linalg.slogdet(J @ cov @ J.T)
    return float(logdet / len(J)) if sign > 0 else math.inf


def a_criterion(cov: np.ndarray, quantities: Quantities, scale: np.ndarray) -> float:
    """Σ (σ_i / scale_i)²."""
    return float(np.sum((sigmas(cov, quantities) / scale) ** 2))


def sigma_criterion(cov: np.ndarray, quantities: Quantities, targets: np.ndarray) -> float:
    """max σ_i / target_i: at most 1 where every quantity meets its target."""
    return float(np.max(sigmas(cov, quantities) / targets))


@dataclass(frozen=True)
class Choice:
    """A chosen experiment: index into the candidates, and its captured periods."""

    candidate: int
    periods: int


@dataclass(frozen=True)
class Design:
    """The optimiser's answer: the experiments in the order the cost was predicted for."""

    choices: tuple[Choice, ...]
    sigma: np.ndarray          # of the quantities
    cost: float                # the caller's cost of the whole sequence
    criterion: float
    met: bool                  # targets met (sigma criterion) or within the budget (D, A)
    cost_calls: int


class _Problem:
    """The criterion of a sequence, and the caller's cost with a cache."""

    def __init__(self, info: Sequence[Information], quantities: Quantities, criterion: Criterion,
                 targets: np.ndarray | None, scale: np.ndarray | None, prior: np.ndarray | None,
                 cost: Callable[[Sequence[Choice]], float],
                 estimate: Callable[[Sequence[Choice]], float] | None = None) -> None:
        self.info, self.quantities, self.criterion = info, quantities, criterion
        self.targets, self.scale, self.prior, self._cost = targets, scale, prior, cost
        self.estimate = estimate
        self._costs: dict[tuple[Choice, ...], float] = {}
        self.calls = 0

    def cov(self, seq: Sequence[Choice]) -> np.ndarray:
        return covariance([(self.info[c.candidate], c.periods) for c in seq], self.prior)

    def value(self, seq: Sequence[Choice]) -> float:
        """The criterion (lower is better); for the σ criterion the shortfall
        Σ max(0, log σ_i/target_i), zero exactly when every target is met."""
        if not seq:
            return math.inf
        cov = self.cov(seq)
        if self.criterion is Criterion.SIGMA:
            assert self.targets is not None
            return float(np.sum(np.maximum(0.0, np.log(sigmas(cov, self.quantities) / self.targets))))
        if self.criterion is Criterion.D:
            return d_criterion(cov, self.quantities)
        assert self.scale is not None
        return a_criterion(cov, self.quantities, self.scale)

    def cost(self, seq: Sequence[Choice]) -> float:
        key = tuple(seq)
        if key not in self._costs:
            self.calls += 1
            self._costs[key] = float(self._cost(key)) if key else 0.0
        return self._costs[key]


def optimise(info: Sequence[Information], quantities: Quantities, cost: Callable[[Sequence[Choice]], float], *,
             criterion: Criterion = Criterion.SIGMA, targets: Sequence[float] | np.ndarray | None = None,
             budget: float | None = None,
             scale: Sequence[float] | None = None, periods: Sequence[int] = (2, 3, 4, 6, 8, 12),
             required: Sequence[Choice] = (), max_experiments: int = 10,
             prior_precision: np.ndarray | None = None, shortlist: int = SHORTLIST,
             estimate: Callable[[Sequence[Choice]], float] | None = None) -> Design:
    """Experiments from the candidates (their ``info``) and their periods, in order.

    ``criterion`` SIGMA: the least-cost plan whose quantities' σ are each at most
    ``targets`` (``budget`` optional, a cap); "D" or "A" (``scale``: the quantities'
    sizes for A): the best criterion within ``budget``.  ``cost(sequence)`` is the
    caller's cost of running those choices in that order (e.g. rig seconds); it is
    called for a shortlist of moves per step only.  ``required``: choices every plan
    keeps (first, in this order).  ``estimate``: a quick approximation of ``cost`` by
    which the shortlist is drawn (most criterion per estimated cost); without it the
    moves that lower the criterion most are shortlisted, whatever they cost."""
    if not info:
        raise DesignError("no candidate experiment to choose from")
    if criterion not in set(Criterion):   # a caller without type checks
        raise DesignError(f"unknown criterion {criterion!r} (criteria: {', '.join(Criterion)})")
    criterion = Criterion(criterion)
    q = len(quantities.names)
    t = None if targets is None else np.asarray(targets, float)
    if criterion is Criterion.SIGMA and (t is None or t.shape != (q,) or not np.all(t > 0)):
        raise DesignError(f"the sigma criterion needs {q} positive targets, one per quantity")
    if criterion is not Criterion.SIGMA and budget is None:
        raise DesignError(f"the {criterion} criterion needs a budget")
    s = np.ones(q) if scale is None else np.asarray(scale, float)
    periods = sorted(set(int(p) for p in periods))
    if not periods or periods[0] < 1:
        raise DesignError("periods must be whole numbers of at least 1")
    problem = _Problem(info, quantities, criterion, t, s, prior_precision, cost, estimate)
    cap = math.inf if budget is None else budget
    size = max_experiments + len(required)

    def done(sequence: list[Choice]) -> bool:
        return criterion is Criterion.SIGMA and problem.value(sequence) <= 0.0

    def build(start: list[Choice], excluded: frozenset[int] = frozenset()) -> list[Choice]:
        grown = _greedy(problem, start, len(info), periods, done, cap, size, shortlist, excluded)
        return _prune(problem, grown, len(required), periods, done, cap)

    seq = build(list(required))
    # Exchange: greedy steps are myopic (one experiment seeing everything can beat two
    # cheaper ones that each see half only by the first step's measure); each chosen
    # experiment is taken out in turn and the plan completed without it, kept where
    # that is better.
    improved = True
    while improved:
        improved = False
        for k in range(len(required), len(seq)):
            trial = build(seq[:k] + seq[k + 1:], frozenset({seq[k].candidate}))
            if _better(problem, trial, seq, done):
                seq, improved = trial, True
                break
    cov = problem.cov(seq) if seq else None
    sigma = sigmas(cov, quantities) if cov is not None else np.full(q, math.inf)
    value = problem.value(seq)
    met = done(seq) if criterion is Criterion.SIGMA else bool(seq) and problem.cost(seq) <= cap
    return Design(tuple(seq), sigma, problem.cost(seq), value, met, problem.calls)


def _better(problem: _Problem, a: list[Choice], b: list[Choice], done: Callable[[list[Choice]], bool]) -> bool:
    """Whether plan a beats plan b: σ criterion, meeting the targets, then cost; D and A,
    the criterion (within the same budget)."""
    if problem.criterion is Criterion.SIGMA:
        if done(a) != done(b):
            return done(a)
        return problem.cost(a) < problem.cost(b) if done(a) else problem.value(a) < problem.value(b)
    return problem.value(a) < problem.value(b)


def _greedy(problem: _Problem, seq: list[Choice], n_candidates: int, periods: list[int],
            done: Callable[[list[Choice]], bool], cap: float, size: int, shortlist: int,
            excluded: frozenset[int]) -> list[Choice]:
    """Moves added one at a time, the most criterion per cost first, until done, out of
    budget or of room."""
    while not done(seq) and len(seq) < size:
        moves = [m for m in _moves(seq, n_candidates, periods) if m[-1].candidate not in excluded or
                 len(m) == len(seq)]
        values = [problem.value(m) for m in moves]
        now = problem.value(seq)
        if not math.isfinite(now):
            # From nothing (no plan, or one that does not see every quantity): gains are
            # counted from the worst first step that does, so that their rate per cost
            # still tells a cheap weak experiment from a dearer strong one.
            now = max((v for v in values if math.isfinite(v)), default=now)
        if problem.estimate is None:
            gains = sorted(((now - v, i) for i, v in enumerate(values)), reverse=True)
        else:
            guess = problem.estimate(seq)
            ranked = sorted(((now - v) / max(problem.estimate(moves[i]) - guess, 1e-9), i)
                            for i, v in enumerate(values) if now - v > 0)
            gains = [(now - values[i], i) for _, i in reversed(ranked)]
        base = problem.cost(seq)
        best, best_rate = None, 0.0
        for gain, i in gains[:shortlist]:
            if not gain > 0:
                break
            extra = problem.cost(moves[i]) - base
            if base + extra > cap:
                continue
            rate = gain / max(extra, 1e-9) if math.isfinite(gain) else math.inf
            # An infinite gain (the first experiments that make the quantities
            # identifiable at all): the cheapest of them.
            if best is None or rate > best_rate or (rate == best_rate == math.inf and extra < best[1]):
                best, best_rate = (moves[i], extra), rate
        if best is None:
            break
        seq = best[0]
    return seq


def _moves(seq: list[Choice], n_candidates: int, periods: list[int]) -> list[list[Choice]]:
    """Every sequence one step on: a candidate appended with each number of periods, or
    one chosen experiment given the next number of periods."""
    out = [seq + [Choice(c, p)] for c in range(n_candidates) for p in periods]
    for k, ch in enumerate(seq):
        more = [p for p in periods if p > ch.periods]
        if more:
            out.append(seq[:k] + [Choice(ch.candidate, more[0])] + seq[k + 1:])
    return out


def _prune(problem: _Problem, seq: list[Choice], keep: int, periods: list[int],
           done: Callable[[list[Choice]], bool], cap: float) -> list[Choice]:
    """Drop experiments and periods the result does not need: repeatedly the cheapest
    plan among those one experiment fewer or one step of periods shorter that still meets
    the targets (sigma criterion) or does not worsen the criterion (D, A)."""
    while True:
        now_cost, now_value = problem.cost(seq), problem.value(seq)
        trials = [seq[:k] + seq[k + 1:] for k in range(keep, len(seq))]
        for k, ch in enumerate(seq):
            fewer = [p for p in periods if p < ch.periods]
            if fewer:
                trials.append(seq[:k] + [Choice(ch.candidate, fewer[-1])] + seq[k + 1:])
        good = [s for s in trials if s and (done(s) if problem.criterion is Criterion.SIGMA else
                                            problem.value(s) <= now_value)]
        if problem.criterion is Criterion.SIGMA and not done(seq):
            good = []   # targets not reached: nothing to give away
        cheaper = [(problem.cost(s), s) for s in good]
        cheaper = [(c, s) for c, s in cheaper if c < now_cost and c <= cap]
        if not cheaper:
            return seq
        seq = min(cheaper, key=lambda cs: cs[0])[1]


__all__ = [
    "Candidate", "Choice", "Criterion", "Design", "DesignError", "Information", "Noise", "Quantities", "a_criterion",
    "covariance", "d_criterion", "derived_quantities", "experiment_information", "optimise", "parameter_quantities",
    "sigma_criterion", "sigmas",
]
