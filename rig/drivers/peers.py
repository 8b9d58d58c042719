"""Who answered where, asked when a link did not come up: the controller's address and
the DAQ's are probed for the other box, so that a wrong or swapped address is named in
one line instead of a timeout and a library's error text.

Only reads go out (the DAQ's ``*IDN?``, the controller's state register): nothing moves.
"""

from __future__ import annotations

from urllib.parse import urlparse

from rig.drivers.daq import DaqError, probe_daq
from rig.drivers.registers import RegisterMap
from rig.drivers.shaker import ShakerAddress, ShakerLinkError, probe_controller
from rig.errors import RigError, RigFault


class WrongPeer(RigFault):
    """The other box answered at an address (the two addresses look swapped, or one is wrong)."""


def _as_serial_url(shaker_url: str) -> str:
    """The controller's address as pyserial opens it (tcp://H:P → socket://H:P, rtu:///dev/X → /dev/X)."""
    address = ShakerAddress.parse(shaker_url)
    return address.device or f"socket://{address.host}:{address.port}"


def _as_modbus_address(daq_url: str) -> ShakerAddress | None:
    """The DAQ's address as a Modbus client opens it; None for pyserial URLs Modbus has no form for."""
    if "://" not in daq_url:
        return ShakerAddress(daq_url, device=daq_url)
    parsed = urlparse(daq_url)
    if parsed.scheme == "socket" and parsed.hostname and parsed.port:
        return ShakerAddress(daq_url, host=parsed.hostname, port=parsed.port)
    return None


def name_wrong_peers(shaker_url: str, daq_url: str, register_map: RegisterMap, *,
                     controller_answered: bool = False) -> WrongPeer | None:
    """The one-line error naming what answered where, if the DAQ answers at the
    controller's address or a Modbus controller at the DAQ's; None if neither does
    (then the link's own error says best what went wrong).  ``controller_answered``:
    the controller's link came up, so its address is not probed.  Call it once both
    links are closed: a DAQ takes one client at a time."""
    daq_there = None if controller_answered else probe_daq(_as_serial_url(shaker_url))
    modbus = _as_modbus_address(daq_url)
    controller_there = probe_controller(modbus, register_map) if modbus is not None else None
    at_shaker = f"at the controller's address {shaker_url} a DAQ answered ({daq_there})"
    at_daq = f"at the DAQ's address {daq_url} {controller_there} answered"
    if daq_there and controller_there:
        return WrongPeer(f"the two addresses look swapped: {at_shaker}, {at_daq}; nothing was moved")
    if daq_there:
        return WrongPeer(f"wrong controller address: {at_shaker}, not a Modbus controller; nothing was moved")
    if controller_there:
        return WrongPeer(f"wrong DAQ address: {at_daq}, not the DAQ; nothing was moved")
    return None


def wrong_peer_or(exc: ShakerLinkError | DaqError, shaker_url: str, daq_url: str,
                  register_map: RegisterMap) -> RigError:
    """What to raise when a link did not come up: the :class:`WrongPeer` naming who
    answered where, else ``exc`` itself.  A DAQ error means the controller's link was up."""
    return name_wrong_peers(shaker_url, daq_url, register_map, controller_answered=isinstance(exc, DaqError)) or exc
