"""The order a plan's experiments run in: the one the damper model predicts quickest.

Most of a session is settling, and an experiment settles for as long as the gas takes
to get from where the one before left it to its own periodic temperature (a move up
the stroke compresses the gas and heats it, a move down cools it).  So the rig time of
an experiment depends on its predecessor; with the model's prediction of every
predecessor–successor pair (:mod:`rig.planning.settling`, through the plan's duration estimate,
which :meth:`rig.planning.plans.Plan.ordered` hands in), the order of least total rig time is a
shortest Hamiltonian path, exact by dynamic programming over subsets up to
``EXACT_UP_TO`` experiments, greedy beyond.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from identify.plans import ExperimentSpec

EXACT_UP_TO = 16    # 2^16 subsets × 16² steps: about a second
# The predicted rig time [s] of each experiment of a sequence run in that order from rest.
Durations = Callable[[Sequence[ExperimentSpec]], Sequence[float]]


# Told (predecessors done, of how many) as the costs are predicted: seconds of CPU for
# the standard plan, which the terminal must not spend in silence.
Progress = Callable[[int, int], object]


def transition_costs(experiments: Sequence[ExperimentSpec], durations: Durations,
                     progress: Progress | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted rig time [s] of each experiment first (from rest), and of j right after i."""
    n = len(experiments)
    first = np.array([durations((e,))[0] for e in experiments])
    after = np.full((n, n), np.inf)
    for i in range(n):
        # Every successor j of i as a two-experiment stretch of one sequence: j's lead-in
        # starts from i's periodic state; what i inherits from the pair before it is not read.
        js = [j for j in range(n) if j != i]
        sequence = tuple(replace(experiments[k], letter=f"{k}.{p}") for p, j in enumerate(js) for k in (i, j))
        after[i, js] = np.asarray(durations(sequence))[1::2]
        if progress is not None:
            progress(i + 1, n)
    return first, after


def quickest_order(first: np.ndarray, after: np.ndarray) -> list[int]:
    """The order of least total cost: ``first[k]`` to begin with k, ``after[i, j]`` for j after i."""
    n = len(first)
    if n <= 1:
        return list(range(n))
    if n > EXACT_UP_TO:
        order = [int(np.argmin(first))]
        while len(order) < n:
            left = [k for k in range(n) if k not in order]
            order.append(min(left, key=lambda k: after[order[-1], k]))
        return order
    full = 1 << n
    cost = np.full((full, n), np.inf)
    previous = np.full((full, n), -1, dtype=int)
    for k in range(n):
        cost[1 << k, k] = first[k]
    bits = 1 << np.arange(n)
    for mask in range(1, full):
        here = cost[mask]
        if not np.isfinite(here).any():
            continue
        step = here[:, None] + after                         # (last, next)
        step[:, (mask & bits) != 0] = np.inf                 # each experiment once
        best_last = np.argmin(step, axis=0)
        best = step[best_last, np.arange(n)]
        for k in map(int, np.flatnonzero(np.isfinite(best))):
            target = mask | (1 << k)
            if best[k] < cost[target, k]:
                cost[target, k], previous[target, k] = best[k], best_last[k]
    mask, last = full - 1, int(np.argmin(cost[full - 1]))
    order = []
    while last >= 0:
        order.append(last)
        mask, last = mask & ~(1 << last), int(previous[mask, last])
    return order[::-1]


def thermal_order(experiments: Sequence[ExperimentSpec], durations: Durations,
                  progress: Progress | None = None) -> tuple[ExperimentSpec, ...]:
    """The experiments in the order of least predicted rig time."""
    first, after = transition_costs(experiments, durations, progress)
    return tuple(experiments[k] for k in quickest_order(first, after))
