"""The four-channel serial DAQ of the datasheet, byte for byte, on a pseudo-terminal
(a device path pyserial opens like a USB-serial adapter) or on TCP (``socket://``).

Idle, the DAQ answers ASCII command lines; streaming, it sends 16-byte frames paced
by the simulation clock: the rig engine asks :meth:`DaqDevice.due_times` which
samples fall in the block it just simulated and hands their ADC counts to
:meth:`DaqDevice.emit`.  A writer thread drains the DAQ's FIFO into the link; a
stalled or slow link fills the FIFO, and what does not fit is lost inside the DAQ
and flagged (bit 1), as on the hardware.

Sequence numbers restart at 0 with every START (this firmware's behaviour; a reader
that sees a first frame with sequence k counts k samples lost at the head).
``OK STOP <n>``: n counts the sequence numbers issued since START, i.e. every sample
taken, including those lost afterwards, so a reader can account for a lost tail.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import tty
from collections.abc import Callable
from typing import Protocol

import crcmod.predefined
import numpy as np

from simulator.faults import FaultLog

FRAME_DTYPE = np.dtype([("sync", "<u2"), ("seq", "<u2"), ("counts", "<i2", (4,)), ("flags", "u1"),
                        ("reserved", "u1"), ("crc", "<u2")])
SYNC = 0x5AA5  # bytes A5 5A little-endian
FLAG_OVER_RANGE, FLAG_OVERFLOW = 0x01, 0x02
RATE_MIN_HZ, RATE_MAX_HZ = 100, 5000
_CRC_TABLE = np.array(crcmod.predefined.Crc("modbus").table, dtype=np.uint16)


def crc16_modbus_rows(data: np.ndarray) -> np.ndarray:
    """CRC-16/MODBUS of each row of a (N, L) uint8 array, vectorised over rows."""
    crc = np.full(data.shape[0], 0xFFFF, dtype=np.uint16)
    for col in range(data.shape[1]):
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ data[:, col]) & 0xFF]
    return crc


def encode_frames(seq0: int, counts: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """Frames (structured array) for counts (4, N) int16 with sequence numbers from seq0."""
    n = counts.shape[1]
    frames = np.zeros(n, dtype=FRAME_DTYPE)
    frames["sync"] = SYNC
    frames["seq"] = (seq0 + np.arange(n)) & 0xFFFF
    frames["counts"] = counts.T
    frames["flags"] = flags
    raw = frames.view(np.uint8).reshape(n, 16)
    frames["crc"] = crc16_modbus_rows(raw[:, 2:14])
    return frames


class Port(Protocol):
    url: str

    def read(self, timeout_s: float) -> bytes: ...
    def write(self, data: bytes) -> None: ...
    def disconnect(self) -> None: ...
    def close(self) -> None: ...


class TcpPort:
    """A TCP listener with one client at a time (like a serial-to-Ethernet converter):
    bytes written while no client is connected go nowhere."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self._listener = socket.create_server((host, port))
        self._listener.settimeout(0.05)
        self.url = f"socket://{host}:{self._listener.getsockname()[1]}"
        self._conn: socket.socket | None = None
        self._closed = False

    def read(self, timeout_s: float) -> bytes:
        conn = self._conn
        if conn is None:
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, OSError):
                return b""
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conn = conn
        ready, _, _ = select.select([conn], [], [], timeout_s)
        if not ready:
            return b""
        try:
            data = conn.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop(conn)
        return data

    def write(self, data: bytes) -> None:
        conn = self._conn
        if conn is None:
            return
        try:
            conn.sendall(data)
        except OSError:
            self._drop(conn)

    def disconnect(self) -> None:
        if self._conn is not None:
            self._drop(self._conn)

    def _drop(self, conn: socket.socket) -> None:
        if self._conn is conn:
            self._conn = None
        try:
            conn.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        conn.close()

    def close(self) -> None:
        self.disconnect()
        self._listener.close()


