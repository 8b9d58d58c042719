"""How QC shows a characteristic — the same in the terminal summary, the report, ``qc
history`` and the operator's console.

The value with its expanded uncertainty k·σ and σ itself to two significant digits, the
value to the same decimal place (identify.notation, GUM 7.2.6); the limits as the spec
states them; the acceptance limits (the limits moved in by k·σ, ISO 14253-1) at the
value's place; every number with its unit; the spec's readable title, the identifier
kept for JSON and as a small second line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from identify.notation import at_place, decimal_place, expanded, plus_minus, rounded, unit_text
from rig.qc.judge import Outcome
from rig.qc.records import CharacteristicRecord, QcRecord

# Which σ the verdict used, as the report and the console name it, and why that one.
BASIS = {"noise": "noise only", "residual": "residual-based", "noise-misfit": "noise only, misfit found",
         "scatter": "period scatter", "budget": "GUM budget", "predicted": "predicted by the model"}
WHY = {"noise": "the fit's residuals are at the level of the measurement noise (no model error found), so the "
                "noise-only covariance of the fit is propagated",
       "residual": "the fit's residuals exceed the measurement noise (model error), so the residual-based "
                   "covariance, the larger one, is propagated: the guard band does not claim a precision the "
                   "model lacks",
       "noise-misfit": "the fit's residuals exceed the measurement noise, but the plan has too few experiments "
                       "for a residual-based covariance: the noise-only one is propagated and may understate σ",
       "scatter": "a measured quantity: σ is the scatter of the loop energy between the captured periods "
                  "(standard error of their mean)",
       "budget": "a measurand: σ is the combined standard uncertainty of its budget (the rows below in quadrature: "
                 "the repeatability over the captured cycles, type A, and the transducers' calibration, the "
                 "temperature correction and the interpolation to the stated condition, type B)",
       "predicted": "predicted by the identified model, not measured: σ propagates the fit's covariance with the "
                    "model discrepancy σ_δ of the spec's type test; shown and judged, it never decides the verdict"}
PREDICTED = "predicted"   # the label a characteristic from the model carries wherever it is shown


@dataclass(frozen=True)
class VerdictColours:
    """How a verdict or an outcome is coloured, the one table the report and the console read."""

    text: str            # the word in colour on white: a table's outcome, the report's banner behind white letters
    banner: str          # the console's large verdict: its background
    banner_text: str     # and its letters


# No verdict (ABORTED, REFUSED, ERROR) is grey, never green.
VERDICT_COLOURS: dict[Outcome | None, VerdictColours] = {
    Outcome.PASS: VerdictColours("#1a7f37", "#2e7d32", "white"),
    Outcome.FAIL: VerdictColours("#c62828", "#c62828", "white"),
    Outcome.INCONCLUSIVE: VerdictColours("#b26a00", "#f9a825", "black"),
    None: VerdictColours("#555555", "#9e9e9e", "white"),
}


def verdict_colours(outcome: Outcome | str | None) -> VerdictColours:
    """The colours of an :class:`~rig.qc.judge.Outcome` (or its name, as a record stores
    it); anything else has no verdict and is grey."""
    known = outcome if outcome in set(Outcome) else None
    return VERDICT_COLOURS[Outcome(known) if known is not None else None]


@dataclass(frozen=True)
class Shown:
    """One characteristic as text cells, each number with its unit."""

    name: str            # the identifier (JSON, the database)
    title: str           # the spec's readable name
    value: str           # 5.909 ± 0.082 bar (value ± k·σ, k times σ as shown)
    sigma: str           # 0.041 bar
    basis: str           # noise only, residual-based, period scatter ("" unknown)
    limits: str          # 6 bar ± 5 %, 60 … 150 N, ≤ 150 N
    acceptance: str      # 5.782 … 6.218 bar
    outcome: str


def limits_text(nominal: float, low: float | None, high: float | None, unit: str) -> str:
    """The limits as a spec states them: nominal ± p % where they are symmetric about it
    by a round percentage, else the two limits, or the one limit."""
    u = unit_text(unit)
    if low is not None and high is not None:
        if nominal and math.isclose(nominal - low, high - nominal, rel_tol=1e-9):
            percent = 100 * (high - nominal) / abs(nominal)
            if math.isclose(percent, round(percent, 3), abs_tol=1e-9):
                return f"{nominal:g} {u} ± {round(percent, 3):g} %"
        return f"{low:g} … {high:g} {u}"
    if low is not None:
        return f"≥ {low:g} {u}"
    return f"≤ {high:g} {u}" if high is not None else "—"


def shown(record: QcRecord, c: CharacteristicRecord, k: float | None = None) -> Shown:
    k = record.k if record.k is not None else k
    u = unit_text(c.unit)
    value = sigma = acceptance = "—"
    if c.value is not None and c.std is not None and k is not None:
        value, sigma = expanded(c.value, c.std, k, c.unit)   # k·σ and σ that agree, at σ's place
        place = decimal_place(c.std)
        low, high = record.acceptance(c) if record.k is not None else (
            None if c.low is None else c.low + k * c.std, None if c.high is None else c.high - k * c.std)
        if low is not None and high is not None:
            acceptance = (f"{at_place(low, place)} … {at_place(high, place)} {u}" if low < high
                          else "none (k·σ exceeds the tolerance)")
        elif low is not None:
            acceptance = f"> {at_place(low, place)} {u}"
        elif high is not None:
            acceptance = f"< {at_place(high, place)} {u}"
    elif c.value is not None:
        value = plus_minus(c.value, None, c.unit)
    title = c.title or c.name
    if c.sigma_basis == "predicted" and PREDICTED not in title.lower():
        title += f" ({PREDICTED})"
    return Shown(c.name, title, value, sigma, BASIS.get(c.sigma_basis or "", ""),
                 limits_text(c.nominal, c.low, c.high, c.unit), acceptance, c.outcome)


def sigma_note(c: CharacteristicRecord) -> str:
    """Which σ the verdict on ``c`` used and why, with its parts (one note per characteristic)."""
    if c.std is None or c.std_fit is None:
        return f"{c.title or c.name}: no σ (no value), so no verdict but INCONCLUSIVE"
    basis = c.sigma_basis or ""
    if basis == "budget":
        return (f"{c.title or c.name}: u {BASIS[basis]} — {WHY[basis]}; type A {rounded(c.std_fit, c.std_fit)[0]} "
                f"{unit_text(c.unit)}, type B {rounded(c.u_cal, c.u_cal)[0] if c.u_cal else '0'} {unit_text(c.unit)}")
    parts = (f"σ = √(σ_fit² + u_cal²) with σ_fit {rounded(c.std_fit, c.std_fit)[0]} {unit_text(c.unit)} and the "
             f"rig's calibration u_cal {c.u_cal:g} {unit_text(c.unit)}")
    if basis not in WHY:
        return f"{c.title or c.name}: {parts} (this record does not say which fit covariance gave σ_fit)"
    return f"{c.title or c.name}: σ {BASIS[basis]} — {WHY[basis]}; {parts}"
