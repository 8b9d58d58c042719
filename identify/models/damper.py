"""The oleo-pneumatic damper models of ``docs/models.md`` (paper eq. 21–24).

Inputs and outputs map to the damper dataset columns: the axle force is the input,
stroke, absolute gas pressure and gas temperature are outputs; ``force_N`` as an output
is the damper force F_d, which the load cell reads in a drop test (axle on the ground).
"""

from __future__ import annotations

from identify.model import Channel, ModelDeclaration, ParameterSpec, State

STROKE = Channel("stroke_mm", "mm", scale=1e-3)
FORCE = Channel("force_N", "N")
PRESSURE = Channel("pressure_bar", "bar", scale=1e5)
TEMPERATURE = Channel("gas_temperature_C", "degC", offset=273.15)


def _parameters(gas_const: ParameterSpec, gas_exponent: ParameterSpec) -> tuple[ParameterSpec, ...]:
    return (
        ParameterSpec("theta1", "mass", "kg", 20.0, "moving mass (drop test: dropped mass)", minimum=0.0),
        ParameterSpec("theta2", "gravity", "m/s^2", 9.81, "gravitational acceleration, sign = orientation"),
        ParameterSpec("theta3", "damping", "N s^2/m^2", 5.0e3, "velocity-squared orifice damping", minimum=0.0),
        ParameterSpec("theta4", "area", "m^2", 5.0e-3, "pneumatic piston area", minimum=0.0),
        gas_const,
        ParameterSpec("theta6", "volume_slope", "1/m", -3.0, "-A/V0, relative gas volume change per metre"),
        gas_exponent,
        ParameterSpec("theta8", "friction0", "N", 80.0, "friction amplitude, constant part"),
        ParameterSpec("theta9", "friction_p", "m^2", 4.0e-5, "friction amplitude, pressure part"),
        ParameterSpec("theta10", "friction_sharpness", "s/m", 2000.0, "steepness of the arctan friction law"),
        ParameterSpec("theta11", "force_offset", "N", -506.6, "force offset (about -p_atm * area)"),
        ParameterSpec("theta12", "stroke_offset", "m", 0.0, "offset of the stroke output"),
        ParameterSpec("theta13", "unused13", "-", 0.0, "not in the paper's models; numbering kept"),
        ParameterSpec("theta14", "unused14", "-", 0.0, "not in the paper's models; numbering kept"),
        ParameterSpec("theta15", "heat_capacity", "J/K", 8.5, "gas heat capacity m*c_v", minimum=0.0),
        ParameterSpec("theta16", "heat_transfer", "W/K", 0.85, "wall heat transfer coefficient x area at q = 0",
                      minimum=0.0),
        ParameterSpec("theta17", "ambient", "K", -293.15, "minus the ambient temperature"),
    )


def _damper_force(s, p):
    """F_d = θ3·q̇|q̇| + θ4·p + (θ8 + θ9·p)·arctan(θ10·q̇) + θ11."""
    import sympy as sp  # only code generation runs this; loading a cached model does not

    return (s.theta3 * s.q_t * sp.Abs(s.q_t) + s.theta4 * p
            + (s.theta8 + s.theta9 * p) * sp.atan(s.theta10 * s.q_t) + s.theta11)


class Damper1Dof(ModelDeclaration):
    """1-dof mechanical model: polytropic gas spring (paper eq. 21–22)."""

    name = "1dof"
    description = "1-dof mechanical damper model, polytropic gas spring"
    states = (State("q", "m", 1e-3),)
    inputs = {"Fe": FORCE}
    outputs = {"stroke_mm": STROKE, "pressure_bar": PRESSURE, "force_N": FORCE}
    default_outputs = ("stroke_mm",)
    parameters = _parameters(
        ParameterSpec("theta5", "gas_const", "Pa", 6.0e5, "gas pressure at q = 0"),
        ParameterSpec("theta7", "gas_exponent", "-", 1.1, "polytropic exponent"),
    )

    @staticmethod
    def pressure(s):
        return s.theta5 * (1 + s.theta6 * s.q) ** (-s.theta7)

    def residuals(self, s):
        return [s.theta1 * (s.q_tt + s.theta2) + _damper_force(s, self.pressure(s)) - s.Fe]

    def output_equations(self, s):
        p = self.pressure(s)
        return {"stroke_mm": s.q + s.theta12, "pressure_bar": p, "force_N": _damper_force(s, p)}


class Damper2Dof(ModelDeclaration):
    """2-dof thermo-mechanical model: gas temperature as second state (paper eq. 23–24)."""

    name = "2dof"
    description = "2-dof thermo-mechanical damper model, gas energy balance"
    states = (State("q", "m", 1e-3), State("T", "K", 1.0))
    inputs = {"Fe": FORCE}
    outputs = {"stroke_mm": STROKE, "pressure_bar": PRESSURE, "gas_temperature_C": TEMPERATURE,
               "force_N": FORCE}
    default_outputs = ("stroke_mm", "pressure_bar")
    parameters = _parameters(
        ParameterSpec("theta5", "gas_const", "Pa/K", 2166.7, "n0*R/V0"),
        ParameterSpec("theta7", "gas_exponent", "1/K", 2.0e-4, "gas 'solubility'"),
    )

    @staticmethod
    def pressure(s):
        return s.theta5 * s.T / (1 + s.theta6 * s.q + s.theta7 * s.T)

    def residuals(self, s):
        p = self.pressure(s)
        g1 = s.theta1 * (s.q_tt + s.theta2) + _damper_force(s, p) - s.Fe
        g2 = (s.theta15 * s.T_t + s.theta16 * (1 + s.theta6 * s.q) * (s.T + s.theta17)
              - (s.theta4 * p + s.theta11) * s.q_t)
        return [g1, g2]

    def output_equations(self, s):
        p = self.pressure(s)
        return {"stroke_mm": s.q + s.theta12, "pressure_bar": p, "gas_temperature_C": s.T,
                "force_N": _damper_force(s, p)}

    def static_guess(self, theta):
        return {"q": 0.0, "T": -theta["theta17"]}
