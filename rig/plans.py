"""Experiment plans: the standard set built in, or a TOML file; checked against the
rig's limits before anything moves (every violation listed), with an estimated
duration."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from identify.plans import STANDARD_SET, ExperimentSpec
from rig.config import RigConfig
from rig.errors import BadInput
from rig.shaker import check_waveform
from rig.tomlfile import read_toml

MOVE_SPEED_M_S = 0.05  # the controller's profile speed, for the duration estimate


class PlanError(BadInput):
    """A plan that cannot be run (file problems, or limit violations listed one per line)."""


@dataclass(frozen=True)
class Plan:
    name: str
    experiments: tuple[ExperimentSpec, ...]
    text: str = ""

    def select(self, letters: list[str] | None) -> Plan:
        if not letters:
            return self
        by_letter = {e.letter: e for e in self.experiments}
        unknown = [x for x in letters if x not in by_letter]
        if unknown:
            raise PlanError(f"plan {self.name!r} has no experiment {', '.join(unknown)} "
                            f"(letters: {', '.join(by_letter)})")
        return replace(self, experiments=tuple(by_letter[x] for x in letters))

    def with_periods(self, periods: int | None) -> Plan:
        if periods is None:
            return self
        if periods < 1:
            raise PlanError(f"--periods {periods}: at least one whole period must be captured")
        return replace(self, experiments=tuple(replace(e, periods=periods) for e in self.experiments))


def load_plan(source: str) -> Plan:
    """``standard`` or the path of a plan TOML file."""
    if source == "standard":
        return Plan("standard", STANDARD_SET, "standard")
    path = Path(source)
    text, doc = read_toml(path, PlanError, "plan ")
    entries = doc.get("experiment", [])
    if not entries:
        raise PlanError(f"plan {path}: no [[experiment]] tables")
    experiments, seen = [], set()
    for i, e in enumerate(entries, 1):
        where = f"plan {path}, experiment {i}"
        try:
            spec = ExperimentSpec(str(e["label"]), str(e.get("group", "")), float(e["static_mm"]),
                                  float(e["amplitude_mm"]), float(e["frequency_Hz"]), str(e.get("waveform", "sine")),
                                  int(e.get("periods", doc.get("periods", 3))))
        except KeyError as exc:
            raise PlanError(f"{where}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise PlanError(f"{where}: {exc}") from None
        if spec.letter in seen:
            raise PlanError(f"{where}: label {spec.letter!r} used twice")
        seen.add(spec.letter)
        experiments.append(spec)
    return Plan(str(doc.get("name", path.stem)), tuple(experiments), text)


def check_plan(plan: Plan, config: RigConfig) -> list[str]:
    """Every violation of the rig's limits and capabilities, one line each."""
    problems = []
    for e in plan.experiments:
        for p in check_waveform(config.limits, e.static_position_mm * 1e-3, e.amplitude_mm * 1e-3,
                                e.frequency_hz, e.waveform):
            problems.append(f"experiment {e.letter}: {p}")
        if e.periods < 1:
            problems.append(f"experiment {e.letter}: periods {e.periods} < 1")
    return problems


def estimate_duration_s(plan: Plan, config: RigConfig, start_position_m: float = 0.0) -> float:
    """Rough simulated-time estimate: moves, ramps, settling (the minimum), capture."""
    ss, total, position = config.steady_state, 0.0, start_position_m
    for e in plan.experiments:
        static = e.static_position_mm * 1e-3
        total += math.pi * abs(static - position) / (2 * MOVE_SPEED_M_S) + 2 * ss.ramp_time_s
        settle_cycles = max(ss.min_cycles, 2 * math.ceil(ss.block_s * e.frequency_hz))
        total += (settle_cycles + e.periods) / e.frequency_hz
        position = static
    return total
