"""Who answers on the links: the controller's and the DAQ's own identification.

Kept in ``session.json`` (one entry per connection: a resumed session may have been
continued elsewhere) and in every QC record.  A peer that names itself a simulator makes
the measurement a simulated one, whatever address it was reached at.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

# Modbus Read Device Identification's object ids (application protocol 6.21), as named in records
OBJECT_NAMES = {0: "vendor", 1: "product_code", 2: "revision", 3: "vendor_url", 4: "product_name",
                5: "model_name", 6: "application"}
_SIMULATOR = re.compile(r"simulat", re.IGNORECASE)


def says_simulator(text: str | None) -> bool:
    return bool(text) and _SIMULATOR.search(text or "") is not None


@dataclass(frozen=True)
class Peers:
    """``controller``: its device identification objects (empty where it offers none) and
    the firmware register; ``daq``: its ``*IDN?`` answer."""

    controller: dict[str, str]
    daq: str

    @property
    def simulated(self) -> bool:
        return says_simulator(self.daq) or any(says_simulator(v) for v in self.controller.values())

    def to_json(self) -> dict[str, Any]:
        return {"controller": dict(self.controller), "daq": self.daq, "simulated": self.simulated}

    def describe(self) -> str:
        """One line: 'controller damper-rig SIMULATOR 1.23 (firmware 1.23); DAQ DAQ4,SIM0001,1.00,SIMULATOR'."""
        c = self.controller
        named = " ".join(c[k] for k in ("vendor", "product_code", "revision") if c.get(k))
        firmware = f"firmware {c['firmware']}" if c.get("firmware") else ""
        controller = (f"{named} ({firmware})" if named and firmware else named or firmware) or "unidentified"
        return f"controller {controller}; DAQ {self.daq or 'unidentified'}"
