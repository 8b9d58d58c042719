"""The matrix-free spectral solver and the oversampled model grid: the same numbers as
the dense LU, exact transposes, and GMRES that says when it fails."""

from __future__ import annotations

import numpy as np
import pytest

from identify import spectral
from identify.differentiation import Grid
from identify.model import load_model
from identify.periodic import PeriodicSolver
from identify.spectral import KrylovError, gmres

F_HZ = 0.5


def _damper_solution(linear_solver: str, n: int = 128, oversample: int = 1):
    m = load_model("2dof")
    th = m.nominal_vector()
    grid = Grid(n, "spectral", linear_solver, oversample)
    solver = PeriodicSolver(m, grid)
    u = (4500 + 800 * np.sin(2 * np.pi * grid.tau))[None]
    return m, th, solver, solver.solve(u, F_HZ, th)


def test_krylov_gives_the_dense_solution_and_sensitivities(monkeypatch):
    monkeypatch.setattr(spectral, "RTOL", 1e-10)  # the fit's 1e-6 is all it needs; here: the same numbers
    m, th, dense, sol_d = _damper_solution("dense")
    _, _, krylov, sol_k = _damper_solution("krylov")
    assert sol_k.factorization.krylov is not None and sol_d.factorization.krylov is None
    np.testing.assert_allclose(sol_k.states, sol_d.states, rtol=1e-9)
    S_d = dense.output_sensitivities(sol_d, th, [3, 5, 15], [0, 1])
    S_k = krylov.output_sensitivities(sol_k, th, [3, 5, 15], [0, 1])
    np.testing.assert_allclose(S_k, S_d, rtol=1e-6, atol=1e-7 * np.abs(S_d).max())
    w = np.random.default_rng(1).standard_normal((2, 128, 3))
    adjoint = dense.input_adjoint(sol_d, th, [0, 1], w)
    np.testing.assert_allclose(krylov.input_adjoint(sol_k, th, [0, 1], w), adjoint, atol=1e-5 * np.abs(adjoint).max())


@pytest.mark.parametrize(("n", "oversample"), [(48, 3), (47, 2)])
def test_refining_and_sampling_are_exact_transposes_and_sampling_undoes_refining(n, oversample):
    grid = Grid(n, "spectral", oversample=oversample)
    rng = np.random.default_rng(0)
    x, w = rng.standard_normal((2, n)), rng.standard_normal((2, n * oversample))
    assert np.sum(w * grid.refine(x)) == pytest.approx(np.sum(grid.refine_transposed(w) * x), abs=1e-12)
    assert np.sum(w * grid.sample_transposed(x)) == pytest.approx(np.sum(grid.sample(w) * x), abs=1e-12)
    np.testing.assert_allclose(grid.sample(grid.refine(x)), x, atol=1e-13)


def test_oversampled_input_adjoint_is_the_transpose_of_the_input_response(monkeypatch):
    monkeypatch.setattr(spectral, "RTOL", 1e-10)
    m, th, solver, sol = _damper_solution("krylov", n=48, oversample=3)
    assert sol.states.shape == (2, 144) and solver.outputs(sol, th, [0, 1]).shape == (2, 48)
    rng = np.random.default_rng(3)
    du, w = rng.standard_normal((1, 48, 2)), rng.standard_normal((2, 48, 2))
    forward = np.einsum("onk,onk->k", w, solver.input_response(sol, th, [0, 1], du))
    backward = np.einsum("jnk,jnk->k", solver.input_adjoint(sol, th, [0, 1], w), du)
    np.testing.assert_allclose(forward, backward, rtol=1e-7)


def test_gmres_reaches_its_tolerance_or_says_it_did_not():
    rng = np.random.default_rng(2)
    A = np.eye(300) + 0.6 * rng.standard_normal((300, 300)) / np.sqrt(300)
    b = rng.standard_normal(300)
    x, iterations = gmres(lambda v: A @ v, b, 1e-10, restart=20)
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b) * 1.01
    assert 20 < iterations < 300  # restarted at least once, far from a direct solve
    with pytest.raises(KrylovError, match="did not converge"):
        gmres(lambda v: A @ v, b, 1e-10, restart=5, max_iterations=10)
