"""A Modbus device's register map declared as data (a TOML file), PyMeasure-style:
each field has a table, an address, a type and a scale to SI.  The driver only
speaks field names and SI values; this module turns them into register words.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from rig.config import CONFIG_DIR
from rig.errors import BadInput
from rig.tomlfile import read_toml

DEFAULT_MAP = CONFIG_DIR / "shaker-datasheet.toml"
TABLES = ("holding", "coils", "inputs")


class ControllerState(StrEnum):
    """The controller's states the program acts on, by the names a register map gives
    its ``state`` register's words (``states = [...]``, in word order)."""

    OFF = "OFF"
    IDLE = "IDLE"
    MOVING = "MOVING"
    AT_STATIC = "AT_STATIC"
    RUNNING = "RUNNING"
    ALARM = "ALARM"


class Mode(StrEnum):
    """The controller's modes the program commands (``modes = {...}``: name → word)."""

    STOP = "stop"
    STATIC = "static"
    RUN = "run"


WAVEFORMS = ("sine", "triangle")     # the waveforms a plan may ask for (``waveforms = {...}``)


class RegisterMapError(BadInput):
    """A register map file that cannot be used (names the file and the field)."""


class RegisterValueError(BadInput):
    """A value that does not fit its register (names the field, the value and the range)."""


@dataclass(frozen=True)
class Field:
    name: str
    table: str
    address: int
    type: str = "u16"
    scale: float = 1.0
    unit: str = ""

    def encode(self, value: float | bool) -> int | bool:
        """SI value → register word (or coil bit); range errors name the field."""
        if self.type == "bool":
            return bool(value)
        counts = round(float(value) / self.scale)
        low, high = (-0x8000, 0x7FFF) if self.type == "s16" else (0, 0xFFFF)
        if not low <= counts <= high:
            raise RegisterValueError(f"{self.name} = {value:g} {self.unit} does not fit a {self.type} register "
                             f"(counts {counts} outside {low}…{high})")
        return counts & 0xFFFF

    def decode(self, word: int | bool) -> float | bool:
        if self.type == "bool":
            return bool(word)
        if self.type == "s16" and word >= 0x8000:
            word -= 0x10000
        return word * self.scale if self.scale != 1.0 else int(word)


@dataclass(frozen=True)
class RegisterMap:
    """The fields of a device by table, plus its enumerations and unit id."""

    source: str
    unit_id: int
    fields: dict[str, Field]
    states: tuple[ControllerState, ...]   # by the state register's word
    alarms: tuple[str, ...]
    modes: dict[Mode, int]
    waveforms: dict[str, int]
    text: str  # the file as read, for the session's configuration snapshot

    def field(self, name: str) -> Field:
        try:
            return self.fields[name]
        except KeyError:
            raise RegisterMapError(f"{self.source}: no field {name!r} in the register map") from None

    def table(self, table: str) -> list[Field]:
        return sorted((f for f in self.fields.values() if f.table == table), key=lambda f: f.address)


def load_register_map(path: str | Path | None = None) -> RegisterMap:
    """Read a register map TOML (the datasheet's map by default)."""
    path = Path(path) if path else DEFAULT_MAP
    text, doc = read_toml(path, RegisterMapError)
    fields: dict[str, Field] = {}
    for table in TABLES:
        for name, spec in doc.get(table, {}).items():
            if not isinstance(spec, dict) or "address" not in spec:
                raise RegisterMapError(f"{path}: [{table}] {name}: needs an address")
            kind = spec.get("type", "bool" if table == "coils" else "u16")
            if kind not in ("u16", "s16", "bool"):
                raise RegisterMapError(f"{path}: [{table}] {name}: type {kind!r} is not u16, s16 or bool")
            fields[name] = Field(name, table, int(spec["address"]), kind, float(spec.get("scale", 1.0)),
                                 spec.get("unit", ""))
    required = {"mode", "waveform", "static_position", "amplitude", "frequency", "ramp_time", "stroke_limit_low",
                "stroke_limit_high", "force_limit", "watchdog_timeout", "heartbeat", "hydraulics_on", "alarm_reset",
                "state", "alarm", "position", "force", "cycles", "hydraulic_pressure"}
    missing = sorted(required - fields.keys())
    if missing:
        raise RegisterMapError(f"{path}: the map lacks {', '.join(missing)}")
    for key in ("states", "alarms", "modes", "waveforms"):
        if key not in doc:
            raise RegisterMapError(f"{path}: missing top-level key {key!r}")
    return RegisterMap(str(path), int(doc.get("unit_id", 1)), fields, _states(path, doc["states"]),
                       tuple(doc["alarms"]), _names(path, "modes", doc["modes"], Mode),
                       _names(path, "waveforms", doc["waveforms"], None), text)


def _states(path: Path, names: object) -> tuple[ControllerState, ...]:
    """The state register's words as :class:`ControllerState`: every name known, each once,
    none the program acts on missing (a renamed state fails here, not at the rig)."""
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise RegisterMapError(f"{path}: states: a list of state names in word order, e.g. {list(ControllerState)}")
    known = {s.value for s in ControllerState}
    for name in names:
        if name not in known:
            raise RegisterMapError(f"{path}: states: {name!r} is not a controller state the program knows "
                                   f"({', '.join(known)})")
    doubled = sorted({n for n in names if names.count(n) > 1})
    missing = [s.value for s in ControllerState if s.value not in names]
    if doubled or missing:
        raise RegisterMapError(f"{path}: states: " + "; ".join(
            ([f"{', '.join(doubled)} named twice"] if doubled else []) +
            ([f"lacks {', '.join(missing)}"] if missing else [])))
    return tuple(ControllerState(n) for n in names)


def _names(path: Path, key: str, table: object, enum: type[Mode] | None) -> dict:
    """A ``name = word`` table (modes, waveforms), checked for the names the program sends."""
    wanted = [m.value for m in enum] if enum is not None else list(WAVEFORMS)
    if not isinstance(table, dict) or not all(isinstance(w, int) for w in table.values()):
        raise RegisterMapError(f"{path}: {key}: a table of name = register word, e.g. {{ {wanted[0]} = 0 }}")
    missing = [n for n in wanted if n not in table]
    if missing:
        raise RegisterMapError(f"{path}: {key}: lacks {', '.join(missing)} (it has {', '.join(table) or 'none'})")
    return {enum(n) if enum is not None else n: int(w) for n, w in table.items() if n in wanted}
