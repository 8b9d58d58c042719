"""The rig's configuration: limits and capabilities, DAQ rate, steady-state criteria
(``config/rig-default.toml``; one file per rig with ``--rig-config``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from identify.move_profile import CONTROLLER_MOVE, MoveProfile
from rig.errors import BadInput
from rig.tomlfile import read_toml

# The shipped data files (register map, DAQ calibration, rig defaults) live beside this module.
CONFIG_DIR = Path(__file__).parent / "config"
DEFAULT_RIG_CONFIG = CONFIG_DIR / "rig-default.toml"
# The four channels every DAQ frame carries, in frame order (engineering units in the names).
CHANNELS = ("stroke_mm", "force_N", "pressure_bar", "gas_temperature_C")


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
class DriftCriterion:
    """The criterion's settings (``[steady_state]`` of rig-default.toml)."""

    fraction: float                  # bound on the bias, in standard deviations of the fit
    fit_cycles: int                  # block means fitted with the geometric law (the latest ones)
    max_time_constant_s: float       # slowest thermal relaxation looked for: bounds r at low frequencies
    noise: dict[str, float]          # transducer noise per sample of each fitted channel (engineering units)
    # the relaxations looked for are within this factor of the damper model's prediction
    # for the experiment (0: any up to max_time_constant_s)
    model_time_constant_factor: float = 0.0

    def time_constant_range_s(self, model_time_constant_s: float | None) -> tuple[float, float]:
        """The relaxations looked for: within the factor of the model's prediction, no
        slower than max_time_constant_s.  The fastest matters as much as the slowest: a
        large transient's first blocks decay faster than its tail (the ramp, the gas
        far from its periodic state), and a fit free to take their pace reads the tail
        as settled."""
        f = self.model_time_constant_factor
        if f > 0 and model_time_constant_s and math.isfinite(model_time_constant_s):
            return model_time_constant_s / f, min(self.max_time_constant_s, f * model_time_constant_s)
        return 0.0, self.max_time_constant_s


@dataclass(frozen=True)
class SteadyStateCriteria:
    """When a periodic experiment counts as settled (engineering units per channel).

    ``criterion``: ``change`` compares the channel means of consecutive blocks with the
    thresholds; ``drift`` bounds the bias the transient left over the capture window
    would cause in the fit (the criterion above)."""

    block_s: float
    thresholds: dict[str, float]
    min_cycles: int
    max_cycles: int
    max_recaptures: int
    ramp_time_s: float
    criterion: str = "change"
    drift: DriftCriterion | None = None


CRITERIA = ("change", "drift")


def steady_state_from_table(ss: dict, where: str, error: type[BadInput]) -> SteadyStateCriteria:
    """``[steady_state]`` of a rig configuration or a QC spec (the drift keys optional:
    without ``criterion`` the change criterion)."""
    try:
        thresholds = {k: float(ss[k]) for k in ("stroke_mm", "force_N", "pressure_bar", "gas_temperature_C")}
        criterion = str(ss.get("criterion", "change"))
        if criterion not in CRITERIA:
            raise error(f"{where}: criterion {criterion!r} is not one of {', '.join(CRITERIA)}")
        drift = None
        if criterion == "drift":
            noise = {str(k): float(v) for k, v in ss["drift_noise"].items()}
            drift = DriftCriterion(float(ss["drift_sigma_fraction"]), int(ss["drift_fit_cycles"]),
                                   float(ss["drift_max_time_constant_s"]), noise,
                                   float(ss.get("drift_model_time_constant_factor", 0.0)))
            if not (drift.fraction > 0 and drift.fit_cycles >= 4 and drift.max_time_constant_s > 0 and noise
                    and drift.model_time_constant_factor >= 0
                    and all(v > 0 for v in noise.values())):
                raise error(f"{where}: drift_sigma_fraction, drift_max_time_constant_s and every drift_noise must be "
                            "positive, drift_fit_cycles at least 4")
        return SteadyStateCriteria(float(ss["block_s"]), thresholds, int(ss["min_cycles"]), int(ss["max_cycles"]),
                                   int(ss["max_recaptures"]), float(ss["ramp_time_s"]), criterion, drift)
    except KeyError as exc:
        raise error(f"{where}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise error(f"{where}: {exc}") from None


@dataclass(frozen=True)
class RigConfig:
    source: str
    limits: Limits
    daq_rate_hz: int
    steady_state: SteadyStateCriteria
    reconnect_s: float = 20.0
    text: str = field(repr=False, default="")
    max_hold_s: float = 0.0     # longest thermal conditioning hold before an experiment (0: none)
    min_hold_s: float = 1.0     # shortest, on a link at the rig's own pace
    hold_timing_s: float = 0.0  # how early or late a hold's end is answered, in the links' seconds
    # the live traces' smallest axis span per channel, engineering units ([display]; none: autoscale)
    min_span: dict[str, float] = field(default_factory=dict)
    # the controller's move to a static position ([limits] move_speed_m_s; default its datasheet's)
    move: MoveProfile = CONTROLLER_MOVE
    # the damper's stroke envelope (full extension, bottom-out) [m] ([damper]; none: unchecked)
    stroke_envelope_m: tuple[float, float] | None = None


def _seconds(table: dict, key: str, default: float, path: Path) -> float:
    """A finite number of seconds from a table (the key named when it is not one)."""
    try:
        value = float(table.get(key, default))
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: [conditioning] {key} = {table[key]!r}: not a number of seconds") from None
    if not math.isfinite(value):
        raise ConfigError(f"{path}: [conditioning] {key} = {value}: not a finite number of seconds")
    return value


def _move_profile(limits: dict, path: Path) -> MoveProfile:
    """The controller's move from ``[limits] move_speed_m_s`` (its peak speed), where the
    rig's controller is not the datasheet's."""
    if "move_speed_m_s" not in limits:
        return CONTROLLER_MOVE
    try:
        return MoveProfile(float(limits["move_speed_m_s"]))
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: [limits] move_speed_m_s = {limits['move_speed_m_s']!r}: not a positive number "
                          f"of m/s") from None


