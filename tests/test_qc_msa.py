"""Measurement-system studies (rig.qc.msa): the type 3 ANOVA of statsmodels against the
one-way ANOVA computed by hand with numpy (the independent computation), to the digits
the study prints; the type 1 figures against their formulae; tables a study refuses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.qc import msa
from rig.qc.msa_run import type3_line
from rig.qc.spec import load_spec


def _table(units: int, repeats: int, seed: int, part_sd: float, noise_sd: float) -> list[msa.Row]:
    rng = np.random.default_rng(seed)
    true = 450.0 + part_sd * rng.standard_normal(units)
    return [msa.Row(f"SN-{u:04d}", r + 1, "damping_force_0.3_N", float(true[u] + noise_sd * rng.standard_normal()))
            for r in range(repeats) for u in range(units)]


def _by_hand(rows: list[msa.Row], tolerance: float) -> msa.Type3:
    """The one-way random-effects ANOVA from its definitions (no statsmodels, no pandas)."""
    units = sorted({r.unit for r in rows})
    y = np.array([[r.value for r in rows if r.unit == u] for u in units])   # units × repeats
    p, n = y.shape
    grand = y.mean()
    ss_unit = n * float(((y.mean(axis=1) - grand) ** 2).sum())
    ss_error = float(((y - y.mean(axis=1, keepdims=True)) ** 2).sum())
    ms_unit, ms_error = ss_unit / (p - 1), ss_error / (p * (n - 1))
    anova = (msa.AnovaRow("unit", p - 1, ss_unit, ms_unit, ms_unit / ms_error, None),
             msa.AnovaRow("repeatability", p * (n - 1), ss_error, ms_error, None, None))
    return msa.components("damping_force_0.3_N", p, n, tolerance, ms_unit, ms_error, anova)


@pytest.mark.parametrize("units, repeats, part_sd, noise_sd", [(10, 2, 8.0, 0.5), (12, 3, 2.0, 1.5), (10, 2, 0.1, 1.0)])
def test_the_type3_anova_agrees_with_the_hand_computation_to_the_printed_digits(units, repeats, part_sd, noise_sd):
    spec = load_spec("default")
    rows = _table(units, repeats, units * 7 + repeats, part_sd, noise_sd)
    (lib,) = msa.type3(rows, {"damping_force_0.3_N": 90.0})
    hand = _by_hand(rows, 90.0)
    assert type3_line(spec, lib) == type3_line(spec, hand)
    for a, b in zip(lib.anova, hand.anova, strict=True):
        assert (a.source, a.df, f"{a.ss:.4g}", f"{a.ms:.4g}") == (b.source, b.df, f"{b.ss:.4g}", f"{b.ms:.4g}")
    assert f"{lib.anova[0].f:.2f}" == f"{hand.anova[0].f:.2f}"
    # and the AIAG definitions hold between the figures
    assert lib.tv == pytest.approx(math.hypot(lib.ev, lib.pv))
    assert lib.ndc == pytest.approx(1.41 * lib.pv / lib.ev)


def test_a_unit_scatter_far_above_the_repeatability_is_an_acceptable_system_and_the_reverse_is_not():
    (good,) = msa.type3(_table(10, 2, 1, part_sd=8.0, noise_sd=0.2), {"damping_force_0.3_N": 90.0})
    (poor,) = msa.type3(_table(10, 2, 1, part_sd=0.5, noise_sd=3.0), {"damping_force_0.3_N": 90.0})
    assert good.acceptable and good.ndc >= 5 and good.grr_tolerance_percent <= 10
    assert not poor.acceptable and poor.ndc < 5


def test_type1_figures_follow_their_formulae():
    rng = np.random.default_rng(5)
    x = 6.01 + 0.004 * rng.standard_normal(25)
    rows = [msa.Row("MU-0001", i, "gas_precharge_bar", float(v)) for i, v in enumerate(x, 1)]
    (r,) = msa.type1(rows, {"gas_precharge_bar": 6.0}, {"gas_precharge_bar": 0.6})
    s = x.std(ddof=1)
    assert r.cg == pytest.approx(0.2 * 0.6 / (6 * s)) and r.cgk == pytest.approx((0.06 - abs(x.mean() - 6.0)) / (3 * s))
    assert r.t == pytest.approx((x.mean() - 6.0) / (s / math.sqrt(25)))
    assert r.bias_significant and r.bias_ci[0] > 0     # 0.01 bar off, s/√n = 0.0008: the bias is seen
    assert r.capable is (r.cg >= 1.33 and r.cgk >= 1.33)


def test_studies_refuse_too_few_runs_units_or_an_unbalanced_table():
    rows = [msa.Row("MU-0001", i, "c", 1.0 + 0.01 * i) for i in range(24)]
    with pytest.raises(msa.StudyError, match="at least 25"):
        msa.type1(rows, {"c": 1.0}, {"c": 1.0})
    with pytest.raises(msa.StudyError, match="9 units × 2 repeats"):
        msa.type3(_table(9, 2, 1, 1.0, 1.0), {"damping_force_0.3_N": 90.0})
    unbalanced = _table(10, 2, 1, 1.0, 1.0)[:-1]
    with pytest.raises(msa.StudyError, match="unbalanced"):
        msa.type3(unbalanced, {"damping_force_0.3_N": 90.0})


def test_the_randomised_order_holds_every_unit_and_repeat_once():
    order = msa.randomised_order([f"SN-{i:04d}" for i in range(10)], 2, seed=3)
    assert sorted(order) == sorted((f"SN-{i:04d}", k) for i in range(10) for k in (1, 2))
    assert order != sorted(order, key=lambda x: (x[1], x[0]))
