"""The simulated DAQ's command interpreter on an in-memory line: whatever bytes arrive,
it answers (ERR for what it does not know) and goes on answering, as the real one does."""

from __future__ import annotations

import threading

import pytest

from simulator.daq import DaqDevice
from simulator.faults import FaultLog
from tests.virtual_rig_inprocess import SerialLine

# A Modbus TCP write-multiple-registers request, as a controller driver sends it to the
# wrong port: bytes above 0x7F and a 0x0A in its payload end a "command line" mid-frame.
MODBUS_FRAME = bytes.fromhex("0001 0000 000b 01 10 0000 0002 04 0a ff 80 01".replace(" ", ""))


@pytest.fixture
def daq():
    line = SerialLine()
    device = DaqDevice(line.device, now=lambda: 0.0, log=FaultLog(lambda text: None))
    device.start()
    yield line.host, device
    device.close()


def answer(host, timeout_s: float = 10.0) -> bytes:
    """The next answer line; the device's threads are waited on, never slept for."""
    got = bytearray()
    done = threading.Event()

    def read() -> None:
        while not got.endswith(b"\n"):
            got.extend(host.read(1))
        done.set()
    threading.Thread(target=read, daemon=True).start()
    assert done.wait(timeout_s), f"no answer line (so far {bytes(got)!r})"
    return bytes(got)


@pytest.mark.parametrize("garbage", [bytes(range(256)).replace(b"\n", b""), "résumé ✓".encode(), MODBUS_FRAME],
                         ids=["every-byte", "utf-8", "modbus-frame"])
def test_any_bytes_get_err_and_the_daq_goes_on(daq, garbage):
    host, device = daq
    host.write(garbage + b"\n")
    assert answer(host).startswith(b"ERR unknown command")
    for tail in garbage.split(b"\n")[1:]:          # each line the garbage held is answered
        if tail.strip():
            assert answer(host).startswith(b"ERR")
    host.write(b"*IDN?\n")
    assert answer(host) == device.identity.encode() + b"\n"
    assert all(t.is_alive() for t in device._threads)
