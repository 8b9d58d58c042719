"""``simulator generate`` of the standard set (14 experiments, 3 periods, 2 kHz).

Target (issue 2): under 30 s.  Baseline: the same steady states by brute-force time
integration from rest (solve_ivp, 120 s of settling per experiment), timed on two
experiments and scaled to fourteen.

    python benchmarks/bench_generate.py
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np
from scipy.integrate import solve_ivp

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from identify.plans import STANDARD_SET, select  # noqa: E402
from simulator.generate import generate  # noqa: E402
from simulator.physics import Actuator, steady_stroke  # noqa: E402
from simulator.truth import load_truth  # noqa: E402


def brute_force(letter: str, settle_s: float = 120.0) -> float:
    damper, actuator = load_truth(), Actuator()
    spec = select(STANDARD_SET, [letter])[0]

    def rhs(t, T):
        q, v, _ = steady_stroke(spec, actuator, np.atleast_1d(t))
        return damper.temperature_rate(q, v, T)

    t0 = time.perf_counter()
    t_eval = settle_s + np.arange(int(3 * 2000 / spec.frequency_hz)) / 2000
    solve_ivp(rhs, (0, t_eval[-1]), [damper.ambient_k], method="DOP853", rtol=1e-9, atol=1e-9, t_eval=t_eval)
    return time.perf_counter() - t0


def main() -> int:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        generate(out, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=1)
        ours = time.perf_counter() - t0
    sample = [brute_force("a"), brute_force("j")]
    baseline = np.mean(sample) * 14
    print("generate: standard set, 14 experiments x 3 periods at 2 kHz")
    print(f"  simulator generate (periodic shooting):      {ours:6.1f} s   "
          f"(target < 30 s: {'met' if ours < 30 else 'NOT met'})")
    print(f"  baseline: time integration from rest, 120 s: {baseline:6.1f} s   (2 experiments timed, x 7)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
