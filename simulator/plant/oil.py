"""The oil: its viscosity (Walther), its compliance with the cylinder's (one effective
bulk modulus) and nitrogen's solubility in it (Henry/Ostwald), reached with a time
constant that is shorter for release than for absorption."""

from __future__ import annotations

import numpy as np

from simulator.plant.constants import R_GAS, PlantConstants


def kinematic_viscosity(k: PlantConstants, T):
    """ν [m²/s] from the Walther law log10 log10(ν_cSt + 0.7) = A − B·log10 T."""
    return (10 ** (10 ** (k.oil_walther_A - k.oil_walther_B * np.log10(T))) - 0.7) * 1e-6


def ostwald(k: PlantConstants, T):
    """Ostwald coefficient of nitrogen in the oil at temperature T."""
    return k.oil_ostwald_20C + k.oil_ostwald_slope * (T - 293.15)


def dissolved_equilibrium(k: PlantConstants, p, T):
    """Moles of nitrogen the oil holds at equilibrium with gas at pressure p, oil at T."""
    return ostwald(k, T) * k.geometry_oil_volume * p / (R_GAS * T)


def dissolution_rate(k: PlantConstants, p, T, dissolved):
    """dn_d/dt [mol/s]: towards equilibrium, release faster than absorption (the time
    constant switches smoothly over a thousandth of the equilibrium amount)."""
    target = dissolved_equilibrium(k, p, T)
    gap = target - dissolved
    absorbing = 0.5 * (1 + np.tanh(gap / (1e-3 * np.abs(target) + 1e-12)))
    tau = k.oil_release_time + (k.oil_absorption_time - k.oil_release_time) * absorbing
    return gap / tau


def compliance_volume(k: PlantConstants, p):
    """Gas volume gained [m³] by the oil's compression and the cylinder's expansion
    above the charge pressure."""
    return k.geometry_oil_volume * (p - k.charge_pressure) / k.oil_bulk_modulus
