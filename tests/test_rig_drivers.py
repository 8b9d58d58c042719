"""Drivers without the simulator: expected byte exchanges replayed (in the spirit of
PyMeasure's ``expected_protocol``), the frame parser, maps, plans and limits."""

from __future__ import annotations

import re
import socket
import struct
import subprocess
import sys
import threading

import crcmod.predefined
import numpy as np
import pytest

from rig.config import load_rig_config
from rig.drivers.daq import Daq
from rig.drivers.frames import FrameParser
from rig.drivers.registers import DEFAULT_MAP, ControllerState, RegisterMapError, load_register_map
from rig.drivers.shaker import LimitError, Shaker, ShakerError

CRC = crcmod.predefined.mkCrcFun("modbus")
LIMITS = load_rig_config().limits


class ModbusReplay:
    """A TCP peer that expects exact request bytes and answers with canned bytes."""

    def __init__(self, exchanges: list[tuple[str, str]]) -> None:
        self.exchanges = [(bytes.fromhex(a), bytes.fromhex(b)) for a, b in exchanges]
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.errors: list[str] = []
        self.done = 0
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        conn.settimeout(5)
        with conn:
            for expected, answer in self.exchanges:
                got = b""
                while len(got) < len(expected):
                    chunk = conn.recv(len(expected) - len(got))
                    if not chunk:
                        self.errors.append(f"connection closed, expected {expected.hex(' ')}")
                        return
                    got += chunk
                if got != expected:
                    self.errors.append(f"got {got.hex(' ')}, expected {expected.hex(' ')}")
                    return
                conn.sendall(answer)
                self.done += 1

    def check(self) -> None:
        self.thread.join(timeout=5)
        assert not self.errors, self.errors
        assert self.done == len(self.exchanges), f"{self.done} of {len(self.exchanges)} exchanges happened"


def test_shaker_connect_status_run_byte_exchanges():
    replay = ModbusReplay([
        # connect: FC16 stroke_limit_low..force_limit = -1000, 27000, 5000 (0.01 mm, 10 N)
        ("0001 0000 000d 01 10 0006 0003 06 fc18 6978 1388", "0001 0000 0006 01 10 0006 0003"),
        # status: FC4 input registers 0..6
        ("0002 0000 0006 01 04 0000 0007",
         "0002 0000 0011 01 04 0e 0003 0000 33f4 01f4 0000 0834 007b"),
        # run(133 mm, 10 mm, 2 Hz, sine, 2 s): FC16 waveform..ramp_time, then FC16 mode = 2
        ("0003 0000 0011 01 10 0001 0005 0a 0000 33f4 03e8 07d0 0014", "0003 0000 0006 01 10 0001 0005"),
        ("0004 0000 0009 01 10 0000 0001 02 0002", "0004 0000 0006 01 10 0000 0001"),
        # a refused write: exception 3
        ("0005 0000 0009 01 10 0000 0001 02 0001", "0005 0000 0003 01 90 03"),
    ])
    shaker = Shaker(f"tcp://127.0.0.1:{replay.port}", LIMITS, reconnect_s=0.5)
    shaker.connect(heartbeat=False)
    st = shaker.status()
    assert (st.state, st.alarm, st.cycles) == ("AT_STATIC", "none", 0)
    assert st.position_m == pytest.approx(0.133) and st.force_n == pytest.approx(5000.0)
    assert st.hydraulic_pressure_pa == pytest.approx(210e5)
    shaker.run(0.133, 0.010, 2.0, "sine", 2.0)
    with pytest.raises(ShakerError, match="illegal data value"):
        shaker.fade_out()
    shaker.close()
    replay.check()


def test_limits_refused_before_anything_is_sent():
    replay = ModbusReplay([("0001 0000 000d 01 10 0006 0003 06 fc18 6978 1388", "0001 0000 0006 01 10 0006 0003")])
    shaker = Shaker(f"tcp://127.0.0.1:{replay.port}", LIMITS, reconnect_s=0.5)
    shaker.connect(heartbeat=False)
    with pytest.raises(LimitError, match="crosses the stroke limits"):
        shaker.run(0.249, 0.030, 1.0)
    with pytest.raises(LimitError, match="flow limit"):
        shaker.run(0.133, 0.100, 2.0)
    with pytest.raises(LimitError, match="outside the stroke limits"):
        shaker.move_to(0.300)
    shaker.close()
    replay.check()  # only the connect exchange went over the wire


class ExpectedSerial:
    """A pyserial stand-in: each write must be the next expected command; its reply
    (bytes) becomes readable."""

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script, self.pending = list(script), b""
        self.errors: list[str] = []
        self.lock = threading.Lock()

    def write(self, data: bytes) -> int:
        with self.lock:
            if not self.script:
                self.errors.append(f"unexpected write {data!r}")
                return len(data)
            expected, reply = self.script.pop(0)
            if data != expected:
                self.errors.append(f"wrote {data!r}, expected {expected!r}")
            self.pending += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        with self.lock:
            out, self.pending = self.pending[:size], self.pending[size:]
        if not out:
            threading.Event().wait(0.005)
        return out

    def close(self) -> None:
        pass


