"""The damping orifice: Q = Cd·A_o·u, u = sqrt(2Δp/ρ) the ideal jet velocity, with the
Lichtarowicz discharge coefficient 1/Cd = 1/Cd_u + (20/Re)(1 + 2.25 L/d), Re = u·d/ν:
laminar (Δp ∝ Q) at low Re, turbulent (Δp ∝ Q²) at high Re.  Given Q the jet velocity
is the positive root of u² − a·u − b = 0, explicit and vectorised."""

from __future__ import annotations

import numpy as np

from simulator.plant.constants import PlantConstants


def orifice_area(k: PlantConstants) -> float:
    return float(np.pi * k.orifice_diameter**2 / 4)


def pressure_drop(k: PlantConstants, flow, nu):
    """|Δp| [Pa] across the orifice for the volume flow ``flow`` [m³/s] at viscosity ν."""
    area, d = orifice_area(k), k.orifice_diameter
    q = np.abs(flow)
    a = q / (area * k.orifice_cd_turbulent)
    b = 20 * (1 + 2.25 * k.orifice_length_ratio) * nu * q / (area * d)
    u = 0.5 * (a + np.sqrt(a**2 + 4 * b))
    return 0.5 * k.oil_density * u**2


def max_flow(k: PlantConstants, dp, nu):
    """Flow [m³/s] the orifice passes under pressure difference ``dp`` ≥ 0."""
    u = np.sqrt(2 * np.maximum(dp, 0.0) / k.oil_density)
    inv_cd = 1 / k.orifice_cd_turbulent + 20 * (1 + 2.25 * k.orifice_length_ratio) * nu / (
        k.orifice_diameter * np.maximum(u, 1e-12))
    return orifice_area(k) * u / inv_cd
