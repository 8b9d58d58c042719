"""Measurement-system analysis of a QC station: the type 1 study (VDA 5; Robert Bosch
GmbH, Booklet No. 10 "Capability of Measurement and Test Processes", 2019; AIAG MSA 4th ed.
2010, ch. III B: bias and repeatability) and the type 3 study (no operator influence:
AIAG MSA ch. III B, "Analysis of Variance (ANOVA) Method", with the operator term absent).

Both take a table of measurements, (unit, repeat, characteristic, value) rows, and each
characteristic's tolerance T = high − low, so that they serve whatever defines the
characteristics (today's identification, measurands at the axle).

Type 1, per characteristic, n ≥ 25 measurements of one master with reference value x_m:
    Cg  = 0.2·T / (6·s)
    Cgk = (0.1·T − |x̄ − x_m|) / (3·s)           goal ≥ 1.33 each
and the bias x̄ − x_m with its one-sample t-test (H₀: no bias; AIAG: the bias is
acceptable at α = 0.05 when 0 lies in its confidence interval).

Type 3, per characteristic, p ≥ 10 units × r ≥ 2 repeats: the one-way ANOVA of value on
unit (statsmodels: ``ols`` and ``anova_lm``, the library's table checked in
tests/test_qc_msa.py against the sums of squares computed by hand with numpy):
    EV (repeatability) = √MS_error                     GRR = EV (no operator: AV = 0)
    PV (part variation) = √max((MS_unit − MS_error)/r, 0)
    TV = √(GRR² + PV²)
    %GRR of tolerance = 100·6·GRR/T,  %GRR of TV = 100·GRR/TV,  ndc = 1.41·PV/GRR
    (AIAG: %GRR ≤ 10 % acceptable, 10-30 % may be acceptable, ndc ≥ 5).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from rig.errors import BadInput

CAPABILITY_GOAL = 1.33
MIN_TYPE1_RUNS = 25
MIN_TYPE3_UNITS = 10
MIN_TYPE3_REPEATS = 2
GRR_GOAL_PERCENT = 10.0
NDC_GOAL = 5
ALPHA = 0.05


@dataclass(frozen=True)
class Row:
    unit: str
    repeat: int
    characteristic: str
    value: float


@dataclass(frozen=True)
class Type1:
    characteristic: str
    n: int
    reference: float
    tolerance: float
    mean: float
    s: float
    cg: float
    cgk: float
    bias: float
    t: float
    p: float                        # two-sided p of H₀: no bias
    bias_ci: tuple[float, float]    # its (1 − α) confidence interval

    @property
    def capable(self) -> bool:
        return self.cg >= CAPABILITY_GOAL and self.cgk >= CAPABILITY_GOAL

    @property
    def bias_significant(self) -> bool:
        return self.p < ALPHA


@dataclass(frozen=True)
class AnovaRow:
    source: str                     # "unit" or "repeatability"
    df: int
    ss: float
    ms: float
    f: float | None
    p: float | None


@dataclass(frozen=True)
class Type3:
    characteristic: str
    units: int
    repeats: int
    tolerance: float
    ev: float                       # repeatability (σ)
    pv: float                       # part-to-part (σ)
    tv: float
    grr_tolerance_percent: float
    grr_tv_percent: float
    ndc: float
    anova: tuple[AnovaRow, ...]

    @property
    def grr(self) -> float:
        return self.ev

    @property
    def acceptable(self) -> bool:
        return self.grr_tolerance_percent <= GRR_GOAL_PERCENT and self.ndc >= NDC_GOAL


class StudyError(BadInput):
    """A table a study cannot be computed from (too few runs, units, repeats; unbalanced)."""


def by_characteristic(rows: Iterable[Row]) -> dict[str, list[Row]]:
    out: dict[str, list[Row]] = {}
    for r in rows:
        out.setdefault(r.characteristic, []).append(r)
    return out


def type1(rows: Iterable[Row], reference: Mapping[str, float], tolerance: Mapping[str, float],
          min_runs: int = MIN_TYPE1_RUNS) -> list[Type1]:
    from scipy import stats

    out = []
    for name, rs in by_characteristic(rows).items():
        x = np.array([r.value for r in rs if math.isfinite(r.value)])
        if len(x) < min_runs:
            raise StudyError(f"type 1 study of {name}: {len(x)} measurements; it needs at least {min_runs}")
        xm, T = reference[name], tolerance[name]
        mean, s = float(x.mean()), float(x.std(ddof=1))
        bias = mean - xm
        test = stats.ttest_1samp(x, xm)
        half = float(stats.t.ppf(1 - ALPHA / 2, len(x) - 1)) * s / math.sqrt(len(x))
        cg = 0.2 * T / (6 * s) if s > 0 else math.inf
        cgk = (0.1 * T - abs(bias)) / (3 * s) if s > 0 else math.inf
        out.append(Type1(name, len(x), xm, T, mean, s, cg, cgk, bias, float(test.statistic), float(test.pvalue),
                         (bias - half, bias + half)))
    return out


def _balanced(name: str, rs: list[Row]) -> tuple[list[str], int]:
    units = sorted({r.unit for r in rs})
    counts = {u: sum(1 for r in rs if r.unit == u) for u in units}
    repeats = min(counts.values())
    if len(set(counts.values())) != 1:
        raise StudyError(f"type 3 study of {name}: unbalanced ({', '.join(f'{u}: {c}' for u, c in counts.items())} "
                         "measurements): every unit needs the same number of repeats")
    return units, repeats


def type3(rows: Iterable[Row], tolerance: Mapping[str, float], min_units: int = MIN_TYPE3_UNITS,
          min_repeats: int = MIN_TYPE3_REPEATS) -> list[Type3]:
    import pandas as pd
    from statsmodels.formula.api import ols
    from statsmodels.stats.anova import anova_lm

    out = []
    for name, rs in by_characteristic(rows).items():
        units, r = _balanced(name, rs)
        if len(units) < min_units or r < min_repeats:
            raise StudyError(f"type 3 study of {name}: {len(units)} units × {r} repeats; it needs at least "
                             f"{min_units} × {min_repeats}")
        frame = pd.DataFrame({"unit": [x.unit for x in rs], "value": [x.value for x in rs]})
        table = anova_lm(ols("value ~ C(unit)", data=frame).fit(), typ=1)
        unit_row, error_row = table.loc["C(unit)"], table.loc["Residual"]
        ms_unit, ms_error = float(unit_row["mean_sq"]), float(error_row["mean_sq"])
        anova = (AnovaRow("unit", int(unit_row["df"]), float(unit_row["sum_sq"]), ms_unit, float(unit_row["F"]),
                          float(unit_row["PR(>F)"])),
                 AnovaRow("repeatability", int(error_row["df"]), float(error_row["sum_sq"]), ms_error, None, None))
        out.append(components(name, len(units), r, tolerance[name], ms_unit, ms_error, anova))
    return out


def components(name: str, units: int, repeats: int, tolerance: float, ms_unit: float, ms_error: float,
               anova: tuple[AnovaRow, ...]) -> Type3:
    """The AIAG figures from the ANOVA's mean squares."""
    ev = math.sqrt(ms_error)
    pv = math.sqrt(max((ms_unit - ms_error) / repeats, 0.0))
    tv = math.hypot(ev, pv)
    return Type3(name, units, repeats, tolerance, ev, pv, tv, 100 * 6 * ev / tolerance,
                 100 * ev / tv if tv > 0 else math.nan, 1.41 * pv / ev if ev > 0 else math.inf, anova)


def randomised_order(units: list[str], repeats: int, seed: int | None = None) -> list[tuple[str, int]]:
    """Each unit ``repeats`` times, shuffled (AIAG: randomised, so that a drift of the
    station is not read as a difference between units)."""
    order = [(u, k + 1) for k in range(repeats) for u in units]
    np.random.default_rng(seed).shuffle(order)
    return order
