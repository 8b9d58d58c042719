"""How long a periodic experiment takes to settle, predicted from the damper model.

The acquisition (:mod:`rig.session.acquisition`) compares the channel means of consecutive
blocks of whole cycles and calls the experiment settled when no mean moves by more
than its threshold.  What moves is the gas temperature (and the pressure, which
follows it through the gas law): it drifts from wherever the lead-in left it
(the previous experiment's periodic state, cooled while the rig pauses, heated by
the move to the new static position) to the new periodic state, and relaxes slowly
where the wall area is small (high static positions).

The model's energy balance is a scalar ODE for the temperature under the imposed
stroke.  It is integrated (RK4, vectorised over experiments) through the lead-in,
and over one period from a Chebyshev grid of start temperatures to get the period
map T(t + P) = F(T(t)) and the per-cycle channel means as smooth functions of the
start temperature.  Iterating those maps gives the block means cycle by cycle, and
so the cycle count at which the criterion passes.  Transducer noise is left out:
the block means average thousands of samples, which puts their noise an order of
magnitude below the thresholds (checked against captured sessions).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, TypeVar

import numpy as np
from numpy.polynomial import chebyshev

from identify.model import CompiledModel, load_model
from identify.move_profile import CONTROLLER_MOVE, MoveProfile
from identify.parameters import Parameters
from identify.plans import ExperimentSpec
from rig.config import SteadyStateCriteria
from rig.planning.criterion import (
    MIN_BLOCKS,
    block_cycles,
    blocks_bias,
    change_passes,
    drift_passes,
    first_block_s,
    last_block_cycles,
)

FloatOrArray = TypeVar("FloatOrArray", float, np.ndarray)
PAUSE_S = 1.0                  # at rest between experiments: commands, handshakes, writing the data

# RK4 steps per half period of a waveform, integrated between the triangle's kinks
# (start temperatures within ~0.003 K of ten times as many steps), and the Chebyshev
# grid of start temperatures for the period maps, which are nearly affine (the slope
# varies by ~1e-5 over hundreds of kelvin): a low degree is exact far below the
# thresholds.
STEPS_PER_HALF_PERIOD = 12   # even: the cycle means use Simpson's rule
INSIDE = 1e-9                # of a step: where a stage or node on a kink is taken, into the step
CHEBYSHEV_DEGREE = 6
# Around ambient: adiabatic compression over the whole stroke about doubles the gas
# temperature; beyond the span the nearly affine series still extrapolates closely.
GRID_SPAN_K = (-150.0, 600.0)
MOVE_STEPS = 16               # the half-cosine move is smooth: within 1e-4 K of 256 steps
REST_STEPS = 16               # a relaxation (time constant >= 10 s): within 0.2 % for pauses up to a minute
# Conditioning holds: candidate positions evenly over the allowed range; secant steps on
# the map from a hold's end temperature to the first block's (nearly affine: two steps
# land within microkelvin); RK4 steps for a hold, a few per second of it (time constants
# of 10 s and more); and what a hold must save beyond its own time to be worth its
# extra commands, handshakes and the DAQ's start and stop.
HOLD_CANDIDATES = 27
SECANT_STEP_K = 1.0
SECANT_ITERATIONS = 2
HOLD_STEPS_PER_S = 2.0
HOLD_STEPS_MAX = 2048
HOLD_OVERHEAD_S = 2.0
# The drift criterion's prediction: noisy draws of the predicted block means (odd: a median).
DRIFT_DRAWS = 7
DRIFT_SEED = 20261123


@dataclass(frozen=True)
class Conditioning:
    """Where and how long the lead-in may hold the damper to pre-condition the gas:
    ``range_m`` (low, high) static positions, ``max_hold_s`` the longest hold."""

    range_m: tuple[float, float]
    max_hold_s: float
    min_hold_s: float = 1.0   # shorter holds land poorly: latencies are then a large part of them
    # How far off, in the rig's seconds, the acquisition may answer a hold's end (the
    # links' answer time times their pace): the gas, still relaxing there, lands off by
    # its rate times this, and the criterion waits that offset out.
    timing_s: float = 0.0


@dataclass(frozen=True)
class Hold:
    """A stop at a static position on the way to an experiment's own.  Settling waits for
    the gas to relax to the experiment's periodic temperature, slowest where the gas is
    compressed and its wall area small; compressed (or expanded) further than the
    experiment's position, the gas is further from that temperature and so gains or
    loses heat faster, and once it holds the heat the periodic state needs, the move on
    brings it there at once: settling starts near its end."""

    position_m: float
    duration_s: float             # predicted: the acquisition ends the hold on the measured temperature
    arrival_temperature_k: float  # the gas's, predicted on arrival at the hold
    end_temperature_k: float      # the gas's at the end of the hold, that brings it to the periodic state


@dataclass(frozen=True)
class SettlingPrediction:
    """What the steady-state criterion will do for one experiment."""

    letter: str
    cycles: int                   # cycles until the criterion passes (whole blocks, in [min, max])
    settled: bool                 # False: max_cycles reached first
    block_cycles: int             # cycles per comparison block
    start_temperature_k: float    # gas temperature when the first block begins
    periodic_temperature_k: float  # gas temperature at the same phase in the periodic state
    multiplier: float             # per-cycle decay of a temperature deviation (Floquet multiplier)
    limiting_channel: str         # closest to its threshold at the last comparison ("" without a thermal state)
    hold: Hold | None = None      # the conditioning hold on the way to it, where one saves rig time
    time_constant_s: float = math.nan  # of the gas's relaxation to the periodic state


def move_duration_s(distance_m: FloatOrArray, move: MoveProfile = CONTROLLER_MOVE) -> FloatOrArray:
    """Duration of the controller's move (:mod:`identify.move_profile`); ``move``: the
    rig's, ``RigConfig.move`` (the controller's datasheet by default)."""
    return move.durations_s(distance_m) if isinstance(distance_m, np.ndarray) else move.duration_s(distance_m)


def earliest_cycles(criteria: SteadyStateCriteria, frequency_hz: float) -> int:
    """Cycles of the first comparison that can pass: two blocks, min_cycles, whole blocks."""
    m = block_cycles(criteria, frequency_hz)
    return min(max(2, math.ceil(criteria.min_cycles / m)) * m, last_block_cycles(criteria, m))


class GasThermalModel:
    """The gas temperature's rate and the criterion's channels, from identify's compiled
    model: Ṫ solves the thermal residual, which is linear in Ṫ (an energy balance)."""

    def __init__(self, params: Parameters) -> None:
        self.model: CompiledModel = load_model(params.model_name)
        self.theta = params.vector()
        names = self.model.state_names
        self.has_thermal_state = "T" in names and "q" in names
        if self.has_thermal_state:
            self._iq, self._iT = names.index("q"), names.index("T")
            self.ambient_k = -params["ambient"].value
        decl = self.model.declaration
        self.channels = tuple(self.model.output_names)
        self._to_engineering = [decl.outputs[c].from_si for c in self.channels]

    def _states(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n = (self.model.n_states,) + shape
        return np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((len(self.model.input_names),) + shape)

    def temperature_rate(self, q: np.ndarray | float, v: np.ndarray | float, a: np.ndarray | float,
                         T: np.ndarray) -> np.ndarray:
        """dT/dt [K/s] under the imposed stroke q, q̇, q̈ (SI)."""
        # The residual at Ṫ = 0 and Ṫ = 1 in one call: Ṫ = -g(0) / (g(1) - g(0)).
        X, DX, DDX, U = self._states((2,) + np.broadcast_shapes(*map(np.shape, (q, v, a, T))))
        X[self._iq], DX[self._iq], DDX[self._iq], X[self._iT] = q, v, a, T
        DX[self._iT, 1] = 1.0
        g = self.model.residual(X, DX, DDX, U, self.theta)[self._iT]
        return -g[0] / (g[1] - g[0])

    def outputs(self, q: np.ndarray, v: np.ndarray, a: np.ndarray, T: np.ndarray) -> np.ndarray:
        """The model's outputs in engineering units (the DAQ's columns), stacked first."""
        X, DX, DDX, U = self._states(np.broadcast_shapes(*map(np.shape, (q, v, a, T))))
        X[self._iq], DX[self._iq], DDX[self._iq], X[self._iT] = q, v, a, T
        y = self.model.output(X, DX, DDX, U, self.theta)
        return np.stack([conv(row) for conv, row in zip(self._to_engineering, y, strict=True)])


Rate = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _shifted(rate: Rate, t0: np.ndarray, t: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``rate`` on a piece that starts at ``t0`` (time since RUN)."""
    return rate(t0 + t, T)


