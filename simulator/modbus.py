"""The controller's Modbus face: a pymodbus server (TCP, or RTU on a serial device)
whose datastore is the controller's register file.

pymodbus 3.16 hands each request's raw 0-based address to the server context; the
context below maps function codes to the datasheet's tables and turns the
controller's refusals into Modbus exceptions (2 illegal address, 3 illegal value).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Sequence

from pymodbus import ModbusDeviceIdentification
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer

from simulator.controller import DEVICE_IDENTIFICATION, AddressError, RegisterError, ShakerController

UNIT_ID = 1
_READ = {1: "coils", 3: "holding", 4: "inputs"}
_WRITE = {5: "coils", 15: "coils", 6: "holding", 16: "holding", 23: "holding"}


class ControllerContext(ModbusServerContext):
    """Server context backed by a :class:`ShakerController` (unit id 1)."""

    def __init__(self, controller: ShakerController) -> None:  # noqa: D107 — no base init: it warns and copies
        self.controller = controller
        self.old_simulator = True  # tells the pymodbus server to call this context directly
        self.simdevices = []
        self._coil_echo: dict[int, bool] = {}

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
        table = _READ.get(func_code) or _WRITE.get(func_code)
        try:
            if func_code == 5:  # write-single-coil echoes the value written (alarm_reset self-clears)
                return [self._coil_echo.get(address, False)]
            if table == "coils":
                return self.controller.read_coils(address, count)
            if table == "holding":
                return self.controller.read_holding(address, count)
            if table == "inputs":
                return self.controller.read_inputs(address, count)
        except AddressError:
            return ExcCodes.ILLEGAL_ADDRESS
        return ExcCodes.ILLEGAL_ADDRESS

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: Sequence[int] | Sequence[bool]):
        table = _WRITE.get(func_code)
        try:
            if table == "coils":
                bits = [bool(v) for v in values]
                self.controller.write_coils(address, bits)
                if func_code == 5:
                    self._coil_echo[address] = bits[0]
                return None
            if table == "holding":
                self.controller.write_holding(address, [int(v) for v in values])
                return None
        except AddressError:
            return ExcCodes.ILLEGAL_ADDRESS
        except RegisterError as exc:
            self.controller.on_event(f"modbus write refused (exception 3): {exc}")
            return ExcCodes.ILLEGAL_VALUE
        return ExcCodes.ILLEGAL_FUNCTION

    def device_ids(self) -> list[int]:
        return [UNIT_ID]


def identity() -> ModbusDeviceIdentification:
    """The controller's answer to Read Device Identification (it names itself a simulator)."""
    return ModbusDeviceIdentification(info_name=DEVICE_IDENTIFICATION)


class ModbusEndpoint:
    """A pymodbus server in its own asyncio thread; can go away and come back (faults)."""

    def __init__(self, controller: ShakerController, *, host: str = "127.0.0.1", port: int = 5020,
                 serial_port: str | None = None) -> None:
        self.context = ControllerContext(controller)
        self.host, self.port, self.serial_port = host, port, serial_port
        self._loop = asyncio.new_event_loop()
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, name="modbus", daemon=True)
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    @property
    def url(self) -> str:
        return f"rtu://{self.serial_port}" if self.serial_port else f"tcp://{self.host}:{self.port}"

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()
        asyncio.run_coroutine_threadsafe(self._up(), self._loop).result(timeout=10)

    def stop(self) -> None:
        """Take the server away (clients see the link drop); :meth:`start` brings it back."""
        if self._server is not None:
            asyncio.run_coroutine_threadsafe(self._down(), self._loop).result(timeout=10)

    def close(self) -> None:
        if not self._thread.is_alive():  # never started (a rig driven in-process): nothing serves
            self._loop.close()
            return
        self.stop()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)

    async def _up(self) -> None:
        if self._server is not None:
            return
        if self.serial_port:
            self._server = ModbusSerialServer(self.context, framer=FramerType.RTU, port=self.serial_port,
                                              baudrate=115200, identity=identity())
        else:
            self._server = ModbusTcpServer(self.context, address=(self.host, self.port), identity=identity())
        await self._server.serve_forever(background=True)
        if not self.serial_port and self.port == 0:
            # pymodbus types a listener's transport as BaseTransport; a TCP one is an asyncio.Server.
            self.port = self._server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]

    async def _down(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()
