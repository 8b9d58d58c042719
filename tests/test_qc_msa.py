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


def test_studies_are_stored_once_reported_and_listed_by_history(tmp_path, monkeypatch, capsys):
    """The study commands' second half on stand-in runs (each a record with the spec's
    characteristics; the runs themselves are qc run's, tested elsewhere): a type 1 and a
    type 3 study stored read-only in the station folder and in its database, with a
    report, and listed by qc history."""
    import dataclasses
    import stat

    from rig.cli import main
    from rig.config import CONFIG_DIR
    from rig.qc import msa_run
    from rig.qc.judge import Outcome
    from rig.qc.records import CharacteristicRecord, QcRecord, RecordStatus
    from rig.qc.run import QcOptions
    from rig.qc.studies import StudyInputError, stored

    spec = load_spec("default")
    rng = np.random.default_rng(2)
    offsets: dict[str, float] = {}

    def run(opt, serial, kind, say):
        off = offsets.setdefault(serial, 0.02 * rng.standard_normal() if serial != "MU-0001" else 0.0)
        chars = tuple(CharacteristicRecord(c.name, c.unit, c.nominal * (1 + off + 5e-4 * rng.standard_normal()),
                                           0.01, 0.01, 0.0, c.low, c.high, c.nominal, Outcome.PASS, c.title)
                      for c in spec.characteristics)
        return QcRecord(str(rng.integers(1 << 60)), serial, "qe", "rig", None, None, "now", "x", spec.name,
                        spec.version, spec.sha256, None, None, Outcome.PASS, RecordStatus.COMPLETE, "s", "d", {},
                        chars, simulated=True)

    monkeypatch.setattr(msa_run, "measure", run)
    opt = QcOptions(spec="default", serial="MU-0001", shaker="tcp://127.0.0.1:9", daq="socket://127.0.0.1:9",
                    out=tmp_path, rig_id="st-1", calibration=str(CONFIG_DIR / "station-calibration-simulated.toml"))
    said: list[str] = []
    reference = str(CONFIG_DIR / "master-simulated.toml")
    with pytest.raises(StudyInputError, match="at least 25"):
        msa_run.run_type1(opt, "MU-0001", reference, 24, said.append)
    assert msa_run.run_type1(opt, "MU-0001", reference, 25, said.append) == msa_run.EXIT_GOALS_MET
    assert msa_run.run_type3(dataclasses.replace(opt), [f"SN-{i:04d}" for i in range(10)], 2, said.append,
                             lambda serial: None, seed=1) == msa_run.EXIT_GOALS_MET
    assert any(line.startswith("  Gas pre-charge: n 25, Cg") for line in said)
    assert any("%GRR" in line and "ndc" in line for line in said)
    studies = stored(tmp_path)
    assert [s.kind for s in studies] == ["type1", "type3"] and all(s.equipment for s in studies)
    files = sorted((tmp_path / "qc-studies").glob("*.json"))
    assert all(not p.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH) for p in files)
    pages = sorted((tmp_path / "qc-studies").glob("*.html"))
    assert len(pages) == 2 and "CAL-2026-0612" in pages[0].read_text() and "ANOVA tables" in pages[1].read_text()
    assert len(list((tmp_path / "qc-studies").glob("*type1*.png"))) == len(spec.characteristics)
    assert msa_run.report_for(studies[1], spec).count("<h3>") == len(spec.characteristics)
    capsys.readouterr()
    assert main(["qc", "history", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "Measurement-system studies and master checks (2)" in out and "station copy only" not in out
