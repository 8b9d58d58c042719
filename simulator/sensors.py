"""The four DAQ channels: transducer noise, optional gain/offset errors and drift,
16-bit quantisation with the datasheet calibration, and the over-range flag."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

COUNTS_MIN, COUNTS_MAX = -32768, 32767


@dataclass(frozen=True)
class ChannelSpec:
    """Datasheet channel: engineering = offset + gain · counts; SI = (eng + si_offset) · si_scale."""

    name: str
    unit: str
    gain: float
    offset: float
    noise_std: float  # transducer noise, engineering units
    si_scale: float = 1.0
    si_offset: float = 0.0

    def to_engineering(self, si: np.ndarray) -> np.ndarray:
        return np.asarray(si) / self.si_scale - self.si_offset


DATASHEET_CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec("stroke_mm", "mm", 0.005, 140.0, 0.01, 1e-3),
    ChannelSpec("force_N", "N", 1.0, 0.0, 2.0),
    ChannelSpec("pressure_bar", "bar", 0.001, 32.768, 0.003, 1e5),    # absolute, not gauge
    ChannelSpec("gas_temperature_C", "degC", 0.005, 50.0, 0.02, 1.0, 273.15),
)


@dataclass
class SensorSet:
    """Transducers + ADC of the four channels.  Deterministic for a given seed."""

    channels: tuple[ChannelSpec, ...] = DATASHEET_CHANNELS
    seed: int = 0
    noise_scale: float = 1.0
    gain_error: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)  # relative, per channel
    offset_error: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)  # engineering units, per channel
    drift_per_s: list[float] = field(default_factory=lambda: [0.0] * 4)  # engineering units per second
    drift_start_s: list[float] = field(default_factory=lambda: [0.0] * 4)
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def counts(self, si: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ADC counts (4, N) int16 of true SI signals (4, N), and the over-range mask (N,)."""
        out = np.empty(si.shape, dtype=np.int16)
        over = np.zeros(si.shape[1], dtype=bool)
        # One draw per sample (all channels) so that the stream does not depend on how
        # the time line is cut into blocks.
        noise = self.rng.standard_normal((si.shape[1], len(self.channels))).T
        for i, ch in enumerate(self.channels):
            eng = ch.to_engineering(si[i])
            eng = (eng * (1 + self.gain_error[i]) + self.offset_error[i]
                   + self.drift_per_s[i] * np.maximum(t - self.drift_start_s[i], 0.0))
            eng = eng + self.noise_scale * ch.noise_std * noise[i]
            raw = np.rint((eng - ch.offset) / ch.gain)
            over |= (raw < COUNTS_MIN) | (raw > COUNTS_MAX)
            out[i] = np.clip(raw, COUNTS_MIN, COUNTS_MAX)
        return out, over

    def engineering(self, counts: np.ndarray) -> np.ndarray:
        """Engineering values (4, N) of counts with the datasheet calibration."""
        return np.vstack([ch.offset + ch.gain * counts[i].astype(float) for i, ch in enumerate(self.channels)])
