"""Numbers with their uncertainty, printed one way everywhere.

The fit report, the batch table, QC's terminal summary, report and history, and the
operator's console all print a value beside its standard uncertainty. They do it the way
the GUM asks (7.2.6): the uncertainty to two significant digits and the value rounded to
the same decimal place, so a reader never sees digits that mean nothing. The rounding is
the ``uncertainties`` package's; this module only chooses the forms.
"""

from __future__ import annotations

import math

from uncertainties import ufloat

DIGITS = 2   # significant digits of an uncertainty (GUM 7.2.6)

# Units as people write them: the models declare ASCII ("m^2"), screens and reports show m².
_SUPERSCRIPTS = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _has_std(value: float, std: float | None) -> bool:
    return std is not None and math.isfinite(std) and std > 0 and math.isfinite(value)


def concise(value: float, std: float | None) -> str:
    """0.850060(60): the std in units of the value's last digits. Keeps several parameters
    and their stds in an 80-column table. Without a usable std, six significant digits."""
    if not _has_std(value, std):
        return f"{value:.6g}"
    return format(ufloat(value, std), f".{DIGITS}uS")


def plus_minus(value: float, std: float | None, unit: str = "") -> str:
    """5.909 ± 0.041 bar. Without a usable std, six significant digits and the unit."""
    suffix = f" {unit_text(unit)}" if unit else ""
    if not _has_std(value, std):
        return f"{value:.6g}{suffix}"
    text = format(ufloat(value, std), f".{DIGITS}uP").replace("±", " ± ")
    return text + suffix


def expanded(value: float, std: float, k: float, unit: str = "") -> tuple[str, str]:
    """A value with its expanded uncertainty k·σ, and σ, printed so that they agree:
    ("6.005 ± 0.042 bar", "0.021 bar") for σ 0.0205 and k 2 — σ to two significant digits,
    k times that σ and the value to σ's decimal place.  Rounding σ and k·σ each on its own
    printed "6.005 ± 0.041" beside "0.021", which no reader can multiply back."""
    suffix = f" {unit_text(unit)}" if unit else ""
    if not _has_std(value, std):
        return f"{value:.6g}{suffix}", "—"
    place = decimal_place(std)
    sigma = at_place(std, place)
    return f"{at_place(value, place)} ± {at_place(k * float(sigma), place)}{suffix}", f"{sigma}{suffix}"


def rounded(value: float, std: float | None) -> tuple[str, str]:
    """The value and its std as two table cells, both to the std's decimal place:
    ("5.909", "0.041"). Without a usable std: the value to six significant digits, "—"."""
    if not _has_std(value, std):
        return f"{value:.6g}", "—"
    assert std is not None
    place = decimal_place(std)
    return at_place(value, place), at_place(std, place)


def decimal_place(std: float) -> int:
    """The decimal place of a std's last significant digit: −3 for 0.041, 0 for 37 and for
    9.96 (which rounds to 10), 1 for 370 (1234 ± 370 rounds to the tens)."""
    place = math.floor(math.log10(std)) - (DIGITS - 1)
    if round(std / 10.0**place) >= 10**DIGITS:   # 9.96 rounds up to 10: one place coarser
        place += 1
    return place


def at_place(x: float, place: int) -> str:
    """x rounded to a decimal place (−3: thousandths), as decimal_place gives it. Limits and
    acceptance limits printed beside a value take the value's place."""
    if place < 0:
        return f"{x:.{-place}f}"
    return f"{round(x / 10.0**place) * 10.0**place:.0f}"


def significant(x: float, digits: int = DIGITS) -> str:
    """A number that has no uncertainty beside it (a residual's std, a bound) to ``digits``
    significant digits, written out without an exponent: 568.08 → 570, 0.000321 → 0.00032."""
    if not math.isfinite(x) or x == 0:
        return f"{x:g}"
    return at_place(x, math.floor(math.log10(abs(x))) - (digits - 1))


def unit_text(unit: str) -> str:
    """A declared unit as people write it: m^2 → m², s^-1 → s⁻¹, N*s/m → N·s/m."""
    out, i = [], 0
    while i < len(unit):
        if unit[i] == "^":
            j = i + 1
            while j < len(unit) and (unit[j].isdigit() or (unit[j] == "-" and j == i + 1)):
                j += 1
            out.append(unit[i + 1:j].translate(_SUPERSCRIPTS))
            i = j
        else:
            out.append("·" if unit[i] == "*" else unit[i])
            i += 1
    return "".join(out)
