"""Vectorised parser of the DAQ's 16-byte frames (rig-interfaces.md §2).

The parser finds every sync word in the buffer, checks the CRC of all candidates at
once, keeps the valid frames (a valid frame never overlaps the previous one), and
turns sequence numbers into a running sample index, so that gaps — samples lost on
the line or inside the DAQ — are counted, never hidden.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import crcmod.predefined
import numpy as np

FRAME_BYTES = 16
SYNC0, SYNC1 = 0xA5, 0x5A
FLAG_OVER_RANGE, FLAG_OVERFLOW = 0x01, 0x02
_CRC_TABLE = np.array(crcmod.predefined.Crc("modbus").table, dtype=np.uint16)
_OFFSETS = np.arange(FRAME_BYTES)


def crc16_modbus_rows(data: np.ndarray) -> np.ndarray:
    """CRC-16/MODBUS of each row of a (N, L) uint8 array, vectorised over rows."""
    crc = np.full(data.shape[0], 0xFFFF, dtype=np.uint16)
    for col in range(data.shape[1]):
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ data[:, col]) & 0xFF]
    return crc


@dataclass
class Block:
    """Valid samples of one parse: running sample index, ADC counts (N, 4), flags."""

    index: np.ndarray
    counts: np.ndarray
    flags: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


@dataclass
class LossCounters:
    lost_samples: int = 0           # sequence gaps (line and DAQ-internal)
    overflow_flags: int = 0         # frames flagged "samples lost inside the DAQ"
    crc_errors: int = 0             # sync words whose frame failed the CRC
    over_range: int = 0             # samples with a channel over range
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (first lost index, count)


class FrameParser:
    """Stateful parser: feed it bytes, get blocks of valid samples."""

    def __init__(self) -> None:
        self._pending = np.empty(0, dtype=np.uint8)
        self._last_seq: int | None = None
        self._next_index = 0
        self.counters = LossCounters()
        self.received = 0

    @property
    def next_index(self) -> int:
        """Running index the next sample will have if nothing is lost."""
        return self._next_index

    def reset(self) -> None:
        """Start a new stream (after START): the first frame carries sequence 0."""
        self._pending = np.empty(0, dtype=np.uint8)
        self._last_seq = None
        self._next_index = 0

    def feed(self, data: bytes) -> Block:
        buf = np.concatenate((self._pending, np.frombuffer(data, dtype=np.uint8))) if len(self._pending) else \
            np.frombuffer(data, dtype=np.uint8)
        n = len(buf)
        starts = np.flatnonzero((buf[:-1] == SYNC0) & (buf[1:] == SYNC1)) if n > 1 else np.empty(0, dtype=np.int64)
        complete = starts[starts + FRAME_BYTES <= n]
        rows = buf[complete[:, None] + _OFFSETS] if len(complete) else np.empty((0, FRAME_BYTES), dtype=np.uint8)
        crc = rows[:, 14].astype(np.uint16) | (rows[:, 15].astype(np.uint16) << 8)
        ok = crc16_modbus_rows(rows[:, 2:14]) == crc
        valid = complete[ok]
        # A false sync inside a frame can pass the CRC only by chance (1 in 65536); drop
        # any valid candidate overlapping the one before it.
        if len(valid) > 1:
            keep = np.concatenate(([True], np.diff(valid) >= FRAME_BYTES))
            valid, rows_ok = valid[keep], rows[ok][keep]
        else:
            rows_ok = rows[ok]
        end = int(valid[-1]) + FRAME_BYTES if len(valid) else 0
        incomplete = starts[(starts + FRAME_BYTES > n) & (starts >= end)]
        keep_from = int(incomplete[0]) if len(incomplete) else max(end, n - 1)
        # A failed candidate is a damaged frame unless it is a sync pattern inside the
        # data of a valid frame; count each only once, when it leaves the buffer.
        failed = complete[~ok & (complete < keep_from)]
        if len(failed) and len(valid):
            j = np.searchsorted(valid, failed, side="right") - 1
            failed = failed[(j < 0) | (failed >= valid[np.maximum(j, 0)] + FRAME_BYTES)]
        self.counters.crc_errors += len(failed)
        self._pending = buf[keep_from:].copy()
        return self._block(rows_ok)

    def _block(self, rows: np.ndarray) -> Block:
        if not len(rows):
            return Block(np.empty(0, dtype=np.int64), np.empty((0, 4), dtype=np.int16), np.empty(0, dtype=np.uint8))
        seq = rows[:, 2].astype(np.int64) | (rows[:, 3].astype(np.int64) << 8)
        prev = np.concatenate(([self._last_seq if self._last_seq is not None else -1], seq[:-1]))
        step = (seq - prev) & 0xFFFF
        if self._last_seq is None:
            step[0] = seq[0] + 1  # the stream starts at sequence 0
        index = self._next_index - 1 + np.cumsum(step)
        lost = step - 1
        for i in np.flatnonzero(lost):
            self.counters.gaps.append((int(index[i] - lost[i]), int(lost[i])))
        self.counters.lost_samples += int(lost.sum())
        flags = rows[:, 12].copy()
        self.counters.overflow_flags += int(np.count_nonzero(flags & FLAG_OVERFLOW))
        self.counters.over_range += int(np.count_nonzero(flags & FLAG_OVER_RANGE))
        self._last_seq = int(seq[-1])
        self._next_index = int(index[-1]) + 1
        self.received += len(rows)
        counts = np.ascontiguousarray(rows[:, 4:12]).view("<i2").reshape(-1, 4)
        return Block(index, counts, flags)

    def account_tail(self, issued: int) -> int:
        """After ``OK STOP <issued>``: count samples lost after the last frame received."""
        tail = max(issued - self._next_index, 0)
        if tail:
            self.counters.gaps.append((self._next_index, tail))
            self.counters.lost_samples += tail
            self._next_index = issued
        return tail
