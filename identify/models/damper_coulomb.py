"""A spring, a viscous dashpot and Coulomb friction in parallel, driven by the
displacement a test machine imposes.

    F = k·x + c·ẋ + z + F0
    ż = (Fc/δ)·(ẋ − |ẋ|·z/Fc)

x is the imposed displacement (input ``displacement_mm``), ẋ its time derivative, which
identify computes from the folded displacement on the periodic grid.  The friction
force z reaches ±Fc (Coulomb) once the motion has run a few pre-sliding displacements δ
in one direction: the jump sign(ẋ) at reversal, which has no periodic grid solution,
written as the seals' pre-sliding does it (Dahl's law), as docs/user-models.md asks of
jumps.  Fix δ at a fraction of the stroke or estimate it like any parameter.
"""

from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class CoulombDamper(ModelDeclaration):
    name = "coulomb-damper"
    description = "spring-viscous-Coulomb damper F = k x + c x' + z + F0, z' = (Fc/delta)(x' - |x'| z/Fc)"
    states = (State("z", "N", 10.0),)
    inputs = {"x": Channel("displacement_mm", "mm", scale=1e-3)}
    outputs = {"force_N": Channel("force_N", "N")}
    default_outputs = ("force_N",)
    parameters = (
        ParameterSpec("k", "stiffness", "N/m", 100.0, "spring stiffness"),
        ParameterSpec("c", "viscous", "N s/m", 500.0, "viscous coefficient", minimum=0.0),
        ParameterSpec("Fc", "coulomb", "N", 50.0, "Coulomb friction force", minimum=0.0),
        ParameterSpec("delta", "presliding", "m", 1.0e-4, "pre-sliding displacement of the friction",
                      minimum=0.0),
        ParameterSpec("F0", "offset", "N", 100.0, "force offset (gas pre-load, load-cell zero)"),
    )

    def residuals(self, s):
        import sympy as sp  # only code generation runs this

        return [s.delta * s.z_t - s.Fc * s.x_t + sp.Abs(s.x_t) * s.z]

    def output_equations(self, s):
        return {"force_N": s.k * s.x + s.c * s.x_t + s.z + s.F0}
