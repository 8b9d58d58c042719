"""Periodic solver: agreement with long transient simulation, O(h²) convergence,
sensitivities, convergence from the static guess on the standard set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from identify.differentiation import Grid
from identify.model import load_model
from identify.periodic import PeriodicSolver
from identify.transient import TransientSimulator

F_HZ = 0.5
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def force(t):
    return 4500.0 + 2500.0 * np.sin(2 * np.pi * F_HZ * np.asarray(t))


def _sine_case(model_name: str, points: int):
    """A model at its nominal parameters under the sine force, solved on a bdf2 grid."""
    m = load_model(model_name)
    th = m.nominal_vector()
    grid = Grid(points)
    solver = PeriodicSolver(m, grid)
    u = force(grid.tau / F_HZ)[None]
    return m, th, grid, solver, u, solver.solve(u, F_HZ, th)


@pytest.fixture(scope="module")
def transient_reference():
    """1-dof response to a sine force, integrated for 20 periods with tight tolerances
    (friction and inertia settle within a few periods); the last period on a fine grid.
    The 2-dof model's slow thermal mode needs minutes of simulated time to settle."""
    m = load_model("1dof")
    th = m.nominal_vector()
    solver = PeriodicSolver(m, Grid(64))
    xs = solver.static_equilibrium(np.array([force(0.0)]), th)
    periods = 20
    tau = np.arange(3200) / 3200
    t = np.concatenate([[0.0], (periods - 2 + tau) / F_HZ, (periods - 1 + tau) / F_HZ])
    traj = TransientSimulator(m, th).run(xs, np.zeros(1), lambda tt: force(tt)[None], t, rtol=1e-11)
    prev, last = traj.states[:, 1:3201], traj.states[:, 3201:]
    assert np.max(np.abs(last - prev)) < 1e-8  # settled: the last two periods agree
    return tau, last


