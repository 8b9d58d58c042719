"""Seal friction: Coulomb friction with a pressure part and a Stribeck breakaway,
F = (F_pre + f_p·p)·[1 + (K_brk − 1)·exp(−(v/v_St)²)]·tanh(v/v_C) + f_v·v
(the Simscape Cylinder Friction form)."""

from __future__ import annotations

import numpy as np

from simulator.plant.constants import PlantConstants


def friction(k: PlantConstants, velocity, chamber_pressure):
    """Friction force [N] opposing the stroke velocity (positive in compression)."""
    coulomb = k.seal_preload_force + k.seal_pressure_area * chamber_pressure
    stribeck = 1 + (k.seal_breakaway_ratio - 1) * np.exp(-((velocity / k.seal_stribeck_velocity) ** 2))
    return coulomb * stribeck * np.tanh(velocity / k.seal_coulomb_velocity) + k.seal_viscous * velocity
