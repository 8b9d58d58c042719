"""How every screen of the console names a pressure (no Qt here): the gas's is absolute
("bar abs.", as the DAQ measures it and the dataset stores it), the hydraulic supply's is
gauge.  One place, so that no screen says "bar" for one and "bar abs." for the same."""

from __future__ import annotations

from rig.drivers.shaker import ShakerStatus

GAS_PRESSURE_UNIT = "bar abs."
SUPPLY_UNIT = "bar gauge"


def supply_text(status: ShakerStatus) -> str:
    """The hydraulic supply pressure as every screen says it."""
    return f"{status.hydraulic_pressure_pa / 1e5:.0f} {SUPPLY_UNIT}"
