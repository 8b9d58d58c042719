"""Real-gas nitrogen: the virial equation of state in Leiden form,
p = RT/v·(1 + B(T)/v + C(T)/v²), with B and C from the sources note's table (Span et al.
2000 reference EOS), the real isochoric heat capacity, and the transport properties the
heat transfer needs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.plant.constants import R_GAS, PlantConstants


@dataclass(frozen=True)
class Nitrogen:
    """Nitrogen's properties as functions of the state (vectorised)."""

    b: np.ndarray   # B(T) = b0 + b1·x + b2·x², x = T − 300 K
    c: np.ndarray   # C(T) = c0 + c1·x
    cv_p: np.ndarray
    cv_molar: np.ndarray
    molar_mass: float
    conductivity: tuple[float, float]
    viscosity: tuple[float, float]

    @classmethod
    def from_constants(cls, k: PlantConstants) -> Nitrogen:
        x = np.asarray(k.gas_virial_T) - 300.0
        return cls(np.polyfit(x, k.gas_virial_B, 2)[::-1], np.polyfit(x, k.gas_virial_C, 1)[::-1],
                   np.asarray(k.gas_cv_p), np.asarray(k.gas_cv) * k.gas_molar_mass, k.gas_molar_mass,
                   (k.gas_conductivity[0], k.gas_conductivity[1]), (k.gas_viscosity[0], k.gas_viscosity[1]))

    def virial(self, T):
        """B, C and their temperature derivatives."""
        x = T - 300.0
        b0, b1, b2 = self.b
        c0, c1 = self.c
        return b0 + x * (b1 + x * b2), c0 + c1 * x, b1 + 2 * b2 * x, c1

    def pressure(self, v, T, coefficients=None):
        """Pressure [Pa] at molar volume ``v`` [m³/mol] and temperature ``T`` [K]
        (``coefficients``: this T's :meth:`virial`, when already at hand)."""
        B, C, _, _ = coefficients if coefficients is not None else self.virial(T)
        return R_GAS * T / v * (1 + B / v + C / v**2)

    def t_dp_dt(self, v, T, coefficients=None):
        """T·(∂p/∂T)_v: the pressure that does the work in the real gas's energy balance
        (for an ideal gas it is p)."""
        B, C, dB, dC = coefficients if coefficients is not None else self.virial(T)
        return self.pressure(v, T, (B, C, dB, dC)) + R_GAS * T**2 / v**2 * (dB + dC / v)

    def molar_volume(self, p, T, iterations: int = 30):
        """v [m³/mol] at pressure p and temperature T (fixed point of the Leiden form)."""
        B, C, _, _ = self.virial(T)
        v = R_GAS * T / p
        for _ in range(iterations):
            v = R_GAS * T / p * (1 + B / v + C / v**2)
        return v

    def compressibility(self, p, T):
        """Z = pv/(RT)."""
        return p * self.molar_volume(p, T) / (R_GAS * T)

    def cv(self, p):
        """Isochoric molar heat capacity [J/(mol K)] (the table's 300 K pressure dependence)."""
        return np.interp(p, self.cv_p, self.cv_molar)

    def transport(self, p):
        """Thermal conductivity [W/(m K)] and viscosity [Pa s], linear in p from 1 to 150 bar."""
        f = np.clip((p - 1e5) / 149e5, 0.0, 1.0)
        k0, k1 = self.conductivity
        m0, m1 = self.viscosity
        return k0 + f * (k1 - k0), m0 + f * (m1 - m0)
