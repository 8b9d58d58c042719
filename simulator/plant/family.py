"""A family of plausible plants: named variants of the nominal plant, each moving a few
constants within the brackets ``constants.toml`` gives them (``low``, ``high``), so that
a claim is measured on more than the one plant whose unsourced constants we chose.

A variant is a TOML file in ``variants/``: a ``basis`` (why this plant is plausible) and
a ``[section.key]`` table with a ``value`` for each constant it changes.  ``nominal`` is
the plant of ``constants.toml`` itself.

    from simulator.plant.family import variant_names, variant_constants
    for name in variant_names():
        k = variant_constants(name)          # PlantConstants
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from simulator.plant.constants import PlantConstants, PlantError, load_constants, sources

VARIANTS_DIR = Path(__file__).with_name("variants")
NOMINAL = "nominal"


@dataclass(frozen=True)
class Variant:
    """A named plant: the constants it changes ({``section_key``: value}) and why."""

    name: str
    basis: str
    changes: dict[str, float]


def variant_names() -> list[str]:
    """``nominal`` first, then the shipped variants in alphabetical order."""
    return [NOMINAL, *sorted(p.stem for p in VARIANTS_DIR.glob("*.toml"))]


def load_variant(name: str) -> Variant:
    """The variant ``name``, each change checked against the constant's bracket."""
    if name == NOMINAL:
        return Variant(NOMINAL, "the plant of simulator/plant/constants.toml", {})
    path = VARIANTS_DIR / f"{name}.toml"
    if not path.is_file():
        raise PlantError(f"plant variant {name!r}: unknown (known: {', '.join(variant_names())})")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PlantError(f"{path}: {exc}") from None
    basis = doc.pop("basis", None)
    if not isinstance(basis, str) or not basis.strip():
        raise PlantError(f"{path}: a variant needs a basis (why this plant is plausible)")
    table = sources()
    changes: dict[str, float] = {}
    for section, entries in doc.items():
        for key, entry in entries.items() if isinstance(entries, dict) else ():
            name_ = f"{section}.{key}"
            nominal = table.get(name_)
            if nominal is None or not isinstance(entry, dict) or "value" not in entry:
                raise PlantError(f"{path}: [{name_}] is no constant of constants.toml with a value")
            value = float(entry["value"])
            if "low" not in nominal or not nominal["low"] <= value <= nominal["high"]:
                raise PlantError(f"{path}: [{name_}] = {value:g} outside its bracket "
                                 f"{nominal.get('low', 'none')}..{nominal.get('high', 'none')}")
            changes[f"{section}_{key}"] = value
    return Variant(name, basis.strip(), changes)


def variant_constants(name: str, base: PlantConstants | None = None) -> PlantConstants:
    """The constants of variant ``name``: its changes applied to ``base`` (default nominal)."""
    return (base or load_constants()).changed(**load_variant(name).changes)


def brackets() -> dict[str, tuple[float, float, float]]:
    """(low, value, high) of every constant that has a bracket, keyed ``section.key``."""
    return {name: (float(e["low"]), float(e["value"]), float(e["high"]))
            for name, e in sources().items() if "low" in e}

