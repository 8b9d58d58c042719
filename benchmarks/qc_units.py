"""What the measurand QC benchmarks share: a unit of either world captured as `rig qc
run` captures the spec's plan (from RUN on: the amplitude ramp, then the plan's periods),
offline with `simulator generate`, and judged as `rig qc judge` judges it."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from identify.plans import ExperimentSpec
from rig.qc.spec import Spec
from simulator.generate import generate
from simulator.physics import Damper
from simulator.truth import load_truth

FAULTS = ("gas-leak", "worn-seal", "worn-orifice")


def captured_plan(spec: Spec) -> list[ExperimentSpec]:
    """The spec's experiments as the rig records them: a transient capture holds the
    ramp's periods before the plan's (rig.planning.plans.transient_capture_s)."""
    ramp = spec.steady_state.ramp_time_s
    return [replace(e, periods=e.periods + math.ceil(ramp * e.frequency_hz)) if e.capture == "transient" else e
            for e in spec.plan.experiments]


def damper(world: str, kind: str | None, seed: int = 0, constants: object = None):
    """A production unit: ``kind`` None is the nominal one; ``constants`` (plant) or a
    Damper (model) given directly for a unit made on purpose (on a limit)."""
    if world == "model":
        return constants if isinstance(constants, Damper) else load_truth(None, "2dof", kind, seed)
    from simulator.plant.damper import PlantDamper
    from simulator.plant.units import unit_constants

    return PlantDamper(constants if constants is not None else unit_constants(kind, seed))  # type: ignore[arg-type]


def capture(spec: Spec, unit, out: Path, seed: int, noise_scale: float = 1.0) -> Path:
    """The unit's session data under ``spec``'s plan (noise_scale 0: its noise-free response)."""
    return generate(out, captured_plan(spec), unit, periods=None, seed=seed, date="261122",
                    ramp_s=spec.steady_state.ramp_time_s, noise_scale=noise_scale)
