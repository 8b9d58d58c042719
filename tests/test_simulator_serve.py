"""The virtual rig seen from outside: a plain pymodbus client by the datasheet's raw
addresses, mbpoll (required under CI), and a small independent DAQ decoder (sync,
CRC-16/MODBUS, sequence) on TCP and on a pseudo-terminal.  No project code on the
client side."""

from __future__ import annotations

import math
import re
import socket
import struct
import subprocess
import time
from collections.abc import Callable
from itertools import pairwise

import crcmod.predefined
import numpy as np
import pytest
import serial
from pymodbus.client import ModbusTcpClient

from tests.conftest import HANG_S, require_program

CRC = crcmod.predefined.mkCrcFun("modbus")
OFF, IDLE, MOVING, AT_STATIC, RUNNING, ALARM = range(6)


def client(rig) -> ModbusTcpClient:
    c = ModbusTcpClient(rig.host, port=rig.port, timeout=2)
    assert c.connect()
    return c


def inputs(c: ModbusTcpClient) -> list[int]:
    return list(c.read_input_registers(0, count=7, device_id=1).registers)


def wait_state(c: ModbusTcpClient, state: int, timeout_s: float = HANG_S) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        regs = inputs(c)
        if regs[0] == state:
            return regs
        time.sleep(0.02)
    raise AssertionError(f"state {regs[0]} (alarm {regs[1]}), expected {state}")


def wait_cycles(c: ModbusTcpClient, count: int, timeout_s: float = HANG_S) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        cycles = inputs(c)[4]
        if cycles >= count:
            return cycles
        time.sleep(0.02)
    raise AssertionError(f"{cycles} cycles after {timeout_s} s, expected {count}")


def s16(word: int) -> int:
    return word - 0x10000 if word >= 0x8000 else word


def test_modbus_map_state_machine_and_cycles(virtual_rig):
    rig = virtual_rig()
    c = client(rig)
    regs = inputs(c)
    assert regs[0] == OFF and regs[1] == 0 and regs[6] == 123
    assert c.read_holding_registers(0, count=11, device_id=1).registers[6:9] == [(-1000) & 0xFFFF, 27000, 5000]
    assert not c.write_coil(0, True, device_id=1).isError()
    assert wait_state(c, IDLE)[5] == 2100  # supply 210.0 bar
    assert not c.write_register(2, 13300, device_id=1).isError()
    assert not c.write_register(0, 1, device_id=1).isError()
    assert inputs(c)[0] == MOVING
    regs = wait_state(c, AT_STATIC)
    assert abs(s16(regs[2]) - 13300) <= 2
    # sine 10 mm at 2 Hz: RUNNING, cycles count whole periods
    assert not c.write_registers(1, [0, 13300, 1000, 2000, 5], device_id=1).isError()
    assert not c.write_register(0, 2, device_id=1).isError()
    wait_state(c, RUNNING)
    read = wait_cycles(c, 50)
    assert not c.write_register(0, 1, device_id=1).isError()  # fade out
    wait_state(c, AT_STATIC)
    c.close()
    log = rig.log()
    started = float(re.search(r"\[sim t=\s*([0-9.]+) s\] RUN: sine 10.00 mm at 2 Hz about 133.00 mm", log)[1])
    m = re.search(r"\[sim t=\s*([0-9.]+) s\] fade out after (\d+) cycles", log)
    faded, counted = float(m[1]), int(m[2])
    assert read <= counted == math.floor((faded - started) * 2.0)  # whole periods of the simulated clock


