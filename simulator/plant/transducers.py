"""What the transducers see: the pressure transducer sits in a dead volume at the
wall's temperature, fed through a thin line (Hagen–Poiseuille, so its reading lags the
gas); the gas thermometer is a first-order lag whose time constant falls with the gas's
density, pulled toward the wall through its mount."""

from __future__ import annotations

import numpy as np

from simulator.plant.constants import R_GAS, PlantConstants


def line_flow(k: PlantConstants, p_gas, p_dead, T_line, viscosity):
    """Molar flow [mol/s] from the gas into the transducer's dead volume."""
    conductance = np.pi * k.transducer_line_radius**4 / (8 * viscosity * k.transducer_line_length)
    return conductance * (p_gas - p_dead) * 0.5 * (p_gas + p_dead) / (R_GAS * T_line)


def thermometer_rate(k: PlantConstants, p, T_gas, T_wall, T_sensor):
    """dT_s/dt [K/s] of the gas thermometer."""
    tau = k.transducer_thermometer_time * np.sqrt(k.charge_pressure / np.maximum(p, 1e4))
    return (T_gas - T_sensor) / tau + (T_wall - T_sensor) / k.transducer_thermometer_mount_time
