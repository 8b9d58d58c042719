"""Heat transfer between the gas and the wall: natural convection (Nu = C·Ra^(1/3),
turbulent, so h does not depend on the length) plus a flow-driven part that grows with
the piston's speed (Nu_f = C_f·Re^0.67); the wall area shrinks with the gas column."""

from __future__ import annotations

import numpy as np

from simulator.plant.constants import G0, R_GAS, PlantConstants
from simulator.plant.gas import Nitrogen

DT_SMOOTH_K = 0.05  # |ΔT|^(1/3) has an infinite slope at 0; below this the flux is linear


def inside_coefficient(k: PlantConstants, gas: Nitrogen, p, T, density, dT, speed, transport=None):
    """Film coefficient h [W/(m² K)] between gas at (p, T, density) and a wall ΔT away,
    the gas column moving at ``speed`` [m/s] (``transport``: conductivity and viscosity
    at p, when already at hand)."""
    cond, mu = transport if transport is not None else gas.transport(p)
    cp = (gas.cv(p) + R_GAS) / gas.molar_mass
    dTs = np.sqrt(dT**2 + DT_SMOOTH_K**2)
    h_nat = k.heat_natural_coefficient * cond * (G0 / T * dTs * density**2 * cp / (mu * cond)) ** (1 / 3)
    reynolds = density * np.abs(speed) * k.geometry_bore / mu
    h_forced = cond / k.geometry_bore * k.heat_forced_coefficient * reynolds ** k.heat_forced_exponent
    return h_nat + h_forced


def inside_area(k: PlantConstants, gas_volume):
    """Wall area the gas touches [m²]: the cylinder's side along the gas column, its
    end cap and the oil's surface (the oil is lumped with the wall)."""
    section = np.pi * k.geometry_bore**2 / 4
    return np.pi * k.geometry_bore * gas_volume / section + 2 * section
