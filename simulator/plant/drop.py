"""The drop test on the plant: a mass released onto the damper (axle on the ground,
the load cell under it), the paper's test of predictive power.  The whole plant is free
here: stroke and velocity join its six states and the mass obeys
M·q̈ = M·g − F_d(q, q̇, y).  Integrated with scipy's LSODA (stiff where the transducer
line is, free elsewhere)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from simulator.plant.constants import G0, PlantConstants
from simulator.plant.damper import PlantDamper
from simulator.plant.units import unit_constants

DROP_MASS_KG = 350.0
DROP_VELOCITY_M_S = 0.5  # at contact; the paper's peak velocity is about 0.5 m/s


@dataclass(frozen=True)
class DropRecord:
    """What a drop rig records (SI): measured stroke, ground load (the damper force),
    the pressure transducer (absolute), the gas thermometer; and the velocity, which it
    does not."""

    t: np.ndarray
    stroke_m: np.ndarray
    force_N: np.ndarray
    pressure_Pa: np.ndarray
    temperature_K: np.ndarray
    velocity_m_s: np.ndarray


def simulate_drop(unit: str | None = None, unit_seed: int = 0, *, mass_kg: float = DROP_MASS_KG,
                  velocity_m_s: float = DROP_VELOCITY_M_S, duration_s: float = 2.5, rate_hz: float = 2000.0,
                  constants: PlantConstants | None = None, ambient_k: float | None = None) -> DropRecord:
    """The plant's drop of ``mass_kg`` touching the extended damper (q = 0, everything
    at rest and ambient) at ``velocity_m_s``; samples at ``rate_hz`` for ``duration_s``.
    ``unit``: a production unit (:mod:`simulator.units`), else the nominal plant or
    ``constants``."""
    plant = PlantDamper(unit_constants(unit, unit_seed, constants), ambient_k)
    t = np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    y0 = np.concatenate([[0.0, velocity_m_s], plant.rest_state(0.0)])

    def rhs(_, x):
        q, v, y = x[0], x[1], x[2:]
        force = plant.forces(q, v, y).damper_force
        return np.concatenate([[v, G0 - force / mass_kg], plant.rates(q, v, y)])

    n = plant.n_total
    atol = [1e-9, 1e-8, 1e-6, 1e-6, 1e-9 * n, 1e-11 * n, 1e-6, 1e-12]
    sol = solve_ivp(rhs, (0.0, t[-1]), y0, method="LSODA", t_eval=t, rtol=1e-7, atol=atol)
    if not sol.success:
        raise ArithmeticError(f"plant drop test: {sol.message}")
    q, v, y = sol.y[0], sol.y[1], sol.y[2:]
    accel = np.gradient(v, t)
    ch = plant.channels(q, v, accel, y)
    damper_force = plant.forces(q, v, y).damper_force
    return DropRecord(t, q, damper_force, ch[2], ch[3], v)