def test_out_of_range_writes_get_exception_3_and_change_nothing(virtual_rig):
    rig = virtual_rig()
    c = client(rig)
    before = c.read_holding_registers(0, count=11, device_id=1).registers
    bad = [(2, [30000]),                       # static position 300 mm > 270 mm limit
           (0, [7]),                           # no such mode
           (0, [1]),                           # STATIC with hydraulics off
           (6, [27500]),                       # low limit above the high limit
           (7, [(-31000) & 0xFFFF]),           # high limit outside the actuator's travel
           ]
    for address, values in bad:
        r = c.write_registers(address, values, device_id=1)
        assert r.isError() and r.exception_code == 3, (address, values, r)
    c.write_coil(0, True, device_id=1)
    c.write_registers(1, [0, 13300, 20000, 0, 5], device_id=1)  # armed only by RUN
    r = c.write_register(0, 2, device_id=1)             # RUN: 200 mm amplitude crosses the limits
    assert r.isError() and r.exception_code == 3
    c.write_registers(3, [1000, 0], device_id=1)
    r = c.write_register(0, 2, device_id=1)             # frequency 0 in RUN
    assert r.isError() and r.exception_code == 3
    after = c.read_holding_registers(0, count=11, device_id=1).registers
    assert after[0] == before[0] == 0 and after[6:9] == before[6:9]
    assert c.read_holding_registers(11, count=1, device_id=1).exception_code == 2
    c.close()


@pytest.mark.parametrize("fault, setup, alarm", [
    ("servo-drift@2=20", None, 1),                   # stroke limit
    (None, "force", 2),                              # force limit
    ("hydraulic-loss@2", None, 3),                   # low hydraulic pressure
    (None, "watchdog", 4),                           # watchdog
    ("estop@2", None, 5),                            # emergency stop
])
def test_every_trip_is_seen_as_alarm_with_its_code(virtual_rig, fault, setup, alarm):
    rig = virtual_rig(faults=[fault] if fault else [])
    c = client(rig)
    c.write_coil(0, True, device_id=1)
    if setup == "force":
        c.write_register(8, 100, device_id=1)          # 1 kN, below the static load
    if setup == "watchdog":
        c.write_register(9, 3, device_id=1)            # 0.3 s without heartbeat
    regs = wait_state(c, ALARM)
    assert regs[1] == alarm
    # latched: stays until reset; motion stopped
    time.sleep(0.2)
    assert inputs(c)[:2] == [ALARM, alarm]
    assert c.write_register(0, 1, device_id=1).exception_code == 3  # no motion while the alarm is latched
    if alarm in (2, 4, 5):
        c.write_register(8, 5000, device_id=1)
        c.write_register(9, 0, device_id=1)
        c.write_coil(1, True, device_id=1)
        assert inputs(c)[1] == 0 and inputs(c)[0] in (OFF, IDLE)
    c.close()


