"""Duffing oscillator, the example of a user-declared model (Silverbox benchmark).

    m·y'' + d·y' + k·y + k2·y² + k3·y³ = u      columns: ``input`` (u), ``output`` (y), volts
"""

from __future__ import annotations

from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class Duffing(ModelDeclaration):
    name = "duffing"
    description = "Duffing oscillator m y'' + d y' + k y + k2 y^2 + k3 y^3 = u"
    states = (State("y", "V", 1e-3),)
    inputs = {"u": Channel("input", "V")}
    outputs = {"output": Channel("output", "V")}
    default_outputs = ("output",)
    parameters = (
        ParameterSpec("m", "mass", "V s^2", 1.0e-5, "inertia", minimum=0.0),
        ParameterSpec("d", "damping", "V s", 1.0e-3, "viscous damping", minimum=0.0),
        ParameterSpec("k", "stiffness", "-", 1.0, "linear stiffness"),
        ParameterSpec("k2", "quadratic", "1/V", 0.0, "quadratic stiffness"),
        ParameterSpec("k3", "cubic", "1/V^2", 0.0, "cubic stiffness"),
    )

    def residuals(self, s):
        return [s.m * s.y_tt + s.d * s.y_t + s.k * s.y + s.k2 * s.y**2 + s.k3 * s.y**3 - s.u]

    def output_equations(self, s):
        return {"output": s.y}