def test_bdf2_periodic_solution_matches_transient_and_converges_second_order(transient_reference):
    tau_ref, states_ref = transient_reference
    m = load_model("1dof")
    th = m.nominal_vector()
    errors = []
    for n in (200, 400, 800, 1600):
        grid = Grid(n)
        sol = PeriodicSolver(m, grid).solve(force(grid.tau / F_HZ)[None], F_HZ, th)
        ref = states_ref[0, :: 3200 // n]
        errors.append(np.max(np.abs(sol.states[0] - ref)))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert errors[-1] < 2e-5, errors  # m: 1600 points agree with the transient to 20 µm
    assert np.all(ratios[1:] > 3.0) and np.all(ratios[1:] < 5.0), (errors, ratios)


@pytest.mark.parametrize("scheme", ["bdf2", "spectral"])
def test_sensitivities_match_finite_differences(scheme):
    m = load_model("2dof")
    th = m.nominal_vector()
    grid = Grid(256, scheme)
    solver = PeriodicSolver(m, grid)
    u = force(grid.tau / F_HZ)[None] if scheme == "bdf2" else (4500 + 800 * np.sin(2 * np.pi * grid.tau))[None]
    sol = solver.solve(u, F_HZ, th)
    idx = [3, 5, 15]
    S = solver.output_sensitivities(sol, th, idx, [0, 1])
    for col, k in enumerate(idx):
        h = abs(th[k]) * 1e-6
        tp, tm = th.copy(), th.copy()
        tp[k] += h
        tm[k] -= h
        yp = solver.outputs(solver.solve(u, F_HZ, tp, start=sol.states), tp, [0, 1])
        ym = solver.outputs(solver.solve(u, F_HZ, tm, start=sol.states), tm, [0, 1])
        fd = (yp - ym) / (2 * h)
        # The central difference carries the Newton tolerance divided by h: about 2e-6 of the
        # largest sensitivity on this grid (scipy 1.17), which the absolute tolerance allows.
        np.testing.assert_allclose(S[:, :, col], fd, rtol=1e-4, atol=5e-6 * np.abs(fd).max())


def test_input_sensitivities_match_finite_differences():
    m, th, grid, solver, u, sol = _sine_case("1dof", 64)
    unit = np.zeros((1, 64, 3))
    unit[0, [0, 17, 40], [0, 1, 2]] = 1.0
    H = solver.input_response(sol, th, [0], unit)
    for col, nu in enumerate((0, 17, 40)):
        up, um = u.copy(), u.copy()
        up[0, nu] += 1e-3
        um[0, nu] -= 1e-3
        fd = (solver.outputs(solver.solve(up, F_HZ, th, start=sol.states), th, [0])
              - solver.outputs(solver.solve(um, F_HZ, th, start=sol.states), th, [0])) / 2e-3
        np.testing.assert_allclose(H[0, :, col], fd[0], rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("scheme", ["bdf2", "spectral"])
def test_input_adjoint_is_the_transpose_of_the_input_response(scheme):
    m = load_model("2dof")
    th = m.nominal_vector()
    grid = Grid(48, scheme)
    solver = PeriodicSolver(m, grid)
    u = (4500 + 800 * np.sin(2 * np.pi * grid.tau))[None]
    sol = solver.solve(u, F_HZ, th)
    rng = np.random.default_rng(3)
    du, w = rng.standard_normal((1, 48, 2)), rng.standard_normal((2, 48, 2))
    forward = np.einsum("onk,onk->k", w, solver.input_response(sol, th, [0, 1], du))
    backward = np.einsum("jnk,jnk->k", solver.input_adjoint(sol, th, [0, 1], w), du)
    np.testing.assert_allclose(forward, backward, rtol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("model_name", ["1dof", "2dof"])
def test_every_standard_experiment_converges_from_the_static_guess(standard_dataset, model_name):
    from identify.dataset import read_dataset
    from identify.preparation import prepare_periodic

    m = load_model(model_name)
    ds = read_dataset(standard_dataset)
    data = prepare_periodic(m, ds.select(kind="periodic"), 800, ["stroke_mm"])
    assert len(data) == 14
    solver = PeriodicSolver(m, Grid(800))
    for d in data:
        sol = solver.solve(d.inputs, d.frequency_hz, m.nominal_vector(), label=d.label)
        assert sol.residual_norm < 1e-8, d.label


def test_a_start_a_small_step_from_the_solution_costs_one_factorisation():
    """One full Newton step from close by leaves an error of about its square, which a
    chord step on the same factorisation confirms: one factorisation, not two, and the
    sensitivities from that one-step-old Jacobian agree to about its age."""
    m, th, grid, solver, u, sol = _sine_case("2dof", 256)
    scales = m.state_scales[:, None]
    near = sol.states + 100 * solver.tolerance * scales * np.sin(2 * np.pi * grid.tau)  # 100 tolerances off
    again = solver.solve(u, F_HZ, th, start=near)
    assert again.iterations == 1
    np.testing.assert_allclose(again.states / scales, sol.states / scales, rtol=0, atol=solver.tolerance)
    index = [m.parameter_index(k) for k in ("theta4", "theta6", "theta16")]
    np.testing.assert_allclose(solver.state_sensitivities(again, th, index), solver.state_sensitivities(sol, th, index),
                               rtol=1e-5, atol=0)


@pytest.mark.slow
def test_the_measured_start_reaches_the_static_starts_solution_in_fewer_iterations(standard_dataset):
    """Stroke and pressure determine q and T, so a 2-dof fit's cold solves start from the
    measurements, to the same periodic solution, in far fewer Newton iterations (the
    steep friction makes the static start's long damped phase).  Where the parameters
    cannot reach the measured stroke, or a fit of the stroke alone cannot map back to T,
    the static start takes over, saying why."""
    from identify.dataset import read_dataset
    from identify.parameters import Parameters
    from identify.preparation import prepare_periodic
    from identify.start import Measured, StartError, measured_start

    m = load_model("2dof")
    outputs = ["stroke_mm", "pressure_bar"]
    data = prepare_periodic(m, read_dataset(standard_dataset).select(kind="periodic"), 800, outputs)
    grid = Grid(800)
    index = [m.output_index(o) for o in outputs]
    scales = m.state_scales[:, None]

    def both_starts(th: np.ndarray) -> tuple[list[str], dict[str, int]]:
        starts, iterations = [], {"auto": 0, "static": 0}
        for d in data:
            auto = PeriodicSolver(m, grid).solve(d.inputs, d.frequency_hz, th, label=d.label,
                                                 measured=Measured(index, d.measured))
            static = PeriodicSolver(m, grid).solve(d.inputs, d.frequency_hz, th, label=d.label)
            assert static.start == "static"
            np.testing.assert_allclose(auto.states / scales, static.states / scales, rtol=0, atol=1e-6)
            starts.append(auto.start)
            iterations["auto"] += auto.iterations
            iterations["static"] += static.iterations
        return starts, iterations

    # The benchmarks' start, 15-40 % off the truth.
    starts, iterations = both_starts(Parameters.from_file(m, str(EXAMPLES / "start-2dof.json")).vector())
    assert set(starts) == {"measured"}
    assert iterations["auto"] < 0.6 * iterations["static"], iterations

    # A gas spring that collapses (1 + θ6·q -> 0) before the measured high strokes.
    th = m.nominal_vector()
    th[m.parameter_index("theta6")] *= 1.3
    starts, _ = both_starts(th)
    assert "static" in starts and "measured" in starts, starts

    d = data[0]
    with pytest.raises(StartError, match="do not determine every state"):
        measured_start(m, grid, d.inputs, th, Measured(index[:1], d.measured[:1]))
    solver = PeriodicSolver(m, grid)
    sol = solver.solve(d.inputs, d.frequency_hz, th, label=d.label, measured=Measured(index[:1], d.measured[:1]))
    assert sol.start == "static" and solver.starts_used == {d.label: "static"}


def test_floquet_multipliers_of_a_linear_oscillator_are_exp_lambda_T():
    m = load_model("duffing")
    names = [p.name for p in m.declaration.parameters]
    th = m.nominal_vector()
    th[names.index("k2")] = th[names.index("k3")] = 0.0
    mass, damping, stiffness = (th[names.index(k)] for k in ("m", "d", "k"))
    f = 20.0
    grid = Grid(800)
    solver = PeriodicSolver(m, grid)
    sol = solver.solve(np.sin(2 * np.pi * grid.tau)[None], f, th)
    mu = solver.floquet_multipliers(sol, th)
    lam = np.roots([mass, damping, stiffness])
    expected = np.exp(lam / f)
    assert len(mu) == 2
    np.testing.assert_allclose(np.sort(np.abs(mu)), np.sort(np.abs(expected)), rtol=2e-3)
    # an unstable orbit is seen as one: negative damping
    th[names.index("d")] = -damping
    sol = solver.solve(np.sin(2 * np.pi * grid.tau)[None], f, th)
    assert np.abs(solver.floquet_multipliers(sol, th)[0]) > 1.0
