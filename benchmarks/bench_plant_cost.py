"""What the plant truth costs and how close its one grid comes to LSODA.

For each experiment of the standard set (faded in from rest at its static position, then
one cycle): the gas's ∮p dV over that cycle and the transducer's peak pressure on the
states' grid (``simulator.plant.integrator.STEP_S``, the step offline and served share)
against scipy's LSODA at rtol 1e-8; then the CPU per rig second of the plant offline
(``simulator generate --physics plant``'s path), served (the engine's 10 kHz steps in
0.1 s blocks) and, beside it, the model tier's served 2-dof damper.

    python benchmarks/bench_plant_cost.py [--experiments a,b,j]
"""

from __future__ import annotations

import argparse
import time

import _setup  # noqa: F401  first: one BLAS thread, set before numpy loads; the repository importable

# isort: split
import numpy as np
from scipy.integrate import solve_ivp

from identify.plans import STANDARD_SET, select
from simulator.physics import Actuator, StreamingPlant
from simulator.plant import load_plant
from simulator.plant.integrator import STEP_S, integrate_stroke
from simulator.plant.sequence import Segment
from simulator.plant.streaming import StreamingPlantTruth
from simulator.truth import load_truth

ENGINE_DT_S = 1e-4
BLOCK_STEPS = 1000


def loop_figures(plant, spec) -> tuple[float, float, float, float, float, float]:
    """(∮p dV, peak) on the grid, the same from LSODA, and the CPU seconds of each."""
    static, period = spec.static_position_mm * 1e-3, spec.period_s
    seg = Segment(spec, Actuator(), static, 1.0, period, 1e9)
    y0 = plant.rest_state(static)
    c0 = time.process_time()
    grid, states = integrate_stroke(plant, seg.stroke, 0.0, 2 * period, y0)
    cpu_grid = time.process_time() - c0

    def rhs(t, y):
        q, v, _ = seg.stroke(np.array([t]))
        return plant.rates(q, v, y[:, None])[:, 0]

    c0 = time.process_time()
    sol = solve_ivp(rhs, (0.0, grid[-1]), y0, method="LSODA", rtol=1e-8, atol=1e-10 * np.abs(y0) + 1e-14,
                    dense_output=True)
    cpu_lsoda = time.process_time() - c0
    last = grid >= grid[-1] - period - 1e-9
    q, v, _ = seg.stroke(grid[last])

    def loop(Y):
        f = plant.forces(q, v, Y)
        return float(-np.trapezoid(f.p_gas, f.gas_volume)), float(np.max(f.p_dead))

    return (*loop(states[:, last]), *loop(sol.sol(grid[last])), cpu_grid, cpu_lsoda)


def served_cpu_per_rig_s(make, spec, rig_s: float) -> float:
    static = spec.static_position_mm * 1e-3
    stream = make(static)
    n = int(round(rig_s / ENGINE_DT_S))
    t = ENGINE_DT_S * np.arange(1, n + 1)
    setpoint = static + spec.amplitude_mm * 1e-3 * np.clip(t / spec.period_s, 0, 1) * np.sin(
        2 * np.pi * spec.frequency_hz * t)
    c0 = time.process_time()
    for start in range(0, n, BLOCK_STEPS):
        block = setpoint[start:start + BLOCK_STEPS]
        out = stream.advance(block)
        stream.commit(len(block), *([out[3]] if isinstance(stream, StreamingPlantTruth) else []))
    return (time.process_time() - c0) / rig_s


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--experiments", help="comma-separated letters (default: all fourteen)")
    args = parser.parse_args()
    plan = select(STANDARD_SET, args.experiments.split(",") if args.experiments else None)
    plant, model, actuator = load_plant(), load_truth(), Actuator()
    print(f"the plant's grid (step {STEP_S * 1e3:g} ms) against LSODA at rtol 1e-8, one cycle after the fade-in")
    print(f"{'exp':>3} {'∮p dV grid J':>13} {'LSODA J':>10} {'Δ %':>7} {'peak grid bar':>14} {'LSODA bar':>10} "
          f"{'Δ %':>7} {'CPU grid s':>10} {'CPU LSODA s':>11}")
    worst = [0.0, 0.0]
    for spec in plan:
        w, p, w_ref, p_ref, c_grid, c_ref = loop_figures(plant, spec)
        dw, dp = 100 * (w / w_ref - 1), 100 * (p / p_ref - 1)
        worst = [max(worst[0], abs(dw)), max(worst[1], abs(dp))]
        print(f"{spec.letter:>3} {w:13.4g} {w_ref:10.4g} {dw:7.3f} {p / 1e5:14.4f} {p_ref / 1e5:10.4f} {dp:7.3f} "
              f"{c_grid:10.2f} {c_ref:11.2f}")
    print(f"worst: ∮p dV {worst[0]:.3f} %, peak pressure {worst[1]:.3f} % (target: within 1 %)")
    print()
    print("CPU seconds per rig second (served: 10 kHz engine steps in 0.1 s blocks)")
    print(f"{'exp':>3} {'plant offline':>14} {'plant served':>13} {'model served':>13}")
    for spec in plan:
        rig_s = max(2 * spec.period_s, 4.0)
        seg = Segment(spec, actuator, spec.static_position_mm * 1e-3, 1.0, spec.period_s, 1e9)
        c0 = time.process_time()
        integrate_stroke(plant, seg.stroke, 0.0, rig_s, plant.rest_state(spec.static_position_mm * 1e-3))
        offline = (time.process_time() - c0) / rig_s
        served = served_cpu_per_rig_s(lambda x: StreamingPlantTruth(plant, actuator, ENGINE_DT_S, x), spec, rig_s)
        modelled = served_cpu_per_rig_s(lambda x: StreamingPlant(model, actuator, ENGINE_DT_S, x), spec, rig_s)
        print(f"{spec.letter:>3} {offline:14.3f} {served:13.3f} {modelled:13.4f}")


if __name__ == "__main__":
    main()
