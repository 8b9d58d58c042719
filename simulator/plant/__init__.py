"""The plant truth: a damper richer than any identification model (real-gas nitrogen,
a wall with its own heat capacity, dissolving gas, compliance, the transducers' dead
volume and lags, a Reynolds-dependent orifice, Stribeck seals, cavitation).  Its
constants, with their sources, are in ``constants.toml``; docs/plant.md describes it."""

from __future__ import annotations

from pathlib import Path

from simulator.plant.constants import PlantConstants, PlantError, load_constants
from simulator.plant.damper import PlantDamper
from simulator.plant.family import variant_constants, variant_names
from simulator.plant.units import unit_constants


def load_plant(unit: str | None = None, unit_seed: int = 0, constants: str | Path | None = None,
               variant: str | None = None) -> PlantDamper:
    """The plant of ``constants`` (a TOML like ``constants.toml``; default the nominal
    plant), changed as the named ``variant`` (:mod:`simulator.plant.family`) says,
    optionally production unit ``unit`` number ``unit_seed`` of it."""
    base = load_constants(constants)
    if variant is not None:
        base = variant_constants(variant, base)
    return PlantDamper(unit_constants(unit, unit_seed, base))


__all__ = ["PlantConstants", "PlantDamper", "PlantError", "load_constants", "load_plant", "unit_constants",
           "variant_constants",
           "variant_names"]