def frame(seq: int, counts=(0, 0, 0, 0), flags: int = 0) -> bytes:
    body = struct.pack("<H4hBB", seq & 0xFFFF, *counts, flags, 0)
    return b"\xa5\x5a" + body + struct.pack("<H", CRC(body))


def test_daq_handshake_stream_and_losses_byte_exchange():
    frames = [frame(i, (i, -i, 2 * i, 0)) for i in range(10)]
    damaged = bytearray(frames[3])
    damaged[7] ^= 0x40                                  # CRC fails: sample 3 lost
    stream = b"".join(frames[:3]) + bytes(damaged) + b"".join(frames[4:6]) + b"".join(frames[8:9]) + \
        frame(9, flags=0x02)                            # 6, 7 lost on the line; flag: lost in the DAQ
    port = ExpectedSerial([
        (b"STOP\n", b"OK STOP 0\n"),
        (b"*IDN?\n", b"DAQ4,SN42,2.01\n"),
        (b"RATE 2000\n", b"OK\n"),
        (b"START\n", b"OK\n" + stream),
        (b"STOP\n", b"OK STOP 12\n"),                  # 10, 11 taken but never arrived
    ])
    daq = Daq("replay://", rate_hz=2000, port=port)
    assert daq.open() == "DAQ4,SN42,2.01"
    got = []
    daq.subscribe(lambda s: got.append(s))
    daq.start()
    threading.Event().wait(0.2)
    assert daq.stop() == 12
    assert not port.errors, port.errors
    index = np.concatenate([s.index for s in got])
    assert list(index) == [0, 1, 2, 4, 5, 8, 9]
    values = np.concatenate([s.values for s in got])
    assert values[1] == pytest.approx([140.005, -1.0, 32.770, 50.0])   # datasheet calibration
    c = daq.counters
    assert c.lost_samples == 5 and c.crc_errors == 1 and c.overflow_flags == 1
    assert c.gaps == [(3, 1), (6, 2), (10, 2)]


def test_frame_parser_is_independent_of_how_bytes_are_cut():
    rng = np.random.default_rng(1)
    stream = b"".join(frame(i % 65536, tuple(rng.integers(-30000, 30000, 4))) for i in range(70000))
    stream = b"\x00garbage\xa5" + stream
    whole = FrameParser()
    ref = whole.feed(stream)
    parts = FrameParser()
    cuts = np.sort(rng.integers(0, len(stream), 500))
    blocks = [parts.feed(stream[a:b]) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(stream)], strict=True)]
    index = np.concatenate([b.index for b in blocks])
    assert np.array_equal(index, ref.index) and np.array_equal(index, np.arange(70000))  # across the wrap
    assert parts.counters.lost_samples == whole.counters.lost_samples == 0
    assert np.array_equal(np.concatenate([b.counts for b in blocks]), ref.counts)


def test_register_map_errors_name_file_and_field(tmp_path):
    bad = tmp_path / "map.toml"
    bad.write_text('unit_id = 1\n[holding]\nmode = { type = "u16" }\n')
    with pytest.raises(RegisterMapError, match=r"map.toml: \[holding\] mode: needs an address"):
        load_register_map(bad)


@pytest.mark.parametrize("change, says", [
    (('"AT_STATIC"', '"AT_REST"'), r"states: 'AT_REST' is not a controller state the program knows"),
    (('"RUNNING", ', ''), r"states: lacks RUNNING$"),
    (('"OFF", "IDLE"', '"OFF", "OFF"'), r"states: OFF named twice; lacks IDLE$"),
    (("static = 1", "statik = 1"), r"modes: lacks static \(it has stop, statik, run\)$"),
    (("sine = 0, ", ""), r"waveforms: lacks sine \(it has triangle\)$"),
])
def test_a_renamed_state_or_mode_fails_at_load_in_one_line_naming_file_and_key(tmp_path, change, says):
    """The names the program acts on (ControllerState, Mode, the waveforms) are checked
    when the map is read, not when the rig first reports or is sent one."""
    text = DEFAULT_MAP.read_text()
    assert change[0] in text
    bad = tmp_path / "map.toml"
    bad.write_text(text.replace(change[0], change[1], 1))
    with pytest.raises(RegisterMapError, match=rf"^{re.escape(str(bad))}: {says}") as refused:
        load_register_map(bad)
    assert "\n" not in str(refused.value)
    assert load_register_map().states == tuple(ControllerState)    # the datasheet's map, in word order


def test_plan_breaking_a_limit_is_refused_before_anything_moves(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text("""
[[experiment]]
label = "x"
static_mm = 260
amplitude_mm = 30
frequency_Hz = 1.0

[[experiment]]
label = "y"
static_mm = 133
amplitude_mm = 100
frequency_Hz = 2.0
""")
    # Nothing listens at the shaker address: a connection attempt would fail differently.
    out = subprocess.run([sys.executable, "-m", "rig", "run", "--plan", str(plan), "--shaker", "tcp://127.0.0.1:9",
                          "--daq", "socket://127.0.0.1:9", "--out", str(tmp_path / "s")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "nothing moved" in out.stderr
    assert "experiment x: stroke 230.0…290.0 mm crosses the stroke limits" in out.stderr
    assert "experiment y: peak velocity 1.257 m/s above the hydraulic flow limit" in out.stderr
    assert not (tmp_path / "s").exists()
