"""A damper model past the paper's 2-dof one: gas that dissolves in the oil with a delay.

The 2-dof model's "solubility" θ7 is an equilibrium: the free gas falls linearly with the
pressure at every instant (paper §6, from static stepwise tests).  Nitrogen dissolves
in oil and comes out of it over seconds to minutes (Henry's law gives the equilibrium,
not the rate; ``docs/models.md``), so a shaker cycle of 25 s sees some of it and a
drop test of 0.3 s almost none: the 2-dof model fitted at shaker speeds takes gas out
of the spring that a landing still has, and predicts a softer gear than the real one.
This model makes the dissolved gas a state:

    θ1·(q'' + θ2) + F_d(q, q', p) = Fe                                (2-dof g1)
    θ15·T' + θ16·(1 + θ6·q)·(T + θ17) = (θ4·p + θ11)·q'              (2-dof g2)
    θ18·z' = θ7·p − z                                                 (dissolution)
    p = (θ5 − z)·T / (1 + θ6·q)                                       (gas law)

with z = n_d·R/V0 the dissolved gas in the units of θ5 = n0·R/V0 (Pa/K), and θ18 the
time constant of dissolution and release.  At equilibrium z = θ7·p, which turns the gas
law into the 2-dof one, p = θ5·T / (1 + θ6·q + θ7·T): with θ18 → 0 the model is the
2-dof model exactly (``tests/test_solubility_model.py`` checks both the periodic and the
transient solution).  The heat the dissolving gas carries is left out, as in the paper.

It is declared the way any user model is (docs/user-models.md): load it with
``--model identify/models/solubility_damper.py:DamperSolubility``.  It reuses the
2-dof declaration's columns and parameters and adds one.  The nominal θ18 = 10 s has no
published source for a landing-gear damper: quiescent diffusion would take months, oil
shaken in a working damper mixes in seconds to minutes; 10 s is a start for a fit, not
a property of a unit.
"""

from __future__ import annotations

from identify.model import ModelDeclaration, ParameterSpec, State
from identify.models.damper import Damper2Dof


def _damper_force(s, p):
    """The 2-dof damper force F_d = θ3·q̇|q̇| + θ4·p + (θ8 + θ9·p)·arctan(θ10·q̇) + θ11."""
    import sympy as sp  # only code generation runs this

    return (s.theta3 * s.q_t * sp.Abs(s.q_t) + s.theta4 * p
            + (s.theta8 + s.theta9 * p) * sp.atan(s.theta10 * s.q_t) + s.theta11)


class DamperSolubility(ModelDeclaration):
    """2-dof damper plus the dissolved gas as a state with a time constant."""

    name = "2dof-solubility"
    description = "2-dof damper whose gas dissolves in the oil with a time constant"
    # z swings by θ7·(pressure swing), about 100 Pa/K over a full stroke: 0.1 is its fine scale.
    states = (State("q", "m", 1e-3), State("T", "K", 1.0), State("z", "Pa/K", 0.1))
    inputs = Damper2Dof.inputs
    outputs = Damper2Dof.outputs
    default_outputs = Damper2Dof.default_outputs
    parameters = Damper2Dof.parameters + (
        # Bounded above 0: at θ18 = 0 the dissolution equation loses its derivative (z turns
        # algebraic, which time integration cannot take); at 10 ms the gas is at equilibrium
        # on every time scale of a shaker cycle or a landing, which is the 2-dof model.
        ParameterSpec("theta18", "solubility_time", "s", 10.0, "time constant of gas dissolution and release",
                      minimum=0.01),
    )

    @staticmethod
    def pressure(s):
        return (s.theta5 - s.z) * s.T / (1 + s.theta6 * s.q)

    def residuals(self, s):
        p = self.pressure(s)
        return [s.theta1 * (s.q_tt + s.theta2) + _damper_force(s, p) - s.Fe,
                s.theta15 * s.T_t + s.theta16 * (1 + s.theta6 * s.q) * (s.T + s.theta17)
                - (s.theta4 * p + s.theta11) * s.q_t,
                s.theta18 * s.z_t - s.theta7 * p + s.z]

    def output_equations(self, s):
        p = self.pressure(s)
        return {"stroke_mm": s.q + s.theta12, "pressure_bar": p, "gas_temperature_C": s.T,
                "force_N": _damper_force(s, p)}

    def static_guess(self, theta):
        # Gas at ambient, q = 0 and the dissolved gas at its equilibrium with that pressure.
        T = -theta["theta17"]
        p = theta["theta5"] * T / (1 + theta["theta7"] * T)
        return {"q": 0.0, "T": T, "z": theta["theta7"] * p}