def load_rig_config(path: str | Path | None = None) -> RigConfig:
    path = Path(path) if path else DEFAULT_RIG_CONFIG
    text, doc = read_toml(path, ConfigError)
    try:
        lim, ss = doc["limits"], doc["steady_state"]
        limits = Limits(lim["stroke_low_mm"] * 1e-3, lim["stroke_high_mm"] * 1e-3, lim["force_limit_kN"] * 1e3,
                        lim["max_velocity_m_s"], lim["max_frequency_Hz"], lim["watchdog_timeout_s"])
        criteria = steady_state_from_table(ss, f"{path}: [steady_state]", ConfigError)
        rate = int(doc["daq"]["rate_Hz"])
        reconnect = float(doc.get("link", {}).get("reconnect_s", 20.0))
        # A rig file from before conditioning existed runs as it did.
        conditioning = doc.get("conditioning", {})
        max_hold = _seconds(conditioning, "max_hold_s", 0.0, path)
        min_hold = _seconds(conditioning, "min_hold_s", 1.0, path)
        hold_timing = _seconds(conditioning, "hold_timing_s", 0.0, path)
        min_span = {str(k): float(v) for k, v in doc.get("display", {}).get("min_span", {}).items()}
        move = _move_profile(lim, path)
        damper = doc.get("damper")
        envelope = None if damper is None else (float(damper["full_extension_mm"]) * 1e-3,
                                                float(damper["bottom_out_mm"]) * 1e-3)
    except KeyError as exc:
        raise ConfigError(f"{path}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if limits.stroke_low_m >= limits.stroke_high_m:
        raise ConfigError(f"{path}: [limits] stroke_low_mm must be below stroke_high_mm")
    if max_hold < 0:
        raise ConfigError(f"{path}: [conditioning] max_hold_s = {max_hold:g}: must be 0 (no holds) or positive")
    if min_hold <= 0 or (max_hold > 0 and min_hold > max_hold):
        raise ConfigError(f"{path}: [conditioning] min_hold_s = {min_hold:g}: must be positive and at most "
                          f"max_hold_s ({max_hold:g})")
    unknown = set(min_span) - set(CHANNELS)
    if unknown or any(not (math.isfinite(v) and v > 0) for v in min_span.values()):
        raise ConfigError(f"{path}: [display] min_span: channels among {', '.join(CHANNELS)}, each a positive span"
                          + (f" ({', '.join(sorted(unknown))} is not one)" if unknown else ""))
    if hold_timing < 0:
        raise ConfigError(f"{path}: [conditioning] hold_timing_s = {hold_timing:g}: must be 0 or positive")
    if envelope is not None and not envelope[0] < envelope[1]:
        raise ConfigError(f"{path}: [damper] full_extension_mm must be below bottom_out_mm")
    return RigConfig(str(path), limits, rate, criteria, reconnect, text, max_hold, min_hold, hold_timing, min_span,
                     move, envelope)