class PtyPort:
    """A pseudo-terminal pair in raw mode; clients open :attr:`url` (``/dev/pts/N``).

    Both ends are set raw before any byte flows (a cooked pty mangles binary), and the
    simulator keeps the slave open itself so that a client closing and reopening the
    device does not make the master fail with EIO."""

    def __init__(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        self.url = os.ttyname(self._slave)

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self._master], [], [], timeout_s)
        return os.read(self._master, 65536) if ready else b""

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._master, view):]

    def disconnect(self) -> None:
        raise NotImplementedError("a pseudo-terminal cannot be unplugged; use the TCP DAQ for disconnects")

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class PtyBridge:
    """Two pseudo-terminals joined back to back (like ``socat pty pty``): a server opens
    :attr:`server_path`, a client :attr:`client_path`; bytes cross over in a thread."""

    def __init__(self) -> None:
        self._pairs = [os.openpty(), os.openpty()]
        for master, slave in self._pairs:
            tty.setraw(master)
            tty.setraw(slave)
        self.server_path, self.client_path = (os.ttyname(slave) for _, slave in self._pairs)
        self._running = True
        self._thread = threading.Thread(target=self._pump, name="pty-bridge", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        a, b = self._pairs[0][0], self._pairs[1][0]
        while self._running:
            ready, _, _ = select.select([a, b], [], [], 0.05)
            for fd in ready:
                data = os.read(fd, 65536)
                os.write(b if fd == a else a, data)

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=1)
        for master, slave in self._pairs:
            os.close(master)
            os.close(slave)


