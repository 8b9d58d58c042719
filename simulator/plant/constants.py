"""The plant's constants: ``constants.toml`` beside this module, each with its physical
basis and source, read into one frozen record; production units change the few a
production line scatters or a fault changes."""

from __future__ import annotations

import tomllib
from dataclasses import MISSING, dataclass, fields, replace
from pathlib import Path
from typing import Any

from simulator.errors import SimulatorError

CONSTANTS_FILE = Path(__file__).with_name("constants.toml")
R_GAS = 8.314462618  # J/(mol K), CODATA 2018
G0 = 9.81
P_ATM = 101325.0
MOVING_MASS_KG = 20.0  # the shaker's moving mass (spec theta1), not a plant constant of the damper


class PlantError(SimulatorError, ValueError):
    """Plant constants the plant cannot use (a malformed or incomplete constants file)."""


@dataclass(frozen=True)
class PlantConstants:
    """Every constant of ``constants.toml`` (SI), named ``section_key``."""

    geometry_piston_area: float
    geometry_gas_volume: float
    geometry_bore: float
    geometry_oil_volume: float
    charge_pressure: float
    charge_temperature: float
    gas_molar_mass: float
    gas_virial_T: tuple[float, ...]
    gas_virial_B: tuple[float, ...]
    gas_virial_C: tuple[float, ...]
    gas_cv_p: tuple[float, ...]
    gas_cv: tuple[float, ...]
    gas_conductivity: tuple[float, ...]
    gas_viscosity: tuple[float, ...]
    heat_natural_coefficient: float
    heat_forced_coefficient: float
    heat_forced_exponent: float
    heat_wall_capacity: float
    heat_outside_conductance: float
    oil_density: float
    oil_walther_A: float
    oil_walther_B: float
    oil_bulk_modulus: float
    oil_ostwald_20C: float
    oil_ostwald_slope: float
    oil_absorption_time: float
    oil_release_time: float
    oil_cavitation_pressure: float
    orifice_diameter: float
    orifice_length_ratio: float
    orifice_cd_turbulent: float
    seal_preload_force: float
    seal_pressure_area: float
    seal_breakaway_ratio: float
    seal_stribeck_velocity: float
    seal_coulomb_velocity: float
    seal_viscous: float
    transducer_dead_volume: float
    transducer_line_radius: float
    transducer_line_length: float
    transducer_thermometer_time: float
    transducer_thermometer_mount_time: float
    gas_loss: float = 1.0  # fraction of the charge's nitrogen left (a leaking unit has less)
    # The end stops ([stops] of constants.toml); a constants file from before them gets these.
    stops_top_out_stroke: float = 0.0
    stops_bottom_out_stroke: float = 0.30
    stops_stiffness: float = 2.0e9

    def changed(self, **values: Any) -> PlantConstants:
        return replace(self, **values)

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def load_constants(path: str | Path | None = None) -> PlantConstants:
    """The constants of ``path`` (default: the nominal plant beside this module)."""
    path = Path(path) if path else CONSTANTS_FILE
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PlantError(f"{path}: {exc}") from None
    values: dict[str, Any] = {}
    for section, entries in doc.items():
        for key, entry in entries.items():
            if not isinstance(entry, dict) or "value" not in entry or "source" not in entry:
                raise PlantError(f"{path}: [{section}.{key}] needs a value and a source")
            value = entry["value"]
            values[f"{section}_{key}"] = tuple(float(x) for x in value) if isinstance(value, list) else float(value)
    names = {f.name for f in fields(PlantConstants)} - {"gas_loss"}
    optional = {f.name for f in fields(PlantConstants) if f.default is not MISSING}
    missing, unknown = names - optional - values.keys(), values.keys() - names
    if missing or unknown:
        raise PlantError(f"{path}: missing {sorted(missing)}, unknown {sorted(unknown)}")
    return PlantConstants(**values)


def sources(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """Each constant's table (value, unit, basis, source), keyed ``section.key``."""
    doc = tomllib.loads(Path(path or CONSTANTS_FILE).read_text(encoding="utf-8"))
    return {f"{s}.{k}": e for s, entries in doc.items() for k, e in entries.items()}
