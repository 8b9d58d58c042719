"""A Dahl damper driven by the displacement a test machine imposes.

    F = Kx·ẋ + Kw·w + F0
    ẇ = ρ·(ẋ − |ẋ|·w)

x is the imposed displacement (input ``displacement_mm``), ẋ its time derivative, which
identify computes from the folded displacement on the periodic grid; w is the
dimensionless hysteretic state (|w| < 1), F the measured force.  The model fitted to
the Labcontrol MR damper (tests/data/mr-damper) by Vargas et al., Sensors 22 (2022) 3644.
"""

from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class Dahl(ModelDeclaration):
    name = "dahl"
    description = "Dahl damper F = Kx x' + Kw w + F0, w' = rho (x' - |x'| w), displacement imposed"
    states = (State("w", "-", 0.1),)
    inputs = {"x": Channel("displacement_mm", "mm", scale=1e-3)}
    outputs = {"force_N": Channel("force_N", "N")}
    default_outputs = ("force_N",)
    parameters = (
        ParameterSpec("Kx", "viscous", "N s/m", 500.0, "viscous coefficient", minimum=0.0),
        ParameterSpec("Kw", "dahl_force", "N", 100.0, "hysteretic (friction) force", minimum=0.0),
        ParameterSpec("rho", "dahl_rate", "1/m", 1.0e4, "how fast w follows the motion", minimum=0.0),
        ParameterSpec("F0", "offset", "N", 100.0, "force offset (gas pre-load, load-cell zero)"),
    )

    def residuals(self, s):
        import sympy as sp  # only code generation runs this

        return [s.w_t - s.rho * (s.x_t - sp.Abs(s.x_t) * s.w)]

    def output_equations(self, s):
        return {"force_N": s.Kx * s.x_t + s.Kw * s.w + s.F0}
