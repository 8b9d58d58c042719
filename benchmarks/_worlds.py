"""The two worlds a claim is measured in: the model world (the simulator's 2-dof truth,
the model the fit uses) and the plant (``simulator/plant/``, physics richer than any
identification model).  One argument, ``--physics``, chooses between them; everything
else a benchmark does is the same in both.

A world gives data of a production unit under a plan (`simulator generate`, offline) and
the unit's own drop test: the truth a prediction is judged against.  The plant world is a
family: ``variant`` names one of its plausible plants (``plant_variants()``, nominal
first; docs/plant.md), so that a claim can be measured on each:

    for variant in plant_variants():
        generate("plant", "standard", out / variant, unit, variant=variant)
        drop("plant", unit, variant=variant)
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
WORLDS = ("model", "plant")
DROP_MASS_KG = 350.0
DROP_VELOCITY_M_S = 0.5  # the paper's peak velocity, five times the shaker's
DROP_DURATION_S = 2.5    # the paper's drop-test record


class WorldUnavailable(RuntimeError):
    """The world is not on this checkout (the plant tier not merged yet)."""


def available(world: str) -> bool:
    if world == "model":
        return True
    return importlib.util.find_spec("simulator.plant") is not None


@dataclass(frozen=True)
class Unit:
    """A production unit: ``kind`` (good or a fault) and its seed; None = the nominal damper."""

    kind: str | None = None
    seed: int = 0

    def args(self) -> list[str]:
        return [] if self.kind is None else ["--unit", self.kind, "--unit-seed", str(self.seed)]

    def __str__(self) -> str:
        return "nominal" if self.kind is None else f"{self.kind}#{self.seed}"


@dataclass(frozen=True)
class Drop:
    """A drop test's record (SI): time, damper force and stroke."""

    t: np.ndarray
    force_N: np.ndarray
    stroke_m: np.ndarray


def plant_variants() -> list[str]:
    """The plant's named variants (simulator.plant.family), ``nominal`` first."""
    if not available("plant"):
        raise WorldUnavailable("no plant world on this checkout")
    from simulator.plant.family import variant_names

    return variant_names()


def plant_variant_args(variant: str | None) -> list[str]:
    """The ``simulator generate|serve`` arguments of plant variant ``variant`` (None or nominal: none)."""
    return [] if variant in (None, "nominal") else ["--plant-variant", variant]


def generate(world: str, plan: str, out: Path, unit: Unit = Unit(), seed: int = 0,
             variant: str | None = None) -> Path:
    """``python -m simulator generate`` of ``plan`` in ``world`` into ``out`` (the plant:
    its ``variant``, default nominal)."""
    if not available(world):
        raise WorldUnavailable(f"no {world} world on this checkout")
    cmd = [sys.executable, "-m", "simulator", "generate", "--plan", plan, "--out", str(out), "--seed", str(seed),
           "--date", "261126", *unit.args()]
    cmd += ["--physics", world]
    if world == "plant":
        cmd += plant_variant_args(variant)
    elif variant not in (None, "nominal"):
        raise ValueError(f"plant variant {variant!r} in the {world} world")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {proc.stderr.strip() or proc.stdout.strip()}")
    return out


def drop(world: str, unit: Unit = Unit(), t: np.ndarray | None = None, variant: str | None = None) -> Drop:
    """The unit's own drop test in ``world`` (the plant: its ``variant``): 350 kg landing
    at 0.5 m/s, 2.5 s."""
    t = np.linspace(0.0, DROP_DURATION_S, 1251) if t is None else t
    if world == "model":
        if variant not in (None, "nominal"):
            raise ValueError(f"plant variant {variant!r} in the model world")
        from simulator.physics import drop_test
        from simulator.truth import load_truth

        damper = load_truth(unit=unit.kind, unit_seed=unit.seed) if unit.kind else load_truth()
        s = drop_test(damper, DROP_MASS_KG, DROP_VELOCITY_M_S, t)
        return Drop(t, s.axle_force, s.stroke - damper.theta["theta12"])
    if not available(world):
        raise WorldUnavailable(f"no {world} world on this checkout")
    from simulator.plant.drop import simulate_drop
    from simulator.plant.family import variant_constants

    rate = (len(t) - 1) / (t[-1] - t[0])
    record = simulate_drop(unit.kind, unit.seed, mass_kg=DROP_MASS_KG, velocity_m_s=DROP_VELOCITY_M_S,
                           duration_s=float(t[-1] - t[0]), rate_hz=rate,
                           constants=variant_constants(variant or "nominal"))
    if len(record.t) != len(t):
        raise RuntimeError(f"plant drop sampled {len(record.t)} times, asked for {len(t)}")
    return Drop(t, np.asarray(record.force_N), np.asarray(record.stroke_m))