def test_mbpoll_reads_the_controller(virtual_rig):
    mbpoll = require_program("mbpoll")
    rig = virtual_rig()
    out = subprocess.run([mbpoll, "-m", "tcp", "-a", "1", "-t", "3", "-r", "0", "-c", "7", "-1", "-0",
                          "-p", str(rig.port), rig.host], capture_output=True, text=True, timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr
    values = dict(line.split(":") for line in out.stdout.splitlines() if line.startswith("["))
    assert int(values["[0]"]) == OFF and int(values["[6]"]) == 123   # state, firmware
    # a write from mbpoll: hydraulics on (coil 0), then the state reads IDLE
    out = subprocess.run([mbpoll, "-m", "tcp", "-a", "1", "-t", "0", "-r", "0", "-0", "-1",
                          "-p", str(rig.port), rig.host, "1"], capture_output=True, text=True, timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr
    c = client(rig)
    wait_state(c, IDLE)
    c.close()


def frame_at(stream: bytes, i: int) -> bool:
    """A sync word at i that starts a frame whose CRC matches."""
    return stream[i:i + 2] == b"\xa5\x5a" and CRC(stream[i + 2:i + 14]) == struct.unpack("<H", stream[i + 14:i + 16])[0]


def decode(stream: bytes) -> tuple[list[int], int]:
    """Independent decoder: sequence numbers of CRC-valid frames, and bad CRCs."""
    seqs, bad, i = [], 0, 0
    while i + 16 <= len(stream):
        if stream[i] != 0xA5 or stream[i + 1] != 0x5A:
            i += 1
            continue
        frame = stream[i:i + 16]
        if CRC(frame[2:14]) != struct.unpack("<H", frame[14:16])[0]:
            bad += 1
            i += 1
            continue
        seqs.append(struct.unpack("<H", frame[2:4])[0])
        i += 16
    return seqs, bad


def exchange(port, read) -> None:
    port.write(b"*IDN?\n")
    assert read().startswith(b"DAQ4,")
    port.write(b"RATE 9000\n")
    assert read().startswith(b"ERR")
    port.write(b"RATE 2000\n")
    assert read() == b"OK\n"


def stream_once(write, read_chunk, frames: int) -> tuple[list[int], int, int]:
    """START, at least ``frames`` frames' bytes, STOP, up to the whole ``OK STOP <n>`` line."""
    write(b"START\n")
    data = b""
    deadline = time.monotonic() + HANG_S
    while len(data) < 3 + 16 * frames and time.monotonic() < deadline:
        data += read_chunk()
    write(b"STOP\n")
    while not re.search(rb"OK STOP \d+\n", data[-64:]) and time.monotonic() < deadline:
        data += read_chunk()
    assert data.startswith(b"OK\n")
    body, _, tail = data[3:].rpartition(b"OK STOP ")
    issued = int(tail.strip())
    seqs, bad = decode(body)
    return seqs, bad, issued


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_daq_stream_decoded_independently(virtual_rig, transport):
    rig = virtual_rig(daq=transport, speed=20)
    if transport == "tcp":
        host, port = rig.daq_url.removeprefix("socket://").rsplit(":", 1)
        sock = socket.create_connection((host, int(port)))
        sock.settimeout(0.05)
        f = sock.makefile("rb")

        def chunk() -> bytes:
            try:
                return sock.recv(65536)
            except TimeoutError:
                return b""
        write, readline = sock.sendall, f.readline
    else:
        port = serial.Serial(rig.daq_url, timeout=0.05)
        write, readline = port.write, port.readline

        def chunk() -> bytes:
            return port.read(65536)
    port_like = type("P", (), {"write": staticmethod(write)})
    exchange(port_like, readline)
    seqs, bad, issued = stream_once(write, chunk, 20000)
    assert bad == 0
    assert len(seqs) == issued >= 20000  # 2 kHz at 20x: about a second of wall time on an idle host
    assert seqs[0] == 0
    assert all((b - a) & 0xFFFF == 1 for a, b in pairwise(seqs))


Chunks = list[tuple[float, bytes]]


def read_stream(sock: socket.socket, enough: Callable[[Chunks], bool]) -> tuple[Chunks, bool]:
    """(arrival time, bytes) chunks until ``enough(chunks)`` holds or the link ends (the
    second item: it ended).  What is awaited is the stream's content, never a duration:
    a loaded host only makes it arrive later (:data:`HANG_S` guards a hang)."""
    chunks: Chunks = []
    deadline = time.monotonic() + HANG_S
    while not enough(chunks):
        if time.monotonic() > deadline:
            raise AssertionError(f"the stream did not have what was awaited within {HANG_S:g} s")
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        except OSError:
            return chunks, True
        if not data:
            return chunks, True
        chunks.append((time.monotonic(), data))
    return chunks, False


def frames_at_least(n: int) -> Callable[[Chunks], bool]:
    """Enough once about ``n`` frames (16 bytes each) have arrived: n / rate seconds of simulated time."""
    return lambda chunks: sum(len(d) for _, d in chunks) >= 16 * n


def daq_socket(rig) -> socket.socket:
    host, port = rig.daq_url.removeprefix("socket://").rsplit(":", 1)
    sock = socket.create_connection((host, int(port)))
    sock.settimeout(0.05)
    return sock


def test_serial_stall_delays_frames_without_losing_them(virtual_rig):
    rig = virtual_rig(faults=["stall@20=50"])           # 1 s of wall time at 50x, longer on a loaded host

    def quiet_then_back(chunks: Chunks) -> bool:         # or the frames reached past the stall's end without it
        return (len(chunks) > 1 and max(np.diff([t for t, _ in chunks])) > 0.7) or frames_at_least(70 * 500)(chunks)
    sock = daq_socket(rig)
    sock.sendall(b"RATE 500\nSTART\n")
    chunks, ended = read_stream(sock, quiet_then_back)
    assert not ended
    arrivals = [t for t, _ in chunks]
    assert max(np.diff(arrivals)) > 0.7                  # the line went quiet
    seqs, bad = decode(b"".join(d for _, d in chunks).split(b"OK\n", 2)[-1])
    assert bad == 0 and all((b - a) & 0xFFFF == 1 for a, b in pairwise(seqs))   # and nothing was lost
    sock.close()


def test_disconnect_drops_the_link_and_a_new_connection_gets_the_stream(virtual_rig):
    rig = virtual_rig(faults=["disconnect@20"])
    sock = daq_socket(rig)
    sock.sendall(b"RATE 500\nSTART\n")
    # Without the disconnect, the stream would run on past 100 s of simulated time.
    chunks, ended = read_stream(sock, frames_at_least(100 * 500))
    assert chunks and ended
    sock.close()
    again = daq_socket(rig)                              # the DAQ kept streaming meanwhile
    seqs, bad = decode(b"".join(d for _, d in read_stream(again, frames_at_least(1100))[0]))
    assert len(seqs) > 1000 and seqs[0] > 0
    again.sendall(b"STOP\n")
    again.close()
    assert "fault: DAQ link disconnected" in rig.stop()


def test_sensor_drift_moves_the_channel(virtual_rig):
    rig = virtual_rig(faults=["drift=3:0.1@30"])        # temperature channel, +0.1 degC per simulated second
    sock = daq_socket(rig)
    sock.sendall(b"RATE 500\nSTART\n")
    stream = b"".join(d for _, d in read_stream(sock, frames_at_least(100 * 500))[0]).split(b"OK\n", 1)[-1]
    sock.sendall(b"STOP\n")
    counts = []
    i = 0
    while i + 16 <= len(stream):
        if frame_at(stream, i):
            counts.append(struct.unpack("<4h", stream[i + 4:i + 12])[3])
            i += 16
        else:
            i += 1
    temperature = 50.0 + 0.005 * np.array(counts)
    assert temperature[-500:].mean() - temperature[:500].mean() > 3.0   # > 30 s of drift at 0.1 degC/s
    sock.close()


def test_modbus_rtu_on_a_pseudo_terminal(virtual_rig):
    from pymodbus.client import ModbusSerialClient
    from pymodbus.framer import FramerType

    rig = virtual_rig(modbus="rtu")
    assert rig.modbus_url.startswith("rtu:///dev/")
    c = ModbusSerialClient(rig.modbus_url.removeprefix("rtu://"), framer=FramerType.RTU, baudrate=115200, timeout=2)
    assert c.connect()
    regs = c.read_input_registers(0, count=7, device_id=1).registers
    assert regs[0] == OFF and regs[6] == 123
    assert c.write_register(2, 30000, device_id=1).exception_code == 3
    c.close()


def test_drop_rig_releases_the_mass_and_the_damper_settles(virtual_rig):
    rig = virtual_rig(rig="drop", speed=50)
    c = client(rig)
    c.write_coil(0, True, device_id=1)
    sock = daq_socket(rig)
    sock.sendall(b"RATE 200\nSTART\n")
    before, _ = read_stream(sock, frames_at_least(60))                 # 0.3 simulated seconds at rest
    assert not c.write_register(0, 2, device_id=1).isError()     # release
    after, _ = read_stream(sock, frames_at_least(130 * 200))           # 130 simulated seconds
    stream = b"".join(d for _, d in before + after).split(b"OK\n", 1)[-1]
    sock.sendall(b"STOP\n")
    sock.close()
    frames = [struct.unpack("<4h", stream[i + 4:i + 12]) for i in range(len(stream) - 15) if frame_at(stream, i)]
    counts = np.array(frames, dtype=float)
    stroke, force = 140 + 0.005 * counts[:, 0], counts[:, 1]
    temperature = 50 + 0.005 * counts[:, 3]
    assert stroke[0] == pytest.approx(0.0, abs=0.1)
    released = int(np.argmax(stroke > 1.0))
    assert stroke[released + 400] < stroke[-100:].mean() - 1.0     # 2 s after release, warm gas; cooled, it sinks
    assert force[-100:].mean() == pytest.approx(350 * 9.81, rel=0.01)   # at rest the load cell carries M·g
    assert temperature.max() > temperature[-100:].mean() + 5
    assert inputs(c)[0] in (IDLE, RUNNING)
    c.close()
