"""A Bouc-Wen damper driven by the displacement a test machine imposes (ν = 1).

    F = c·ẋ + k·x + α·z + F0
    ż = ẋ − β·|ẋ|·z − γ·ẋ·|z|

x is the imposed displacement (input ``displacement_mm``) and ẋ its time derivative,
which identify computes from the folded displacement on the periodic grid; z (in
metres) is the hysteretic displacement, F the measured force.  The loop saturates at
|z| = 1/(β + γ): α/(β + γ) is the hysteretic force's plateau.  Spencer's MR damper
model adds a second mass-less branch to this one.
"""

from identify.model import Channel, ModelDeclaration, ParameterSpec, State


class BoucWenDamper(ModelDeclaration):
    name = "bouc-wen-damper"
    description = "Bouc-Wen damper F = c x' + k x + alpha z + F0, z' = x' - beta |x'| z - gamma x' |z|"
    states = (State("z", "m", 1e-4),)
    inputs = {"x": Channel("displacement_mm", "mm", scale=1e-3)}
    outputs = {"force_N": Channel("force_N", "N")}
    default_outputs = ("force_N",)
    parameters = (
        ParameterSpec("c", "viscous", "N s/m", 500.0, "viscous coefficient", minimum=0.0),
        ParameterSpec("k", "stiffness", "N/m", 100.0, "linear stiffness (gas spring, centring)"),
        ParameterSpec("alpha", "hysteretic_stiffness", "N/m", 5.0e5, "stiffness of the hysteretic branch",
                      minimum=0.0),
        ParameterSpec("beta", "loop_shape_abs", "1/m", 5.0e3, "weight of |x'| z in z'", minimum=0.0),
        ParameterSpec("gamma", "loop_shape_sign", "1/m", 5.0e3, "weight of x' |z| in z'"),
        ParameterSpec("F0", "offset", "N", 100.0, "force offset (gas pre-load, load-cell zero)"),
    )

    def residuals(self, s):
        import sympy as sp  # only code generation runs this

        return [s.z_t - s.x_t + s.beta * sp.Abs(s.x_t) * s.z + s.gamma * s.x_t * sp.Abs(s.z)]

    def output_equations(self, s):
        return {"force_N": s.c * s.x_t + s.k * s.x + s.alpha * s.z + s.F0}
