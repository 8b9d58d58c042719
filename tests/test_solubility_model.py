"""The dissolving-gas damper of identify/models/solubility_damper.py: declared as a user
declares a model, it fits data it did not generate itself (tests/solubility_data.py) and
is the 2-dof model when the gas dissolves instantly."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from identify.differentiation import Grid
from identify.model import load_model
from identify.periodic import PeriodicSolver
from identify.plans import STANDARD_SET, select
from identify.transient import drop_test
from tests.solubility_data import generate_dataset

SPEC = "identify/models/solubility_damper.py:DamperSolubility"


def _models():
    return load_model("2dof"), load_model(SPEC)


def test_instant_dissolution_is_the_2dof_model_periodic_and_transient():
    m2, m3 = _models()
    th2 = m2.nominal_vector()
    th3 = np.append(th2, 1e-6)  # θ18 → 0: the dissolved gas at equilibrium at every instant
    n, f = 400, 0.5
    t = np.arange(n) / n / f
    u = (3200 + 800 * np.sin(2 * np.pi * f * t))[None]
    s2 = PeriodicSolver(m2, Grid(n, "bdf2")).solve(u, f, th2)
    s3 = PeriodicSolver(m3, Grid(n, "bdf2")).solve(u, f, th3)
    y2 = m2.output(s2.states, s2.dstates, s2.ddstates, u, th2)
    y3 = m3.output(s3.states, s3.dstates, s3.ddstates, u, th3)
    for name in ("stroke_mm", "pressure_bar"):
        a, b = y2[m2.output_index(name)], y3[m3.output_index(name)]
        assert np.max(np.abs(a - b)) < 1e-5 * np.ptp(a), name
    tt = np.linspace(0.0, 1.0, 201)
    d2 = drop_test(m2, th2, 350.0, 0.5, tt)
    d3 = drop_test(m3, th3, 350.0, 0.5, tt)
    f2, f3 = d2.outputs[m2.output_index("force_N")], d3.outputs[m3.output_index("force_N")]
    assert np.max(np.abs(f2 - f3)) < 1e-4 * np.ptp(f2)
    # ... and a slow dissolution leaves more gas in the spring during a landing: stiffer, less stroke.
    d_slow = drop_test(m3, np.append(th2, 10.0), 350.0, 0.5, tt)
    assert d_slow.states[0].max() < d2.states[0].max() - 1e-3


def test_fits_data_of_its_own_structure_made_by_an_independent_generator(tmp_path):
    data = generate_dataset(tmp_path / "data", select(STANDARD_SET, ["a", "b", "h", "j"]),
                            theta={"theta18": 5.0, "theta16": 0.7}, seed=3)
    start = tmp_path / "START.json"
    # θ18's step scale is set as docs/user-models.md advises: with the default (half of
    # 10 s) the first Gauss-Newton step sends it to its bound 0, a local minimum 5 mm off.
    start.write_text(json.dumps({"model": "2dof-solubility",
                                 "parameters": {"theta4": 5.6e-3, "theta6": -3.3, "theta16": 0.85,
                                                "theta18": {"value": 10.0, "prior_std": 2.0}}}))
    out = tmp_path / "RESULT.json"
    proc = subprocess.run([sys.executable, "-m", "identify", "fit", str(data), "--model", SPEC, "--params",
                           str(start), "--estimate", "theta4,theta6,theta16,theta18", "--output", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    params = json.loads(out.read_text())["parameters"]
    # The tolerances of the 2-dof recovery test (tests/test_fit.py): the bdf2 grid's own
    # discretisation error, not the noise, sets them; θ18 is held to its slower family.
    truth = {"theta4": (5.0e-3, 1e-3), "theta6": (-3.0, 1e-3), "theta16": (0.7, 1e-2), "theta18": (5.0, 2e-2)}
    for name, (value, tolerance) in truth.items():
        est, std = params[name]["value"], params[name]["std"]
        assert abs(est / value - 1) < tolerance, (name, est, std, value)
        assert std < 0.05 * abs(value), (name, std)


@pytest.mark.parametrize(("name", "factor"), [("theta18", 0.01), ("theta7", 3.0)])
def test_the_dissolution_parameters_move_the_drop_test(name, factor):
    _, m3 = _models()
    th = m3.nominal_vector()
    tt = np.linspace(0.0, 0.6, 121)
    base = drop_test(m3, th, 350.0, 0.5, tt).states[0].max()
    th[m3.parameter_index(name)] *= factor
    assert abs(drop_test(m3, th, 350.0, 0.5, tt).states[0].max() - base) > 1e-3
