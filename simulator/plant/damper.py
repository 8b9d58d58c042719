"""The plant damper assembled: six states that no identification model carries, driven
by the stroke (shaker) or free (drop test).

States (SI), in this order:

=========  ==========================================================================
T_gas      temperature of the main nitrogen volume
T_wall     lumped temperature of the wall around the gas and of the oil
n_diss     moles of nitrogen dissolved in the oil
n_dead     moles in the pressure transducer's dead volume (at the wall's temperature)
T_sensor   the gas thermometer's temperature
V_void     cavitation void in the rebound chamber (0 unless the oil cavitated)
=========  ==========================================================================

The main gas's energy balance is the first law of an open volume for a real gas:
n·c_v·dT/dt = Q̇ − T(∂p/∂T)_v·n·dv/dt, v the molar volume (nitrogen that dissolves or
flows to the transducer leaves with its own enthalpy, so only the specific volume's change
does work).  The oil's compression and the cylinder's expansion give the gas volume
V_oil·(p − p_charge)/β; in the rate of V its share is taken at the gas spring's local
stiffness with κ = 1.3 (a 1 % correction of a 1 % term).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.plant import heat, oil, orifice, seals, transducers
from simulator.plant.constants import G0, MOVING_MASS_KG, P_ATM, PlantConstants, load_constants
from simulator.plant.gas import Nitrogen

KAPPA_COMPLIANCE = 1.3


@dataclass(frozen=True)
class Forces:
    """Algebraic quantities at a state (vectorised); pressures absolute [Pa]."""

    p_gas: np.ndarray
    gas_volume: np.ndarray
    chamber_pressure: np.ndarray
    damper_force: np.ndarray
    p_dead: np.ndarray


class PlantDamper:
    """The damper of ``constants`` (SI), its state equations and its outputs."""

    def __init__(self, constants: PlantConstants | None = None, ambient_k: float | None = None) -> None:
        self.k = k = constants or load_constants()
        self.gas = Nitrogen.from_constants(k)
        self.ambient_k = float(ambient_k if ambient_k is not None else k.charge_temperature)
        T0, p0 = k.charge_temperature, k.charge_pressure
        v0 = float(self.gas.molar_volume(p0, T0))
        self.n_total = k.gas_loss * ((k.geometry_gas_volume + k.transducer_dead_volume) / v0
                                     + float(oil.dissolved_equilibrium(k, p0, T0)))
        self.area = k.geometry_piston_area
        self.moving_mass = MOVING_MASS_KG

    # ----- states ------------------------------------------------------------------
    def rest_state(self, q: float = 0.0) -> np.ndarray:
        """The state at rest at stroke ``q``, everything at ambient temperature and the
        dissolved gas at equilibrium (found by bisection on the pressure)."""
        k, T = self.k, self.ambient_k
        volume = k.geometry_gas_volume - self.area * q
        lo, hi = 1e3, 1e9
        for _ in range(100):
            p = np.sqrt(lo * hi)
            v = self.gas.molar_volume(p, T)
            moles = (volume + oil.compliance_volume(k, p) + k.transducer_dead_volume) / v \
                + oil.dissolved_equilibrium(k, p, T)
            lo, hi = (p, hi) if moles < self.n_total else (lo, p)
        v = self.gas.molar_volume(p, T)
        return np.array([T, T, float(oil.dissolved_equilibrium(k, p, T)), k.transducer_dead_volume / v, T, 0.0])

    def gas_pressure(self, q, y, coefficients=None):
        """Main gas pressure [Pa] and volume [m³] at stroke q and state y (the compliance's
        fixed point contracts by ~1e-2 per pass: two passes leave 1e-6 of it)."""
        k = self.k
        T, n_diss, n_dead, void = y[0], y[2], y[3], y[5]
        coefficients = coefficients if coefficients is not None else self.gas.virial(T)
        n = self.n_total - n_diss - n_dead
        base = k.geometry_gas_volume - self.area * q - void
        volume = base
        for _ in range(2):
            p = self.gas.pressure(volume / n, T, coefficients)
            volume = base + oil.compliance_volume(k, p)
        return self.gas.pressure(volume / n, T, coefficients), volume

    def forces(self, q, velocity, y) -> Forces:
        """Pressures (absolute) and the damper force (on the piston, positive compressing) [N]."""
        k = self.k
        p, volume = self.gas_pressure(q, y)
        nu = oil.kinematic_viscosity(k, y[1])
        flow = self.area * velocity               # oil pushed up through the orifice
        dp = orifice.pressure_drop(k, flow, nu)
        cavitating = self._cavitating(p, velocity, nu, y[5])
        chamber = np.where(cavitating, k.oil_cavitation_pressure, p + np.sign(velocity) * dp)
        chamber = np.maximum(chamber, k.oil_cavitation_pressure)
        force = self.area * (chamber - P_ATM) + seals.friction(k, velocity, chamber) + self.stop_force(q)
        p_dead = self.gas.pressure(k.transducer_dead_volume / y[3], y[1])
        return Forces(p, volume, chamber, force, p_dead)

    def stop_force(self, q):
        """The end stops' contact force [N], positive compressing: the top-out stop
        pushes an over-extended piston back in, the bottom-out stop resists further
        compression; nothing between them."""
        k = self.k
        return k.stops_stiffness * (np.minimum(q - k.stops_top_out_stroke, 0.0)
                                    + np.maximum(q - k.stops_bottom_out_stroke, 0.0))

    def _cavitating(self, p, velocity, nu, void):
        q_max = orifice.max_flow(self.k, p - self.k.oil_cavitation_pressure, nu)
        return (void > 0) | (-self.area * velocity > q_max)

    def void_drive(self, q, velocity, y):
        """The rate the cavitation void would grow at [m³/s]: the oil the extending piston
        demands below it less what the orifice passes at the cavitation pressure; the
        void follows it where it is open and stays shut where it would go negative."""
        p, _ = self.gas_pressure(q, y)
        nu = oil.kinematic_viscosity(self.k, y[1])
        return -self.area * velocity - orifice.max_flow(self.k, p - self.k.oil_cavitation_pressure, nu)

    def rates(self, q, velocity, y):
        """dy/dt at stroke q [m] and stroke velocity [m/s]; y is (6,) or (6, m)."""
        k, gas = self.k, self.gas
        T, Tw, n_diss, n_dead, Ts, void = y
        virial = gas.virial(T)
        p, volume = self.gas_pressure(q, y, virial)
        n = self.n_total - n_diss - n_dead
        cond, mu_gas = gas.transport(p)
        nu = oil.kinematic_viscosity(k, Tw)
        p_dead = gas.pressure(k.transducer_dead_volume / n_dead, Tw)
        dn_dead = transducers.line_flow(k, p, p_dead, Tw, mu_gas)
        dn_diss = oil.dissolution_rate(k, p, Tw, n_diss)
        # Cavitation: while the rebound chamber holds a void its pressure is the
        # cavitation pressure and the orifice passes what that difference drives.
        demand = -self.area * velocity
        q_max = orifice.max_flow(k, p - k.oil_cavitation_pressure, nu)
        cavitating = (void > 0) | (demand > q_max)
        dvoid = np.where(cavitating, demand - q_max, 0.0)
        dvoid = np.where((void <= 0) & (dvoid < 0), 0.0, dvoid)
        through = np.where(cavitating, q_max, np.abs(demand))
        dp = np.where(cavitating, p - k.oil_cavitation_pressure, orifice.pressure_drop(k, demand, nu))
        chamber = np.where(cavitating, k.oil_cavitation_pressure, p + np.sign(velocity) * dp)
        # Gas volume rate: the piston, the void, the compliance at the spring's stiffness.
        stiff = 1 + KAPPA_COMPLIANCE * p * k.geometry_oil_volume / (k.oil_bulk_modulus * volume)
        dvolume = (-self.area * velocity - dvoid) / stiff
        dn = -dn_diss - dn_dead
        dv_molar = (dvolume - volume / n * dn) / n
        density = n * gas.molar_mass / volume
        h = heat.inside_coefficient(k, gas, p, T, density, Tw - T, velocity, (cond, mu_gas))
        q_wall = h * heat.inside_area(k, volume) * (Tw - T)
        dT = (q_wall - gas.t_dp_dt(volume / n, T, virial) * n * dv_molar) / (n * gas.cv(p))
        dissipated = dp * through + seals.friction(k, velocity, chamber) * velocity
        dTw = (-q_wall - k.heat_outside_conductance * (Tw - self.ambient_k) + dissipated) / k.heat_wall_capacity
        dTs = transducers.thermometer_rate(k, p, T, Tw, Ts)
        return np.array([dT, dTw, dn_diss, dn_dead, dTs, dvoid]) + 0 * y

    # ----- outputs -----------------------------------------------------------------
    def channels(self, q, velocity, acceleration, y, gravity: float = G0):
        """The four SI channels the DAQ digitises: measured stroke, axle force (inverse
        dynamics of the imposed stroke), the transducer's absolute pressure (the paper
        recorded gauge: subtract P_ATM to compare), the thermometer's temperature."""
        f = self.forces(q, velocity, y)
        force = self.moving_mass * (acceleration + gravity) + f.damper_force
        return np.vstack([q + 0 * velocity, force, f.p_dead, y[4] + 0 * q])


def equilibrium_pressure(plant: PlantDamper, q: float, T: float) -> float:
    """Gas pressure at rest at stroke q, gas and wall at T, dissolved gas at equilibrium."""
    saved = plant.ambient_k
    plant.ambient_k = T
    try:
        y = plant.rest_state(q)
    finally:
        plant.ambient_k = saved
    return float(plant.gas_pressure(q, y)[0])


__all__ = ["PlantDamper", "Forces", "equilibrium_pressure"]
