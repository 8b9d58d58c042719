"""Fault injection: what can go wrong on a rig, on demand, each logged with its
simulated time.

TIME is simulated seconds since the simulator started, or ``run+T``: T simulated
seconds after the first RUN command, which lands a fault inside an experiment
however long the client took to connect and move (tests on a busy machine).

A fault is written ``KIND[@TIME][=VALUE]`` on the command line (``--fault`` may be
repeated) or built with :func:`parse_fault`:

==================  ==========================================================
``corrupt=1e-4``    each byte of the DAQ stream corrupted with this probability
``drop=1e-3``       each DAQ frame lost on the line with this probability
``overflow@T=N``    at T s, N samples lost inside the DAQ (flag bit 1 on the next frame)
``stall@T=D``       at T s the serial line stalls for D s (the DAQ FIFO fills)
``disconnect@T``    at T s the DAQ link drops (TCP: connection closed)
``modbus-down@T=D`` at T s the Modbus server goes away, back after D s
``hydraulic-loss@T[=D]`` at T s the supply pressure is lost (for D s, else for good)
``estop@T``         at T s the emergency stop is pressed
``drift=CH:RATE[@T]`` from T s, channel CH drifts by RATE engineering units per s
``gain=CH:REL[@T]`` from T s (else from the start), channel CH reads (1 + REL) times the
                    truth: a transducer whose gain drifted since its calibration (CH a
                    channel's number 0…3 or name, e.g. ``gain=force_N:0.03``)
``servo-drift@T=RATE`` from T s the servo valve's null drifts: the actuator creeps
                    away from its command at RATE mm/s (what trips the stroke limit)
==================  ==========================================================
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

from simulator.errors import SimulatorError

KINDS = ("corrupt", "drop", "overflow", "stall", "disconnect", "modbus-down", "hydraulic-loss", "estop", "drift",
         "servo-drift", "gain")
CHANNEL_NAMES = ("stroke_mm", "force_N", "pressure_bar", "gas_temperature_C")   # the DAQ's channels, in order
_TIMED = {"overflow", "stall", "disconnect", "modbus-down", "hydraulic-loss", "estop", "servo-drift"}
_TIME = r"(?:run\+)?[0-9.eE+-]+"
_SYNTAX = re.compile(rf"^(?P<kind>[a-z-]+)(?:@(?P<at>{_TIME}))?(?:=(?P<value>[^@]+))?(?:@(?P<at2>{_TIME}))?$")


class FaultError(SimulatorError, ValueError):
    """A fault specification that cannot be understood."""


@dataclass(frozen=True)
class Fault:
    kind: str
    at_s: float | None = None
    value: float | None = None
    channel: int | None = None
    after_run: bool = False   # at_s counts from the first RUN command

    def __str__(self) -> str:
        when = f"@{'run+' if self.after_run else ''}{self.at_s:g}" if self.at_s is not None else ""
        if self.kind in ("drift", "gain"):
            return f"{self.kind}={self.channel}:{self.value:g}{when}"
        return f"{self.kind}{when}" + (f"={self.value:g}" if self.value is not None else "")


def parse_fault(text: str) -> Fault:
    """``KIND[@TIME][=VALUE]`` → :class:`Fault`, with the reason when it is malformed."""
    m = _SYNTAX.match(text.strip())
    if not m or m["kind"] not in KINDS:
        raise FaultError(f"fault {text!r}: expected KIND[@TIME][=VALUE] with KIND one of {', '.join(KINDS)}")
    kind, at_text, value_text = m["kind"], m["at"] or m["at2"], m["value"]
    after_run = bool(at_text and at_text.startswith("run+"))
    try:
        at = float(at_text.removeprefix("run+")) if at_text is not None else None
        if kind in ("drift", "gain"):
            if not value_text or ":" not in value_text:
                raise FaultError(f"fault {text!r}: {kind} needs =CHANNEL:{'RATE' if kind == 'drift' else 'REL'}")
            ch, rate = value_text.split(":", 1)
            if ch not in CHANNEL_NAMES and not ch.isdigit():
                raise FaultError(f"fault {text!r}: channel {ch!r} is none of 0…3, {', '.join(CHANNEL_NAMES)}")
            channel = CHANNEL_NAMES.index(ch) if ch in CHANNEL_NAMES else int(ch)
            if not 0 <= channel <= 3:
                raise FaultError(f"fault {text!r}: channel {channel} is not 0…3")
            return Fault(kind, at, float(rate), channel, after_run)
        value = float(value_text) if value_text is not None else None
    except ValueError as exc:
        if isinstance(exc, FaultError):
            raise
        raise FaultError(f"fault {text!r}: {exc}") from None
    if kind in _TIMED and at is None:
        raise FaultError(f"fault {text!r}: {kind} needs @TIME (simulated seconds)")
    if kind in ("corrupt", "drop") and (value is None or not 0 <= value < 1):
        raise FaultError(f"fault {text!r}: {kind} needs =PROBABILITY in [0, 1)")
    if kind in ("overflow", "stall", "modbus-down") and (value is None or value <= 0):
        raise FaultError(f"fault {text!r}: {kind} needs a positive =VALUE")
    if kind == "servo-drift" and not value:
        raise FaultError(f"fault {text!r}: {kind} needs a positive =VALUE")
    return Fault(kind, at, value, None, after_run)


@dataclass
class FaultLog:
    """Every fault and trip with its simulated time; echoed to a sink (stderr by default)."""

    sink: Callable[[str], None] = field(default=lambda line: print(line, file=sys.stderr, flush=True))
    entries: list[tuple[float, str]] = field(default_factory=list)

    def record(self, t_s: float, message: str) -> None:
        self.entries.append((t_s, message))
        self.sink(f"[sim t={t_s:10.3f} s] {message}")