class DaqDevice:
    """Command interpreter, sampler bookkeeping, FIFO and link faults of the DAQ."""

    def __init__(self, port: Port, *, now: Callable[[], float], log: FaultLog, speed: float = 1.0,
                 seed: int = 0, serial: str = "SIM0001", firmware: str = "1.00") -> None:
        self.port, self._now, self._log, self.speed = port, now, log, speed
        # The fourth field says it is a simulator (a real DAQ4 answers three fields).
        self.identity = f"DAQ4,{serial},{firmware},SIMULATOR"
        self.rate_hz = 1000
        self.streaming = False
        self.corrupt_probability = 0.0
        self.drop_probability = 0.0
        self._rng = np.random.default_rng(seed + 7919)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._sent = threading.Condition(self._lock)   # the writer handed a chunk to the link
        self._sending = False                          # a chunk left the FIFO and is being written
        self._out = bytearray()
        self._t_start = 0.0
        self._next_k = 0
        self._seq = 0
        self._issued = 0
        self._overflow_pending = 0
        self._flag_overflow = False
        self._stall_until_s = -1.0
        self.lost = {"dropped": 0, "corrupted": 0, "overflow": 0}
        self._running = True
        self._threads = [threading.Thread(target=self._reader, name="daq-rx", daemon=True),
                         threading.Thread(target=self._writer, name="daq-tx", daemon=True)]

    @property
    def lost_frames(self) -> int:
        """Sequence numbers issued whose frame never reached the link intact."""
        return sum(self.lost.values())

    @property
    def fifo_capacity_bytes(self) -> int:
        # Two seconds of stream at the wall-clock frame rate: a reader hiccup is absorbed,
        # a stalled link is not.
        return max(65536, int(2 * 16 * self.rate_hz * self.speed))

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._running = False
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            t.join(timeout=2)
        self.port.close()

    # ----- faults ------------------------------------------------------------------------
    def overflow_burst(self, samples: int) -> None:
        with self._lock:
            self._overflow_pending += samples

    def stall(self, until_s: float) -> None:
        with self._lock:
            self._stall_until_s = until_s

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait until every byte emitted so far has been written to the link (or the link
        stalls); False on timeout.  For clients that drive simulated time themselves and
        must know that the stream up to now is on the line, not still in the FIFO."""
        with self._sent:
            return self._sent.wait_for(
                lambda: not self._sending and (not self._out or self._now() < self._stall_until_s), timeout_s)

    # ----- engine side -------------------------------------------------------------------
    def due_times(self, t_end: float) -> np.ndarray:
        """Simulated times of the samples due up to ``t_end`` (none while idle)."""
        with self._lock:
            if not self.streaming:
                return np.empty(0)
            k_end = int(np.floor((t_end - self._t_start) * self.rate_hz + 1e-9))
            k = np.arange(self._next_k, k_end + 1)
            self._next_k = k_end + 1
            return self._t_start + k / self.rate_hz

    def emit(self, counts: np.ndarray, over_range: np.ndarray) -> None:
        """Frames for samples returned by :meth:`due_times` (counts (4, N) int16)."""
        n = counts.shape[1]
        if n == 0:
            return
        with self._lock:
            if not self.streaming:
                return
            seq0 = self._seq
            self._seq = (self._seq + n) & 0xFFFF
            self._issued += n
            keep = np.ones(n, dtype=bool)
            if self._overflow_pending:
                lost = min(n, self._overflow_pending)
                keep[:lost] = False
                self._overflow_pending -= lost
                self.lost["overflow"] += lost
                self._flag_overflow = True
            flags = over_range.astype(np.uint8) * FLAG_OVER_RANGE
            first = int(np.argmax(keep)) if keep.any() else None
            if first is not None and self._flag_overflow:
                flags[first] |= FLAG_OVERFLOW
                self._flag_overflow = False
            frames = encode_frames(seq0, counts, flags)[keep]
            if self.drop_probability:
                dropped = self._rng.random(len(frames)) < self.drop_probability
                self.lost["dropped"] += int(dropped.sum())
                frames = frames[~dropped]
            raw = frames.view(np.uint8).reshape(-1, 16).copy()
            if self.corrupt_probability and len(raw):
                hit = self._rng.random(raw.shape) < self.corrupt_probability
                if hit.any():
                    raw[hit] ^= self._rng.integers(1, 256, int(hit.sum()), dtype=np.uint8)
                    self.lost["corrupted"] += int(hit.any(axis=1).sum())
            data = raw.tobytes()
            if len(self._out) + len(data) > self.fifo_capacity_bytes:
                self.lost["overflow"] += len(raw)
                self._flag_overflow = True
                return
            self._out += data
            self._cond.notify()

    # ----- link side ---------------------------------------------------------------------
    def _answer(self, text: str) -> None:
        # An answer may quote what was received, and that can be any bytes (a Modbus frame
        # on the wrong port, line noise): escaped, never fatal to the command thread.
        with self._cond:
            self._out += text.encode("ascii", errors="backslashreplace") + b"\n"
            self._cond.notify()

    def _handle(self, line: str) -> None:
        command = line.strip()
        if self.streaming:
            if command == "STOP":
                with self._lock:
                    self.streaming = False
                    issued = self._issued
                self._answer(f"OK STOP {issued}")
            return
        if command == "*IDN?":
            self._answer(self.identity)
        elif command.startswith("RATE"):
            parts = command.split()
            if len(parts) != 2 or not parts[1].isdigit():
                self._answer("ERR usage: RATE <hz>")
            elif not RATE_MIN_HZ <= int(parts[1]) <= RATE_MAX_HZ:
                self._answer(f"ERR rate {parts[1]} outside {RATE_MIN_HZ}..{RATE_MAX_HZ} Hz")
            else:
                self.rate_hz = int(parts[1])
                self._answer("OK")
        elif command == "START":
            with self._lock:
                self._t_start, self._next_k, self._issued, self._seq = self._now(), 1, 0, 0
                self._out += b"OK\n"
                self.streaming = True
                self._cond.notify()
        elif command == "STOP":
            self._answer("OK STOP 0")
        elif command:
            self._answer(f"ERR unknown command {command[:20]!r}")

    def _reader(self) -> None:
        pending = b""
        while self._running:
            try:
                data = self.port.read(0.05)
            except OSError:
                continue
            if not data:
                continue
            pending += data
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                self._handle(line.decode("ascii", errors="replace"))
            pending = pending[-256:]  # a command line is short; garbage does not accumulate

    def _writer(self) -> None:
        while self._running:
            with self._cond:
                while self._running and (not self._out or self._now() < self._stall_until_s):
                    self._cond.wait(timeout=0.02)
                chunk = bytes(self._out[:65536])
                del self._out[:65536]
                self._sending = bool(chunk)
            if chunk:
                try:
                    self.port.write(chunk)
                except OSError:
                    pass
                with self._sent:
                    self._sending = False
                    self._sent.notify_all()
