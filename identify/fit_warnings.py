"""What may make a fit's numbers wrong, as data: a code and its numbers.

A fit's warnings are :class:`FitWarning` records; the sentence a report or the CLI
prints is rendered from them (``str(warning)``), and code that acts on a warning (QC's
choice of the σ to propagate, its rewording for the verdict) reads ``code`` and the
numbers, never the sentence, so rewording one cannot change a decision.

Not named ``warnings``: that would shadow the standard library's module for every
script run from this folder.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from identify import notation


class WarningCode(StrEnum):
    AT_BOUND = "at-bound"                        # an estimate ended on a bound
    UNDETERMINED = "undetermined"                # σ more than UNDETERMINED times the value: a flat direction
    POORLY_IDENTIFIABLE = "poorly-identifiable"  # σ above RELATIVE_STD_WARNING of the value
    ILL_CONDITIONED = "ill-conditioned"          # the sensitivity matrix's condition number
    NOISE_NOT_ESTIMABLE = "noise-not-estimable"  # σ assume white residuals
    MODEL_ERROR = "model-error"                  # residuals above what the measurement noise explains
    INPUT_NOISE = "input-noise"                  # errors in variables explain much of the residual variance
    UNSTABLE_ORBIT = "unstable-orbit"            # a Floquet multiplier on or outside the unit circle
    BDF2_UNRESOLVED = "bdf2-unresolved"          # bdf2 asked for on lines it differentiates wrong
    DRIFT = "drift"                              # a column's mean drifted within records


@dataclass(frozen=True)
class FitWarning:
    """One warning: its code and the numbers (and names) its sentence is made of."""

    code: WarningCode
    numbers: Mapping[str, Any] = field(default_factory=dict)

    @property
    def finding(self) -> str:
        """What was found, without what it means for the standard deviations (which the
        QC verdict words its own way, since it may propagate another σ)."""
        return _RENDER[self.code][0](self.numbers)

    def __str__(self) -> str:
        return self.finding + _RENDER[self.code][1](self.numbers)

    def to_json(self) -> dict[str, Any]:
        return {"code": self.code.value, **self.numbers}

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> FitWarning:
        """A warning as RESULT.json's ``findings`` lists it (ValueError for an unknown code)."""
        numbers = dict(doc)
        return cls(WarningCode(numbers.pop("code")), numbers)


def _at_bound(v: Mapping[str, Any]) -> str:
    why = ("where no physical value lies (model error, or data that do not determine it)" if v["physical"]
           else "outside the range the START file allows")
    return (f"{v['name']} ({v['alias']}) ended on its {v['side']} {v['limit']:g} {v['unit']}: the data pull it "
            f"beyond, {why}; its σ is that of a free parameter")


def _undetermined(v: Mapping[str, Any]) -> str:
    return (f"{v['name']} ({v['alias']}) is not determined by these experiments: its σ "
            f"({notation.significant(v['std'])}) is more than {v['factor']:g} times its value; a flat "
            f"direction of the fit, so its estimate is no result")


def _poorly(v: Mapping[str, Any]) -> str:
    return (f"{v['name']} ({v['alias']}) is poorly identifiable from these experiments: ±{v['percent']:.0f} %"
            + (" (residual-based σ)" if v["residual"] else ""))


def _ill_conditioned(v: Mapping[str, Any]) -> str:
    return (f"sensitivity matrix is ill-conditioned (condition number {v['condition']:.2g}): the data "
            f"hardly separate {', '.join(v['names'])}")


def _noise_not_estimable(v: Mapping[str, Any]) -> str:
    return ("measurement noise not estimable (a single sample per grid bin, or no scatter at all "
            "between periods): standard deviations assume white residuals")


def _model_error(v: Mapping[str, Any]) -> str:
    share = v.get("input_share")
    clause = ("" if share is None else
              f"; the inputs' folding noise, carried through the model, explains {100 * share:.0f} % of its "
              f"residual variance")
    return (f"{v['output']}: residuals up to {v['ratio']:.1f}x what the measurement noise explains (worst: "
            f"{v['worst']}{clause}): systematic model or discretisation error")


def _model_error_consequence(v: Mapping[str, Any]) -> str:
    beside = ("; residual-based standard deviations, which include it, are given beside them" if v["residual_based"]
              else f"; with {v['experiments']} experiments for {v['parameters']} parameters, and too few frequency "
                   f"lines carrying the misfit, no residual-based ones can be given")
    return "; the standard deviations cover the noise only" + beside


def _input_noise(v: Mapping[str, Any]) -> str:
    return (f"{v['output']}: the inputs' noise left by folding, carried through the model (errors in "
            f"variables), explains {v['percent']:.0f} % of its residual variance in "
            f"{v['record']}; the weights and standard deviations include it")


def _unstable(v: Mapping[str, Any]) -> str:
    return (f"unstable periodic solution (a Floquet multiplier on or outside the unit circle): "
            f"{', '.join(v['records'])}; the fit may describe an orbit the damper cannot follow")


def _bdf2(v: Mapping[str, Any]) -> str:
    return (f"bdf2 on {v['n']} points differentiates the highest excited line of {v['record']} (harmonic "
            f"{v['harmonic']} of {v['lines']}) {v['percent']:.0f} % wrong: a resonance lands elsewhere; "
            f"use --scheme spectral")


def _drift(v: Mapping[str, Any]) -> str:
    where = ", ".join(f"{label} {notation.significant(amount)}" for label, amount in v["records"])
    return (f"the mean of {v['column']} drifts within records (by {where} {v['unit']}); the drift was removed "
            f"before folding (a one-period moving mean fitted by a cubic in time), since folded as it was it "
            f"would read as signal and as input noise")


def _nothing(v: Mapping[str, Any]) -> str:
    return ""


_RENDER: dict[WarningCode, tuple[Callable[[Mapping[str, Any]], str], Callable[[Mapping[str, Any]], str]]] = {
    WarningCode.AT_BOUND: (_at_bound, _nothing),
    WarningCode.UNDETERMINED: (_undetermined, _nothing),
    WarningCode.POORLY_IDENTIFIABLE: (_poorly, _nothing),
    WarningCode.ILL_CONDITIONED: (_ill_conditioned, _nothing),
    WarningCode.NOISE_NOT_ESTIMABLE: (_noise_not_estimable, _nothing),
    WarningCode.MODEL_ERROR: (_model_error, _model_error_consequence),
    WarningCode.INPUT_NOISE: (_input_noise, _nothing),
    WarningCode.UNSTABLE_ORBIT: (_unstable, _nothing),
    WarningCode.BDF2_UNRESOLVED: (_bdf2, _nothing),
    WarningCode.DRIFT: (_drift, _nothing),
}
