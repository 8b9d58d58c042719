"""Bouc-Wen hysteretic oscillator (ν = 1), a user-model example with non-smooth terms.

    m·y'' + c·y' + k·y + z = u
    z' = α·y' − βγ·|y'|·z − βδ·y'·|z|            columns: ``force_N`` (u), ``displacement_mm`` (y)

z is the hysteretic restoring force.  At rest (y' = 0) the second equation holds for
every z: a continuum of static equilibria, which the periodic start handles
(``identify/start.py``); no relaxation term is needed.  docs/user-models.md walks
through this declaration.
"""

from __future__ import annotations

from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class BoucWen(ModelDeclaration):
    name = "bouc-wen"
    description = "Bouc-Wen oscillator m y'' + c y' + k y + z = u, z' = a y' - bg |y'| z - bd y' |z|"
    # The scales are typical sizes (50 N RMS on ~1e5 N/m): Newton's step tolerance is relative to them.
    states = (State("y", "m", 1e-4), State("z", "N", 1.0))
    inputs = {"u": Channel("force_N", "N")}
    outputs = {"displacement_mm": Channel("displacement_mm", "mm", scale=1e-3)}
    default_outputs = ("displacement_mm",)
    parameters = (
        ParameterSpec("m", "mass", "kg", 2.0, "moving mass", minimum=0.0),
        ParameterSpec("c", "damping", "N s/m", 10.0, "viscous damping", minimum=0.0),
        ParameterSpec("k", "stiffness", "N/m", 5.0e4, "linear (elastic) stiffness"),
        ParameterSpec("alpha", "hysteretic_stiffness", "N/m", 5.0e4, "initial stiffness of the hysteretic force"),
        ParameterSpec("beta_gamma", "loop_shape_abs", "1/m", 800.0, "weight of |y'| z in z'"),
        ParameterSpec("beta_delta", "loop_shape_sign", "1/m", -1100.0, "weight of y' |z| in z'"),
    )

    def residuals(self, s):
        import sympy as sp  # only code generation runs this

        return [s.m * s.y_tt + s.c * s.y_t + s.k * s.y + s.z - s.u,
                s.z_t - s.alpha * s.y_t + s.beta_gamma * sp.Abs(s.y_t) * s.z + s.beta_delta * s.y_t * sp.Abs(s.z)]

    def output_equations(self, s):
        return {"displacement_mm": s.y}
