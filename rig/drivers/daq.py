"""Driver of the four-channel serial DAQ (pyserial: a device path, ``socket://`` or any
pyserial URL).

A reader thread journals every byte received (append-only, flushed at least every
:data:`JOURNAL_FLUSH_S`), parses frames (:mod:`rig.drivers.frames`), converts counts with the
rig's calibration file, fills a ring buffer for live views and hands each block to
the listeners (the acquisition).  Lost samples are counted from sequence gaps and
``OK STOP <n>``; a dropped link is reopened with back-off and the stream goes on,
the gap counted as lost.
"""

from __future__ import annotations

import importlib.util
import os
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import serial

from rig.config import CHANNELS, CONFIG_DIR
from rig.drivers.frames import Block, FrameParser, LossCounters
from rig.errors import AddressError, BadInput, RigFault
from rig.events import LinkCondition, LinkNotice
from rig.tomlfile import read_toml

DEFAULT_CALIBRATION = CONFIG_DIR / "daq-calibration-datasheet.toml"
JOURNAL_FLUSH_S = 0.5
BAUDRATE = 460800
IDENTITY_PREFIX = "DAQ4,"                 # how the datasheet's DAQ begins its *IDN? answer
_STOP_ANSWER = re.compile(rb"OK STOP (\d+)\n")
# The datasheet's channel order of the frames; the dataset columns carry these names.


class SerialLine(Protocol):
    """What the driver needs of a line: pyserial's ports have it, and so do test doubles."""

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def close(self) -> None: ...


class DaqError(RigFault):
    """The DAQ did not answer as the datasheet says (names the command and the answer)."""


class CalibrationError(BadInput):
    """A calibration file that cannot be used (names the file and the channel)."""


def check_daq_address(url: str) -> None:
    """Refuse an address pyserial cannot even try: an unknown ``scheme://`` or a
    ``socket://`` without host and port.  A device path is only known once opened."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        if re.match(r"[A-Za-z][\w+.-]*:/?[^/]", url):
            # socket:/host:port or socket:host:port: a URL with its slashes mistyped, not a device path.
            raise AddressError(f"DAQ address {url!r}: not a device path nor a URL (expected a device path, "
                               "socket://HOST:PORT or another pyserial URL)")
        return
    if not scheme.isidentifier() or importlib.util.find_spec(f"serial.urlhandler.protocol_{scheme}") is None:
        raise AddressError(f"DAQ address {url!r}: unknown scheme {scheme!r} (expected a device path, "
                           "socket://HOST:PORT or another pyserial URL)")
    if scheme == "socket":
        host, _, port = rest.partition("/")[0].rpartition(":")
        if not host or not port.isdigit():
            raise AddressError(f"DAQ address {url!r}: expected socket://HOST:PORT")


def probe_daq(url: str, timeout_s: float = 1.0) -> str | None:
    """The identity a DAQ answers ``*IDN?`` with at ``url`` (a device path or pyserial
    URL); None where no DAQ answers within ``timeout_s``."""
    try:
        port = serial.serial_for_url(url, baudrate=BAUDRATE, timeout=0.05)
    except (serial.SerialException, OSError, ValueError):
        return None
    try:
        # The newline first ends whatever partial line an earlier client left behind.
        port.write(b"\n*IDN?\n")
        deadline, buf = time.monotonic() + timeout_s, b""
        while time.monotonic() < deadline:
            buf += port.read(256)
            *lines, buf = buf.split(b"\n")
            for line in lines:
                if line.startswith(IDENTITY_PREFIX.encode()):
                    return line.decode("ascii", errors="replace").strip()
    except (serial.SerialException, OSError):
        return None
    finally:
        port.close()
    return None


@dataclass(frozen=True)
class Calibration:
    """engineering = offset + gain · counts, per channel, from the rig's calibration file."""

    source: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    gain: np.ndarray
    offset: np.ndarray
    text: str = ""

    @classmethod
    def from_file(cls, path: str | Path | None = None) -> Calibration:
        path = Path(path) if path else DEFAULT_CALIBRATION
        text, doc = read_toml(path, CalibrationError, "calibration ")
        try:
            # A station's certificate file (rig.qc.calibration) holds the coefficients in its
            # [[transducer]] tables, one per channel, beside what the certificates say.
            channels = doc["transducer"] if "transducer" in doc and "channel" not in doc else doc["channel"]
            if len(channels) != len(CHANNELS):
                raise CalibrationError(f"calibration {path}: {len(channels)} channel tables, the DAQ has "
                                       f"{len(CHANNELS)}")
            names = tuple(c.get("channel", c.get("name")) or c["name"] for c in channels)
            calibration = cls(str(path), names, tuple(c.get("unit", "") for c in channels),
                              np.array([float(c["gain"]) for c in channels]),
                              np.array([float(c["offset"]) for c in channels]), text)
        except KeyError as exc:
            raise CalibrationError(f"calibration {path}: a [[channel]] lacks {exc.args[0]!r}") from None
        except (ValueError, TypeError) as exc:
            raise CalibrationError(f"calibration {path}: {exc}") from None
        # The tables are applied to the frame's channels by position: a file whose tables
        # were reordered would silently give stroke the pressure's gain and label it so.
        for i, (name, expected) in enumerate(zip(names, CHANNELS, strict=True)):
            if name != expected:
                raise CalibrationError(f"calibration {path}: [[channel]] {i + 1} is named {name!r}, but the DAQ's "
                                       f"channel {i} is {expected!r} (the order is {', '.join(CHANNELS)})")
        return calibration

    def engineering(self, counts: np.ndarray) -> np.ndarray:
        return self.offset + self.gain * counts.astype(float)


