"""Declared models: generated derivatives agree with finite differences of the residuals."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from identify.model import ModelError, load_model


def _point(model, rng):
    n = 5
    if model.name == "duffing":
        X = rng.normal(0, 0.2, (1, n))
    else:
        X = np.vstack([rng.uniform(0.0, 0.25, n), rng.uniform(280, 330, n)])[: model.n_states]
    DX = rng.normal(0, 0.05, X.shape)
    DDX = rng.normal(0, 0.5, X.shape)
    U = rng.normal(3000 if model.name != "duffing" else 0.0, 500 if model.name != "duffing" else 0.1,
                   (len(model.input_names), n))
    th = model.nominal_vector()
    if model.name == "duffing":
        th = np.array([5e-6, 2e-4, 1.0, -0.02, 4.0])
    return X, DX, DDX, U, th


def _fd(f, args, which, k, h):
    plus = [a.copy() for a in args]
    minus = [a.copy() for a in args]
    plus[which].flat[k] += h
    minus[which].flat[k] -= h
    return (f(*plus) - f(*minus)) / (2 * h)


@pytest.mark.parametrize("name", ["1dof", "2dof", "duffing", "bouc-wen"])
def test_declared_derivatives_match_finite_differences(name):
    m = load_model(name)
    rng = np.random.default_rng(1)
    X, DX, DDX, U, th = _point(m, rng)
    args = [X, DX, DDX, U, th]
    for fun, jac, dth, din in ((m.residual, m.residual_jacobian, m.residual_dtheta, m.residual_dinput),
                               (m.output, m.output_jacobian, m.output_dtheta, m.output_dinput)):
        J = jac(*args)
        for w in range(3):  # states, first derivatives, second derivatives
            for j in range(m.n_states):
                h = 1e-7 * max(1.0, np.abs(args[w][j]).max())
                pert = [a.copy() for a in args]
                pert2 = [a.copy() for a in args]
                pert[w][j] += h
                pert2[w][j] -= h
                fd = (fun(*pert) - fun(*pert2)) / (2 * h)
                np.testing.assert_allclose(J[w][:, j], fd, rtol=2e-5, atol=1e-6 * np.abs(fd).max() + 1e-9)
        D = dth(*args)
        for k in range(len(th)):
            h = 1e-6 * max(abs(th[k]), 1e-3)
            np.testing.assert_allclose(D[:, k], _fd(fun, args, 4, k, h), rtol=2e-5,
                                       atol=1e-6 * np.abs(D[:, k]).max() + 1e-9)
        Du = din(*args)
        for j in range(U.shape[0]):
            h = 1e-6 * max(1.0, np.abs(U[j]).max())
            pert = [a.copy() for a in args]
            pert2 = [a.copy() for a in args]
            pert[3][j] += h
            pert2[3][j] -= h
            np.testing.assert_allclose(Du[:, j], (fun(*pert) - fun(*pert2)) / (2 * h), rtol=1e-6, atol=1e-9)


def test_user_model_loads_from_a_file(tmp_path):
    src = textwrap.dedent('''
        from identify.model import Channel, ModelDeclaration, ParameterSpec, State

        class Spring(ModelDeclaration):
            name = "spring_test"
            states = (State("x", "m", 1e-3),)
            inputs = {"f": Channel("force_N", "N")}
            outputs = {"stroke_mm": Channel("stroke_mm", "mm", scale=1e-3)}
            default_outputs = ("stroke_mm",)
            parameters = (ParameterSpec("m", "mass", "kg", 1.0), ParameterSpec("c", "damping", "N s/m", 2.0),
                          ParameterSpec("k", "stiffness", "N/m", 100.0))

            def residuals(self, s):
                return [s.m * s.x_tt + s.c * s.x_t + s.k * s.x - s.f]

            def output_equations(self, s):
                return {"stroke_mm": s.x}
    ''')
    path = tmp_path / "spring.py"
    path.write_text(src)
    m = load_model(f"{path}:Spring")
    assert m.name == "spring_test" and m.orders == (2,)
    X = np.array([[0.01]])
    g = m.residual(X, np.zeros_like(X), np.zeros_like(X), np.array([[1.0]]), m.nominal_vector())
    assert g[0, 0] == pytest.approx(100.0 * 0.01 - 1.0)


def test_kinks_and_jumps_compile_to_their_generalised_derivatives(tmp_path):
    """sign, max and Heaviside in a residual: the Jacobian takes the derivative of a jump
    as zero (semismooth Newton) instead of a DiracDelta numpy cannot evaluate, and the
    model is flagged as non-smooth (a finer model grid by default on spectral grids)."""
    src = textwrap.dedent('''
        import sympy as sp
        from identify.model import Channel, ModelDeclaration, ParameterSpec, State

        class Stop(ModelDeclaration):
            name = "stop_test"
            states = (State("x", "m", 1e-3),)
            inputs = {"f": Channel("force_N", "N")}
            outputs = {"stroke_mm": Channel("stroke_mm", "mm", scale=1e-3)}
            default_outputs = ("stroke_mm",)
            parameters = (ParameterSpec("k", "stiffness", "N/m", 100.0), ParameterSpec("F", "friction", "N", 2.0),
                          ParameterSpec("g", "gap", "m", 0.01))

            def residuals(self, s):
                contact = sp.Max(s.x - s.g, 0) * sp.Heaviside(s.x)
                return [s.x_t + s.F * sp.sign(s.x_t) * s.x**2 + s.k * (s.x + 10 * contact) - s.f]

            def output_equations(self, s):
                return {"stroke_mm": s.x}
    ''')
    path = tmp_path / "stop.py"
    path.write_text(src)
    m = load_model(f"{path}:Stop")
    assert m.nonsmooth and not load_model("duffing").nonsmooth
    X, DX = np.array([[0.005, 0.02]]), np.array([[-0.1, 0.3]])
    gx, gdx, _ = m.residual_jacobian(X, DX, np.zeros_like(X), np.array([[1.0, 1.0]]), m.nominal_vector())
    np.testing.assert_allclose(gx[0, 0], [2 * 2.0 * 0.005 * -1 + 100, 2 * 2.0 * 0.02 + 100 * 11])
    np.testing.assert_allclose(gdx[0, 0], [1.0, 1.0])  # d sign(x')/dx' = 0 away from the jump


def test_unknown_model_is_a_clear_error(tmp_path):
    with pytest.raises(ModelError, match="unknown model"):
        load_model("3dof")
    with pytest.raises(ModelError, match="not found"):
        load_model(f"{tmp_path}/nope.py:X")
