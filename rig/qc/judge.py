"""The decision with the uncertainty: guard bands as in ISO 14253-1.

A characteristic conforms (PASS) when value ± k·σ lies strictly inside its limits, does
not conform (FAIL) when value ∓ k·σ lies strictly outside, and is INCONCLUSIVE when the
uncertainty interval straddles a limit — a value exactly on a limit is never a PASS.
The unit's verdict is FAIL if any characteristic fails, else INCONCLUSIVE if any is
inconclusive, else PASS; a *predicted* characteristic (from the identified model) is
judged and shown but never decides the verdict.  Each failed
characteristic names its likely cause from the spec's table.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from rig.qc.characteristics import Measured
from rig.qc.spec import Spec


class Outcome(StrEnum):
    PASS = "PASS"
    FAIL = "FAIL"
    INCONCLUSIVE = "INCONCLUSIVE"


@dataclass(frozen=True)
class Judged:
    measured: Measured
    low: float | None
    high: float | None
    nominal: float
    outcome: Outcome
    direction: str | None     # "low" or "high" for a value outside or near a limit
    cause: str | None         # for a FAIL: the spec's likely cause
    title: str = ""           # the spec's readable name

    @property
    def name(self) -> str:
        return self.measured.name


@dataclass(frozen=True)
class Judgement:
    verdict: Outcome
    characteristics: tuple[Judged, ...]
    k: float

    @property
    def diagnosis(self) -> list[str]:
        """One line per failed characteristic: what, which way, the likely cause."""
        return [f"{j.title or j.name} too {j.direction}: {j.cause or 'no cause listed in the spec'}"
                for j in self.characteristics if j.outcome is Outcome.FAIL]


def decide(value: float | None, std: float | None, low: float | None, high: float | None,
           k: float) -> tuple[Outcome, str | None]:
    """The outcome for one value, and on which side of the tolerance it is (if outside or near)."""
    if value is None or std is None:
        return Outcome.INCONCLUSIVE, None
    u = k * std
    if low is not None and value + u < low:
        return Outcome.FAIL, "low"
    if high is not None and value - u > high:
        return Outcome.FAIL, "high"
    if (low is None or value - u > low) and (high is None or value + u < high):
        return Outcome.PASS, None
    near_low = low is not None and (high is None or abs(value - low) <= abs(value - high))
    return Outcome.INCONCLUSIVE, "low" if near_low else "high"


def judge(spec: Spec, measured: list[Measured]) -> Judgement:
    by_name = {m.name: m for m in measured}
    judged = []
    for c in spec.characteristics:
        m = by_name[c.name]
        outcome, direction = decide(m.value, m.std, c.low, c.high, spec.k)
        cause = spec.cause(c.name, direction) if outcome is Outcome.FAIL and direction else None
        judged.append(Judged(m, c.low, c.high, c.nominal, outcome, direction, cause, c.title))
    outcomes = {j.outcome for j in judged if not j.measured.predicted}   # the model explains, it does not decide
    verdict = (Outcome.FAIL if Outcome.FAIL in outcomes else
               Outcome.INCONCLUSIVE if Outcome.INCONCLUSIVE in outcomes else Outcome.PASS)
    return Judgement(verdict, tuple(judged), spec.k)
