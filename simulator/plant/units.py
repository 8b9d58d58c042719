"""Production units in the plant tier: the same units as the model tier's
(:mod:`simulator.units`, same seeds, same scatter, same fault severities), carried to
the plant's physical constants.  A parameter's relative change becomes the change of the
constant behind it:

=============  ============================================================================
θ3 (orifice)   the orifice's area: θ3 ∝ 1/(Cd·A_o)², so the bore scales with factor^(−1/4)
θ5 (gas)       the nitrogen charge (moles); a leak loses gas, the charge pressure falls
θ6 (−A/V0)     the gas volume at full extension, V0 ∝ 1/θ6
θ8, θ9         the seals' preload and pressure part
=============  ============================================================================
"""

from __future__ import annotations

from identify.model import load_model
from identify.parameters import Parameters
from simulator.plant.constants import PlantConstants, load_constants
from simulator.units import unit_parameters


def unit_constants(kind: str | None, seed: int = 0, base: PlantConstants | None = None) -> PlantConstants:
    """The plant constants of production unit ``kind`` number ``seed`` (None: nominal)."""
    base = base or load_constants()
    if kind is None:
        return base
    nominal = Parameters(load_model("2dof")).as_dict()
    unit = unit_parameters(kind, seed, nominal)
    ratio = {name: unit[name] / nominal[name] for name in ("theta3", "theta5", "theta6", "theta8", "theta9")}
    return base.changed(
        orifice_diameter=base.orifice_diameter * ratio["theta3"] ** -0.25,
        gas_loss=base.gas_loss * ratio["theta5"],
        geometry_gas_volume=base.geometry_gas_volume / ratio["theta6"],
        seal_preload_force=base.seal_preload_force * ratio["theta8"],
        seal_pressure_area=base.seal_pressure_area * ratio["theta9"],
    )
