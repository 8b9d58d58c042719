"""The rig's configuration: limits and capabilities, DAQ rate, steady-state criteria
(``config/rig-default.toml``; one file per rig with ``--rig-config``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from rig.errors import BadInput
from rig.registers import CONFIG_DIR
from rig.tomlfile import read_toml

DEFAULT_RIG_CONFIG = CONFIG_DIR / "rig-default.toml"


class ConfigError(BadInput):
    """A configuration file that cannot be used (names the file and the key)."""


@dataclass(frozen=True)
class Limits:
    """What the rig may do (SI)."""

    stroke_low_m: float
    stroke_high_m: float
    force_limit_n: float
    max_velocity_m_s: float
    max_frequency_hz: float
    watchdog_timeout_s: float


@dataclass(frozen=True)
class SteadyStateCriteria:
    """When a periodic experiment counts as settled (engineering units per channel)."""

    block_s: float
    thresholds: dict[str, float]
    min_cycles: int
    max_cycles: int
    max_recaptures: int
    ramp_time_s: float


@dataclass(frozen=True)
class RigConfig:
    source: str
    limits: Limits
    daq_rate_hz: int
    steady_state: SteadyStateCriteria
    reconnect_s: float = 20.0
    text: str = field(repr=False, default="")


def load_rig_config(path: str | Path | None = None) -> RigConfig:
    path = Path(path) if path else DEFAULT_RIG_CONFIG
    text, doc = read_toml(path, ConfigError)
    try:
        lim, ss = doc["limits"], doc["steady_state"]
        limits = Limits(lim["stroke_low_mm"] * 1e-3, lim["stroke_high_mm"] * 1e-3, lim["force_limit_kN"] * 1e3,
                        lim["max_velocity_m_s"], lim["max_frequency_Hz"], lim["watchdog_timeout_s"])
        thresholds = {k: float(ss[k]) for k in ("stroke_mm", "force_N", "pressure_bar", "gas_temperature_C")}
        criteria = SteadyStateCriteria(float(ss["block_s"]), thresholds, int(ss["min_cycles"]),
                                       int(ss["max_cycles"]), int(ss["max_recaptures"]), float(ss["ramp_time_s"]))
        rate = int(doc["daq"]["rate_Hz"])
        reconnect = float(doc.get("link", {}).get("reconnect_s", 20.0))
    except KeyError as exc:
        raise ConfigError(f"{path}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if limits.stroke_low_m >= limits.stroke_high_m:
        raise ConfigError(f"{path}: [limits] stroke_low_mm must be below stroke_high_mm")
    return RigConfig(str(path), limits, rate, criteria, reconnect, text)