@dataclass
class Samples:
    """Calibrated samples: running index (sample number since START), values (N, 4), flags."""

    index: np.ndarray
    values: np.ndarray
    flags: np.ndarray


class RingBuffer:
    """The last ``capacity`` samples, for live views (the writer never waits on readers)."""

    def __init__(self, capacity: int) -> None:
        self.index = np.full(capacity, -1, dtype=np.int64)
        self.values = np.zeros((capacity, 4))
        self._pos = 0
        self._lock = threading.Lock()

    def append(self, index: np.ndarray, values: np.ndarray) -> None:
        n, cap = len(index), len(self.index)
        if n >= cap:
            index, values, n = index[-cap:], values[-cap:], cap
        with self._lock:
            at = (self._pos + np.arange(n)) % cap
            self.index[at], self.values[at] = index, values
            self._pos = (self._pos + n) % cap

    def latest(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``n`` most recent samples, oldest first."""
        with self._lock:
            cap = len(self.index)
            n = min(n, cap)
            at = (self._pos - n + np.arange(n)) % cap
            idx, vals = self.index[at].copy(), self.values[at].copy()
        valid = idx >= 0
        return idx[valid], vals[valid]


class Journal:
    """Append-only file of every byte received, flushed to disk at least every 0.5 s."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = open(path, "ab")
        self._last_flush = time.monotonic()

    def write(self, data: bytes) -> None:
        self._file.write(data)
        if time.monotonic() - self._last_flush >= JOURNAL_FLUSH_S:
            self.flush()

    def flush(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()

    def close(self) -> None:
        self.flush()
        self._file.close()


class Daq:
    """The DAQ: handshake, streaming with a reader thread, losses, journal, ring buffer."""

    def __init__(self, url: str, calibration: Calibration | None = None, *, rate_hz: int = 2000,
                 port: SerialLine | None = None,
                 on_event: Callable[[LinkNotice], object] = lambda notice: None, reconnect_s: float = 10.0) -> None:
        if port is None:
            check_daq_address(url)
        self.url, self.rate_hz, self.on_event, self.reconnect_s = url, rate_hz, on_event, reconnect_s
        self.calibration = calibration or Calibration.from_file()
        self.journal: Journal | None = None
        # Bytes of the handshake, kept until a journal is attached: the session folder is
        # made only once both links answer, and the journal must still begin at the first byte.
        self._unjournaled: bytearray | None = bytearray()
        self.parser = FrameParser()
        self.ring = RingBuffer(4 * 5000)
        self.identity = ""
        self.issued: int | None = None
        self._port = port
        self._listeners: list[Callable[[Samples], None]] = []
        self._thread: threading.Thread | None = None
        self._streaming = threading.Event()
        self._stop_sent = False
        self._stopped = threading.Event()
        self._tail = b""
        self.reader_error: str | None = None

    @property
    def counters(self) -> LossCounters:
        return self.parser.counters

    @property
    def _line(self) -> SerialLine:
        if self._port is None:
            raise DaqError(f"DAQ at {self.url}: not open")
        return self._port

    def attach_journal(self, path: Path) -> None:
        """Journal every byte from now on into ``path``, the handshake included."""
        self.journal = Journal(path)
        if self._unjournaled:
            self.journal.write(bytes(self._unjournaled))
        self._unjournaled = None

    def detach_journal(self) -> None:
        """Close the session's journal (the links outlive a script's session)."""
        journal, self.journal = self.journal, None
        if journal is not None:
            journal.close()

    def subscribe(self, listener: Callable[[Samples], None]) -> None:
        """Call ``listener`` from the reader thread with every calibrated block (keep it quick)."""
        self._listeners.append(listener)

    # ----- handshake ---------------------------------------------------------------------
    def open(self) -> str:
        """Open the line, stop any stream left running, identify, set the rate."""
        if self._port is None:
            self._port = self._open_port()
        try:
            self._line.write(b"STOP\n")
            self._drain(0.3)
            self.identity = self.command("*IDN?")
            while self.identity.startswith("OK STOP"):  # a late answer to the STOP above
                self.identity = self._read_line(2.0) or ""
        except (serial.SerialException, OSError) as exc:
            raise DaqError(f"DAQ at {self.url}: link lost during the handshake ({exc})") from None
        if not self.identity.startswith(IDENTITY_PREFIX):
            raise DaqError(f"DAQ at {self.url}: *IDN? answered {self.identity!r}, expected '{IDENTITY_PREFIX}…'")
        answer = self.command(f"RATE {self.rate_hz}")
        if answer != "OK":
            raise DaqError(f"DAQ at {self.url}: RATE {self.rate_hz} answered {answer!r}")
        return self.identity

    def _open_port(self) -> SerialLine:
        try:
            return serial.serial_for_url(self.url, baudrate=BAUDRATE, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DaqError(f"cannot open the DAQ at {self.url}: {exc}") from None

    def _drain(self, quiet_s: float) -> None:
        """Read and discard until the line has been quiet for ``quiet_s``."""
        last = time.monotonic()
        while time.monotonic() - last < quiet_s:
            data = self._line.read(65536)
            if data:
                self._journal(data)
                last = time.monotonic()

    def command(self, text: str, timeout_s: float = 2.0) -> str:
        """Send one command line and return its answer line.  A link that drops during
        the exchange is reopened (within the reconnect time), the DAQ brought back to
        idle with STOP, and the command sent once more."""
        try:
            return self._exchange(text, timeout_s)
        except (serial.SerialException, OSError) as exc:
            lost = exc
        if self._reopen_idle(lost):
            try:
                return self._exchange(text, timeout_s)
            except (serial.SerialException, OSError) as exc:
                lost = exc
        raise DaqError(f"DAQ at {self.url}: link lost during {text!r} and not back ({lost})")

    def _exchange(self, text: str, timeout_s: float) -> str:
        self._line.write(text.encode("ascii") + b"\n")
        line = self._read_line(timeout_s)
        if line is None:
            raise DaqError(f"DAQ at {self.url}: no answer to {text!r} within {timeout_s:g} s")
        return line

    def _reopen_idle(self, exc: Exception) -> bool:
        """Reopen the line outside a stream; True once it is open and quiet again."""
        self.on_event(LinkNotice("DAQ", LinkCondition.LOST, f"DAQ link lost ({exc}); reopening {self.url}"))
        deadline, delay = time.monotonic() + self.reconnect_s, 0.05
        while time.monotonic() < deadline:
            time.sleep(delay)
            delay = min(2 * delay, 1.0)
            try:
                self._line.close()
                self._port = self._open_port()
                self._line.write(b"STOP\n")  # a START that got through before the drop
                self._drain(0.3)
            except (DaqError, serial.SerialException, OSError):
                continue
            self.on_event(LinkNotice("DAQ", LinkCondition.BACK, "DAQ link back"))
            return True
        return False

    def _read_line(self, timeout_s: float) -> str | None:
        deadline, buf = time.monotonic() + timeout_s, b""
        while time.monotonic() < deadline:
            byte = self._line.read(1)
            self._journal(byte)
            buf += byte
            if buf.endswith(b"\n"):
                return buf[:-1].decode("ascii", errors="replace").strip()
        return None

    # ----- streaming ---------------------------------------------------------------------
    @property
    def streaming(self) -> bool:
        """START answered and the stream not stopped since (the console's DAQ line says it)."""
        return self._streaming.is_set()

    def start(self) -> None:
        """START the stream; samples are indexed from 0 at this START."""
        self.parser.reset()
        self.issued = None
        self._stop_sent = False
        self._tail = b""
        self._stopped.clear()
        answer = self.command("START")
        if answer != "OK":
            raise DaqError(f"DAQ at {self.url}: START answered {answer!r}")
        self._streaming.set()
        self._thread = threading.Thread(target=self._reader, name="daq-reader", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> int:
        """STOP the stream; returns the samples the DAQ took (lost tail counted)."""
        if not self._streaming.is_set():
            return self.issued or 0
        self._stop_sent = True
        try:
            self._line.write(b"STOP\n")
        except (serial.SerialException, OSError) as exc:
            self.on_event(LinkNotice("DAQ", LinkCondition.WARNING, f"DAQ STOP not sent: {exc}"))
        if not self._stopped.wait(timeout_s):
            self.on_event(LinkNotice("DAQ", LinkCondition.WARNING,
                                     f"DAQ at {self.url}: no 'OK STOP' within {timeout_s:g} s; tail losses unknown"))
        self._streaming.clear()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self.journal:
            self.journal.flush()
        return self.issued if self.issued is not None else self.parser.next_index

    def close(self) -> None:
        if self._streaming.is_set():
            self.stop()
        if self.journal:
            self.journal.close()
        if self._port is not None:
            self._port.close()

    def _reader(self) -> None:
        while self._streaming.is_set():
            try:
                data = self._line.read(65536)
            except (serial.SerialException, OSError) as exc:
                if not self._reopen(exc):
                    return
                continue
            if not data:
                continue
            self._journal(data)
            if self._stop_sent:
                # The answer follows the last frame; frames never contain this text.
                text = self._tail + data
                m = _STOP_ANSWER.search(text)
                if m:
                    data = data[:max(m.start() - len(self._tail), 0)]
                    self._deliver(self.parser.feed(data))
                    self.issued = int(m.group(1))
                    self.parser.account_tail(self.issued)
                    self._stopped.set()
                    return
                self._tail = text[-32:]
            self._deliver(self.parser.feed(data))

    def _journal(self, data: bytes) -> None:
        if not data:
            return
        if self.journal:
            self.journal.write(data)
        elif self._unjournaled is not None and len(self._unjournaled) < 65536:
            self._unjournaled += data

    def _reopen(self, exc: Exception) -> bool:
        self.on_event(LinkNotice("DAQ", LinkCondition.LOST, f"DAQ link lost ({exc}); reopening {self.url}"))
        deadline, delay = time.monotonic() + self.reconnect_s, 0.05
        while self._streaming.is_set() and time.monotonic() < deadline:
            time.sleep(delay)
            delay = min(2 * delay, 1.0)
            try:
                self._line.close()
                self._port = self._open_port()
                self.on_event(LinkNotice("DAQ", LinkCondition.BACK,
                                         "DAQ link back; the stream continues (the gap is counted as lost samples)"))
                return True
            except DaqError:
                continue
        self.reader_error = f"DAQ link to {self.url} lost and not back within {self.reconnect_s:g} s"
        self.on_event(LinkNotice("DAQ", LinkCondition.GONE, self.reader_error))
        self._stopped.set()
        return False

    def _deliver(self, block: Block) -> None:
        if not len(block):
            return
        values = self.calibration.engineering(block.counts)
        self.ring.append(block.index, values)
        samples = Samples(block.index, values, block.flags)
        for listener in self._listeners:
            listener(samples)