def _rk4(rate: Rate, T: np.ndarray, duration_s: np.ndarray, steps: int, nodes: bool = False) -> np.ndarray:
    """Integrate dT/dt = rate(t, T) over [0, duration] per row (time shape broadcasts to T).

    Returns the end values, or with ``nodes`` every step's values stacked first.  The
    first and last stages are taken just inside the step, so that a kink of the stroke
    on a step boundary is seen from the step's side."""
    h = np.asarray(duration_s, dtype=float) / steps
    if not nodes and not h.any():
        return T                  # e.g. no fade-out before the first experiment
    inside = INSIDE * h
    out = [T]
    for k in range(steps):
        t = k * h
        k1 = rate(t + inside, T)
        k2 = rate(t + h / 2, T + h / 2 * k1)
        k3 = rate(t + h / 2, T + h / 2 * k2)
        k4 = rate(t + h - inside, T + h * k3)
        T = T + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if nodes:
            out.append(T)
    return np.stack(out) if nodes else T


def _between_kinks(t_from_s: np.ndarray, duration_s: np.ndarray,
                   frequency_hz: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """[t_from, t_from + duration] (time since RUN, per row) cut where a triangle has its
    kinks, a quarter period after RUN and every half period on: the pieces' (start, end),
    rows with fewer pieces padded with empty ones.  RK4 keeps its order only where the
    stroke velocity is smooth; a sine is cut the same way, harmlessly."""
    half = 0.5 / frequency_hz
    end = t_from_s + duration_s
    first_kink = half * (np.floor(t_from_s / half - 0.5) + 1.5)          # the first after t_from
    kinks = int(np.max(np.ceil(np.maximum(end - first_kink, 0.0) / half)))
    cuts = [t_from_s + 0 * end] + [np.clip(first_kink + j * half, t_from_s, end) for j in range(kinks)] + [end]
    return list(zip(cuts[:-1], cuts[1:], strict=True))


def _rk4_waveform(rate: Rate, T: np.ndarray, t_from_s: np.ndarray, duration_s: np.ndarray,
                  frequency_hz: np.ndarray) -> np.ndarray:
    """:func:`_rk4` over a stretch of a waveform (``rate`` takes the time since RUN)."""
    for a, b in _between_kinks(t_from_s, duration_s, frequency_hz):
        T = _rk4(partial(_shifted, rate, a), T, b - a, STEPS_PER_HALF_PERIOD)
    return T


def _waveform(waveform: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit waveform, its derivative and second derivative with respect to phase (the
    controller's sine and triangle; the triangle's kinks carry no acceleration here)."""
    s, c = np.sin(phase), np.cos(phase)
    tri = waveform == "triangle"
    if not tri.any():
        return s, c, -s
    w = np.where(tri, (2 / np.pi) * np.arcsin(np.clip(s, -1, 1)), s)
    dw = np.where(tri, (2 / np.pi) * np.sign(c), c)
    ddw = np.where(tri, 0.0, -s)
    return w, dw, ddw


@dataclass(frozen=True)
class _Runs:
    """The experiments' waveforms as column arrays (SI), for vectorised strokes."""

    static_m: np.ndarray
    amplitude_m: np.ndarray
    frequency_hz: np.ndarray
    waveform: np.ndarray

    @classmethod
    def of(cls, experiments: Sequence[ExperimentSpec]) -> _Runs:
        return cls(np.array([e.static_position_mm * 1e-3 for e in experiments]),
                   np.array([e.amplitude_mm * 1e-3 for e in experiments]),
                   np.array([e.frequency_hz for e in experiments]),
                   np.array([e.waveform for e in experiments]))

    def stroke(self, t_run: np.ndarray, envelope: np.ndarray | float, denvelope: np.ndarray | float,
               index: Any = np.s_[:]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stroke at time ``t_run`` since RUN with an amplitude envelope (and its rate)."""
        s, A, f, wf = (x[index] for x in (self.static_m, self.amplitude_m, self.frequency_hz, self.waveform))
        omega = 2 * np.pi * f
        w, dw, ddw = _waveform(wf, omega * t_run)
        q = s + A * envelope * w
        v = A * (envelope * omega * dw + denvelope * w)
        a = A * (envelope * omega**2 * ddw + 2 * denvelope * omega * dw)
        return q, v, a


def predict_settling(experiments: Sequence[ExperimentSpec], criteria: SteadyStateCriteria, rate_hz: float,
                     params: Parameters | None = None, *, start_position_m: float = 0.0,
                     start_temperature_k: float | None = None, pause_s: float | Sequence[float] = PAUSE_S,
                     conditioning: Conditioning | None = None, noise_draws: int = DRIFT_DRAWS,
                     move: MoveProfile = CONTROLLER_MOVE) -> list[SettlingPrediction]:
    """Settle cycles of each experiment run in this order, the damper resting at
    ``start_position_m`` and ``start_temperature_k`` (default: ambient) before the first.

    Each experiment's lead-in starts from the previous one's periodic state (where it
    settled and was captured): its fade-out, ``pause_s`` at rest (one for all, or one
    per experiment), the move (by way of a conditioning hold where ``conditioning``
    allows one and it is predicted to save rig time), the amplitude ramp and the wait
    before the first block.
    ``params``: the damper's parameters (default: the 2-dof model's nominal values);
    ``noise_draws``: see :func:`_apply_drift_criterion`; ``move``: the controller's move
    profile (the rig's configuration, ``RigConfig.move``).
    """
    params = params if params is not None else Parameters(load_model("2dof"))
    gas = GasThermalModel(params)
    if not experiments:
        return []
    if not gas.has_thermal_state:
        return [SettlingPrediction(e.letter, earliest_cycles(criteria, e.frequency_hz), True,
                                   block_cycles(criteria, e.frequency_hz), math.nan, math.nan, 0.0, "")
                for e in experiments]
    runs = _Runs.of(experiments)
    t0 = first_block_s(criteria, rate_hz)
    period_map = _PeriodMap(gas, runs, t0)
    prev_static, T_rest = _after_previous(gas, runs, period_map, criteria, t0, start_position_m,
                                          gas.ambient_k if start_temperature_k is None else start_temperature_k,
                                          np.broadcast_to(np.asarray(pause_s, dtype=float), len(experiments)))
    T_start = _run_in(gas, runs, criteria, t0, _move(gas, move, prev_static, runs.static_m, T_rest))
    m = np.array([block_cycles(criteria, e.frequency_hz) for e in experiments])
    cycles, settled, limiting = _settle(period_map, T_start, m, gas.channels, criteria, runs, experiments, rate_hz,
                                        noise_draws)
    holds: list[Hold | None] = [None] * len(experiments)
    if conditioning is not None:
        position, duration, arrival_k, end_k = _plan_holds(gas, runs, period_map, criteria, t0, prev_static, T_rest,
                                                           conditioning, move)
        planned = np.isfinite(duration)
        if planned.any():
            steps = int(min(HOLD_STEPS_MAX, REST_STEPS + HOLD_STEPS_PER_S * duration[planned].max()))
            T_end = _rest(gas, position, _move(gas, move, prev_static, position, T_rest),
                          np.where(planned, duration, 0.0), steps)
            T_held, held = _settle_after_hold(gas, runs, period_map, criteria, t0, position, T_end,
                                              conditioning.timing_s, m, experiments, rate_hz, noise_draws, move)
            period = 1.0 / runs.frequency_hz
            direct_s = move.durations_s(runs.static_m - prev_static) + cycles * period
            held_s = (move.durations_s(position - prev_static) + np.where(planned, duration, 0.0)
                      + move.durations_s(runs.static_m - position) + held[0] * period)
            # A hold must pay for itself by more than the commands and waits it adds.
            better = planned & (held_s < direct_s - HOLD_OVERHEAD_S)
            T_start = np.where(better, T_held, T_start)
            cycles, settled, limiting = (np.where(better, h, d) for h, d in zip(held, (cycles, settled, limiting),
                                                                                   strict=True))
            holds = [Hold(float(position[i]), float(duration[i]), float(arrival_k[i]), float(end_k[i]))
                     if better[i] else None
                     for i in range(len(experiments))]
    tau = time_constants_s(period_map.multiplier, runs.frequency_hz)
    return [SettlingPrediction(e.letter, int(cycles[i]), bool(settled[i]), int(m[i]), float(T_start[i]),
                               float(period_map.fixed_point_k[i]), float(period_map.multiplier[i]),
                               gas.channels[limiting[i]], holds[i], float(tau[i]))
            for i, e in enumerate(experiments)]


def landing_error_k(gas: GasThermalModel, position_m: np.ndarray, end_temperature_k: np.ndarray,
                    timing_s: float) -> np.ndarray:
    """How far off [K] a hold lands when its end is answered ``timing_s`` of the rig's
    time early or late: the gas's rate at rest there, at the hold's end temperature,
    times that time (the gas model's energy balance; a hold's end is where it still
    relaxes fastest toward the wall)."""
    return np.abs(gas.temperature_rate(position_m, 0.0, 0.0, end_temperature_k)) * timing_s


def _settle_after_hold(gas: GasThermalModel, runs: _Runs, period_map: _PeriodMap, criteria: SteadyStateCriteria,
                       t0_s: float, position_m: np.ndarray, end_temperature_k: np.ndarray, timing_s: float,
                       m: np.ndarray, experiments: Sequence[ExperimentSpec], rate_hz: float,
                       draws: int, move: MoveProfile) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The gas at the first block after a hold ending at ``end_temperature_k``, and the
    criterion's settle cycles, whether it passes and the limiting channel from there.

    With a ``timing_s`` the hold's end is answered that much early or late, at random:
    the gas lands :func:`landing_error_k` above or below the planned temperature, and
    the settle cycles are the mean of the two (the two-point Gauss-Hermite rule for a
    normal timing error of that standard deviation), whole blocks, rounded up.  The
    criterion waits out an offset of either sign, so a hold that would land exactly
    is predicted to settle longer than that once its landing is uncertain."""
    def first_block(T_end: np.ndarray) -> np.ndarray:
        return _run_in(gas, runs, criteria, t0_s, _move(gas, move, position_m, runs.static_m, T_end))

    T_held = first_block(end_temperature_k)
    if timing_s <= 0:
        return T_held, _settle(period_map, T_held, m, gas.channels, criteria, runs, experiments, rate_hz, draws)
    miss = landing_error_k(gas, position_m, end_temperature_k, timing_s)
    high, low = (_settle(period_map, first_block(end_temperature_k + sign * miss), m, gas.channels, criteria, runs,
                         experiments, rate_hz, draws) for sign in (1.0, -1.0))
    cycles = m * np.ceil((high[0] + low[0]) / (2 * m))
    return T_held, (cycles.astype(int), high[1] & low[1], np.where(high[0] >= low[0], high[2], low[2]))


def time_constants_s(multiplier: np.ndarray, frequency_hz: np.ndarray) -> np.ndarray:
    """The relaxation's time constant [s] from its per-cycle Floquet multiplier."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((multiplier > 0) & (multiplier < 1), -1 / (frequency_hz * np.log(multiplier)), np.inf)


def _settle(period_map: _PeriodMap, T_start: np.ndarray, m: np.ndarray, channels: tuple[str, ...],
            criteria: SteadyStateCriteria, runs: _Runs, experiments: Sequence[ExperimentSpec],
            rate_hz: float, draws: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The criterion's settle cycles, whether it passes, and the limiting channel."""
    if criteria.criterion == "drift":
        return _apply_drift_criterion(period_map, T_start, m, channels, criteria, runs,
                                      [e.periods for e in experiments], rate_hz, draws)
    thresholds = np.array([criteria.thresholds.get(c, math.inf) for c in channels])
    return _apply_criterion(period_map, T_start, m, thresholds, criteria)


def _plan_holds(gas: GasThermalModel, runs: _Runs, period_map: _PeriodMap, criteria: SteadyStateCriteria,
                t0_s: float, prev_static: np.ndarray, T_rest: np.ndarray,
                conditioning: Conditioning, move: MoveProfile) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per experiment, the quickest hold that brings the gas to the experiment's periodic
    temperature at its first block: position [m], duration [s] (inf: none within
    ``conditioning``'s range and longest hold), the gas temperature on arrival and at
    the end [K].

    At each candidate position the temperature needed at the end of the hold is found by
    secant steps on the (nearly affine) map from there to the first block; the hold is
    the time the gas takes at rest to get from its temperature on arrival to that one,
    in the exponential relaxation a static gas spring's energy balance gives (the
    prediction is then integrated as the acquisition will run it)."""
    col = np.s_[:, None]
    lo, hi = conditioning.range_m
    position = np.broadcast_to(np.linspace(lo, hi, HOLD_CANDIDATES), (len(T_rest), HOLD_CANDIDATES))
    target, wanted = runs.static_m[col], period_map.fixed_point_k[col]
    T_arrive = _move(gas, move, prev_static[col], position, T_rest[col])

    def to_first_block(T_end: np.ndarray) -> np.ndarray:
        return _run_in(gas, runs, criteria, t0_s, _move(gas, move, position, target, T_end), col)

    a, fa = T_arrive, to_first_block(T_arrive)
    b = T_arrive - SECANT_STEP_K
    fb = to_first_block(b)
    for _ in range(SECANT_ITERATIONS):
        new = a + (wanted - fa) * (a - b) / (fa - fb)
        a, fa, b, fb = new, to_first_block(new), a, fa
    needed = a
    r_arrive = gas.temperature_rate(position, 0.0, 0.0, T_arrive)
    r_needed = gas.temperature_rate(position, 0.0, 0.0, needed)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = (r_arrive - r_needed) / (T_arrive - needed)          # the relaxation's rate [1/s], negative
        rest_k = T_arrive - r_arrive / k                          # where the gas would come to rest there
        hold = np.log((needed - rest_k) / (T_arrive - rest_k)) / k
    reachable = (k < 0) & np.isfinite(hold) & (hold >= conditioning.min_hold_s) & (hold <= conditioning.max_hold_s)
    moves_s = move.durations_s(position - prev_static[col]) + move.durations_s(target - position)
    total = np.where(reachable, moves_s + hold, np.inf)
    best = np.argmin(total, axis=1)
    rows = np.arange(len(T_rest))
    return (position[rows, best], np.where(np.isfinite(total[rows, best]), hold[rows, best], np.inf),
            T_arrive[rows, best], needed[rows, best])


class _PeriodMap:
    """Per experiment, as Chebyshev series in the start temperature of a cycle (the
    cycle starting at the first block's phase): the temperature one period later and
    the cycle means of the channels."""

    def __init__(self, gas: GasThermalModel, runs: _Runs, t0_s: float) -> None:
        n = len(runs.static_m)
        self.lo_k, self.hi_k = gas.ambient_k + GRID_SPAN_K[0], gas.ambient_k + GRID_SPAN_K[1]
        grid = chebyshev.chebpts1(CHEBYSHEV_DEGREE + 1)
        T0 = np.tile(self._from_unit(grid), (n, 1))                       # (E, G)
        period = 1.0 / runs.frequency_hz[:, None]
        col = np.s_[:, None]
        one = np.ones((n, 1))

        def rate(t, T):
            return gas.temperature_rate(*runs.stroke(t, one, 0.0 * one, col), T)

        # One period from the first block's phase, piece by piece between the kinks; the
        # cycle means by Simpson's rule on each piece's steps.
        steps = STEPS_PER_HALF_PERIOD
        simpson = np.ones(steps + 1)
        simpson[1:-1:2], simpson[2:-1:2] = 4, 2
        T, integral = T0, 0.0
        for a, b in _between_kinks(np.full((n, 1), t0_s), period, runs.frequency_hz[:, None]):
            nodes = _rk4(partial(_shifted, rate, a), T, b - a, steps, nodes=True)   # (steps+1, E, G)
            h = (b - a) / steps
            t = a + np.arange(steps + 1)[:, None, None] * h[None]
            t[0] += INSIDE * h                                           # the piece's side of a kink
            t[-1] -= INSIDE * h
            q, v, acc = runs.stroke(t, 1.0, 0.0, np.s_[None, :, None])
            y = gas.outputs(*np.broadcast_arrays(q, v, acc, nodes))     # (C, steps+1, E, G)
            integral = integral + np.tensordot(y, simpson, axes=([1], [0])) * (h / 3)
            T = nodes[-1]
        means = integral / period                                       # (C, E, G)
        self.end = chebyshev.chebfit(grid, T.T, CHEBYSHEV_DEGREE)        # (D+1, E)
        self.means = np.stack([chebyshev.chebfit(grid, mc.T, CHEBYSHEV_DEGREE) for mc in means], axis=-1)
        slope = chebyshev.chebder(self.end) * 2 / (self.hi_k - self.lo_k)
        # The map is a contraction with a nearly constant slope: a few Newton steps find T*.
        Ts = np.full(n, gas.ambient_k)
        for _ in range(8):
            x = self._to_unit(Ts)
            Ts = Ts - (chebyshev.chebval(x, self.end, tensor=False) - Ts) / (
                chebyshev.chebval(x, slope, tensor=False) - 1)
        self.fixed_point_k = Ts
        self.multiplier = chebyshev.chebval(self._to_unit(Ts), slope, tensor=False)

    def _to_unit(self, T: np.ndarray) -> np.ndarray:
        return (2 * T - (self.hi_k + self.lo_k)) / (self.hi_k - self.lo_k)

    def _from_unit(self, x: np.ndarray) -> np.ndarray:
        return 0.5 * (self.hi_k + self.lo_k) + 0.5 * (self.hi_k - self.lo_k) * x

    def step(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Temperature one period later and the channel means (E, C) of that cycle."""
        x = self._to_unit(T)
        return chebyshev.chebval(x, self.end, tensor=False), chebyshev.chebval(x[:, None], self.means, tensor=False)


def _after_previous(gas: GasThermalModel, runs: _Runs, period_map: _PeriodMap, criteria: SteadyStateCriteria,
                    t0_s: float, start_position_m: float, start_temperature_k: float,
                    pause_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each experiment's lead-in starts: the previous experiment's static position
    and the gas temperature after its fade-out and the pause at rest.

    The previous experiment ends its capture at the first block's phase (whole cycles
    later) in its periodic state and fades out over the ramp time.  Before the first
    experiment the damper rests at the start position and temperature."""
    n = len(runs.static_m)
    ramp = criteria.ramp_time_s
    prev = np.r_[-1, np.arange(n - 1)]
    first = prev < 0
    prev_static = np.where(first, start_position_m, runs.static_m[prev])
    T = np.where(first, start_temperature_k, period_map.fixed_point_k[prev])

    # Fade-out of the previous waveform (of zero duration before the first experiment,
    # for which prev = -1 only fills the row).
    prev_runs = _Runs(*(x[prev] for x in (runs.static_m, runs.amplitude_m, runs.frequency_hz, runs.waveform)))

    # The envelope's rate jumps at the ends of a ramp, so each ramp is a stretch of its
    # own: RK4 keeps its order only where the stroke velocity is smooth.
    def fade(t, T):
        return gas.temperature_rate(*prev_runs.stroke(t, 1 - (t - t0_s) / ramp, -1 / ramp), T)

    T = _rk4_waveform(fade, T, np.full(n, t0_s), np.where(first, 0.0, ramp), prev_runs.frequency_hz)
    return prev_static, _rest(gas, prev_static, T, pause_s, REST_STEPS)


def _rest(gas: GasThermalModel, position_m: np.ndarray, T: np.ndarray, duration_s: np.ndarray,
          steps: int) -> np.ndarray:
    """The gas temperature after ``duration_s`` at rest at a static position."""
    def rest(t, T):
        return gas.temperature_rate(position_m, 0.0, 0.0, T)

    return _rk4(rest, T, duration_s, steps)


def _move(gas: GasThermalModel, profile: MoveProfile, from_m: np.ndarray, to_m: np.ndarray,
          T: np.ndarray) -> np.ndarray:
    """The gas temperature after the controller's move (arrays broadcast)."""
    duration = profile.durations_s(to_m - from_m)

    def move(t, T):
        return gas.temperature_rate(*MoveProfile.during(from_m, to_m, duration, t), T)

    duration, T = np.broadcast_arrays(duration, T)
    return _rk4(move, T, duration, MOVE_STEPS)


def _run_in(gas: GasThermalModel, runs: _Runs, criteria: SteadyStateCriteria, t0_s: float, T: np.ndarray,
            col: Any = np.s_[:]) -> np.ndarray:
    """The gas temperature at the first block, from RUN at the static position: the
    amplitude ramp and the acquisition's wait (``col`` indexes the runs to T's shape)."""
    ramp = criteria.ramp_time_s
    shape = np.shape(T)
    f = np.broadcast_to(runs.frequency_hz[col], shape)

    def ramp_in(t, T):
        return gas.temperature_rate(*runs.stroke(t, t / ramp, 1 / ramp, col), T)

    T = _rk4_waveform(ramp_in, T, np.zeros(shape), np.full(shape, ramp), f)

    def until_first_block(t, T):
        return gas.temperature_rate(*runs.stroke(t, 1.0, 0.0, col), T)

    return _rk4_waveform(until_first_block, T, np.full(shape, ramp), np.full(shape, t0_s - ramp), f)


def _apply_drift_criterion(period_map: _PeriodMap, T_start: np.ndarray, m: np.ndarray, channels: tuple[str, ...],
                           criteria: SteadyStateCriteria, runs: _Runs, periods: list[int], rate_hz: float,
                           draws: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The acquisition's drift criterion (rig.planning.criterion) on the predicted block means:
    settle cycles, whether it passed, and the fitted channel with the largest drift.

    The criterion bounds what its data cannot exclude, so the transducers' noise (its
    own figures, averaged over a block) sets when it passes as much as the transient
    does: it is applied to ``draws`` noisy copies of the predicted means (fixed seed)
    and the median draw is the prediction (0 draws: the noise-free means alone)."""
    drift = criteria.drift
    assert drift is not None   # a drift criterion always has its settings (rig.config)
    tau = time_constants_s(period_map.multiplier, runs.frequency_hz)
    fitted = [channels.index(c) for c in drift.noise]
    sigma = np.array(list(drift.noise.values()))
    n = len(T_start)
    last = np.array([last_block_cycles(criteria, int(k)) for k in m])
    scale, draws = (1.0, draws) if draws > 0 else (0.0, 1)
    passed = np.tile(last[:, None], (1, draws))                     # cycle each draw passed (or gave up) at
    ok = np.zeros((n, draws), dtype=bool)
    open_ = np.ones((n, draws), dtype=bool)
    limiting = np.zeros(n, dtype=int)
    history: list[list[np.ndarray]] = [[] for _ in range(n)]        # (draws, channels) per block
    rng = np.random.default_rng(DRIFT_SEED)
    T = T_start.copy()
    block_sum = np.zeros((n, len(channels)))
    for cycle in range(1, int(last.max()) + 1):
        T, means = period_map.step(T)
        block_sum += means
        for i in np.flatnonzero(open_.any(axis=1) & (cycle % m == 0)):
            spp = rate_hz / runs.frequency_hz[i]
            noise = scale * sigma / math.sqrt(m[i] * spp) * rng.standard_normal((draws, len(sigma)))
            history[i] = (history[i] + [block_sum[i, fitted] / m[i] + noise])[-drift.fit_cycles:]
            block_sum[i] = 0.0
            for d in np.flatnonzero(open_[i]):
                if len(history[i]) >= MIN_BLOCKS:
                    fit = blocks_bias(drift, np.array([h[d] for h in history[i]]), int(m[i]),
                                      runs.frequency_hz[i], spp, periods[i], float(tau[i]))
                    if d == 0:
                        limiting[i] = fitted[int(np.argmax(np.abs(fit.drift) / sigma))]
                    if drift_passes(criteria, cycle, fit):
                        passed[i, d], ok[i, d], open_[i, d] = cycle, True, False
                        continue
                if cycle >= last[i]:
                    open_[i, d] = False
        if not open_.any():
            break
    median = np.argsort(passed, axis=1)[:, draws // 2]
    rows = np.arange(n)
    return passed[rows, median], ok[rows, median], limiting


def _apply_criterion(period_map: _PeriodMap, T_start: np.ndarray, m: np.ndarray, thresholds: np.ndarray,
                     criteria: SteadyStateCriteria) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The acquisition's block comparison on the predicted cycle means: settle cycles,
    whether the criterion passed, and the channel closest to its threshold at the last comparison."""
    n = len(T_start)
    last = np.array([last_block_cycles(criteria, int(k)) for k in m])
    cycles, settled = last.copy(), np.zeros(n, dtype=bool)
    open_ = np.ones(n, dtype=bool)
    T = T_start.copy()
    block_sum = np.zeros((n, len(thresholds)))
    previous = np.full((n, len(thresholds)), np.nan)
    worst = np.zeros((n, len(thresholds)))   # latest change / threshold per channel
    for cycle in range(1, int(last.max()) + 1):
        T, means = period_map.step(T)
        block_sum += means
        ends = open_ & (cycle % m == 0)
        if not ends.any():
            continue
        block = block_sum[ends] / m[ends, None]
        change = np.abs(block - previous[ends])                  # NaN at the first block: fails below
        passed = change_passes(criteria, cycle, change, thresholds)
        worst[ends] = np.divide(change, thresholds, out=np.full_like(change, np.inf),
                                where=(thresholds > 0) & ~np.isnan(change))
        idx = np.flatnonzero(ends)
        done = idx[passed | (cycle >= last[idx])]
        cycles[done], settled[idx[passed]] = cycle, True
        open_[done] = False
        previous[ends], block_sum[ends] = block, 0.0
        if not open_.any():
            break
    return cycles, settled, np.argmax(worst, axis=1)
