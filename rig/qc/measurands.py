"""Characteristics that are measurands: what is measured at the axle, under which
conditions, computed straight from the captured channels, each with its GUM uncertainty
budget.  No model is fitted for a value here: a model's error cannot move it.

A record is one captured experiment (a sine of stroke at a stated static position,
amplitude and frequency) as four channels: stroke, axle force, gas pressure, gas
temperature.  Only the cycles at full amplitude count (a transient capture's amplitude
ramp is left out), so a record captured from RUN on, while the wall still warms, is
measured as it is: the value is the mean over the captured cycles, the cycles' linear
trend (the warming) is taken out of their scatter before it counts as repeatability.

The measurands (SI inside; the spec reports them in its units):

``gas_spring_pressure``  the gas pressure where the stroke passes the stated stroke, the
                         compression and the rebound pass averaged (the transducer line's
                         lag and the gas's heat exchange cancel to first order), each
                         referred to the stated temperature by the measured gas
                         temperature (isochoric ideal gas: the volume at a stroke is fixed)
``damping_force``        the axle force where the stroke velocity passes the stated
                         velocity in the stated direction, less the gas force A·(p − p_atm)
                         at that instant, the moving mass's weight and inertia m·(g + a);
                         what remains is the orifice's force with the seal friction at that
                         velocity (the two crossings of a cycle, accelerating and braking,
                         averaged); rebound reported as a magnitude
``seal_friction``        half the jump of the axle force at each velocity reversal: the
                         force on either side extrapolated to the reversal from the sliding
                         range (stated velocities), everything else (gas, inertia, orifice)
                         continuous through it
``cycle_energy``         the energy dissipated per cycle, the work loop ∮F dq of each
                         whole captured cycle

Each value comes with the rows of its budget (:class:`BudgetRow`): repeatability over the
captured cycles (type A), each transducer's calibration (type B: the value recomputed
with the channel's gain and offset moved by their standard uncertainties,
:func:`sensitivities`), the temperature correction (gas spring), and the interpolation
or folding to the stated condition (type B: the value recomputed another way that is
equally right: a quadratic instead of a linear interpolation, another smoothing window,
another cycle phase, another extrapolation order).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from identify.dataset import Experiment

CELSIUS = 273.15
P_ATM = 101325.0           # the gauge reference of the gas force [Pa]
G = 9.80665
CHANNELS = ("stroke", "force", "pressure", "temperature")
KINDS = ("gas_spring_pressure", "damping_force", "seal_friction", "cycle_energy")
DIRECTIONS = ("compression", "rebound")
HARMONICS = 6              # of the stroke's fit: a controller's sine with its distortion
FULL_AMPLITUDE = 0.98      # a cycle counts when its stroke swing reaches this share of the last cycle's
SETTLING_CYCLES = 1        # the first full-amplitude cycles left out (still settling from the ramp)


@dataclass(frozen=True)
class Record:
    """The captured channels of one experiment, SI: time [s], stroke [m], axle force
    [N], gas pressure [Pa absolute], gas temperature [K], at the stated frequency."""

    t: np.ndarray
    stroke: np.ndarray
    force: np.ndarray
    pressure: np.ndarray
    temperature: np.ndarray
    frequency_hz: float
    # the stroke's kinematics by harmonics (kinematics()): shared by the records that differ in another channel
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_experiment(cls, exp: Experiment) -> Record:
        return cls(exp.time_s.astype(float), exp.column("stroke_mm") * 1e-3, exp.column("force_N").astype(float),
                   exp.column("pressure_bar") * 1e5, exp.column("gas_temperature_C") + CELSIUS, exp.frequency_hz)

    def calibrated(self, channel: str, gain: float = 0.0, offset: float = 0.0) -> Record:
        """The record as a transducer whose gain were off by ``gain`` (relative) and
        offset by ``offset`` (SI) would have read it."""
        x = getattr(self, channel)
        changed = replace(self, **{channel: x * (1.0 + gain) + offset})
        return replace(changed, cache={}) if channel == "stroke" else changed


@dataclass(frozen=True)
class Definition:
    """What is measured and under which conditions (SI).  ``kind`` one of :data:`KINDS`."""

    kind: str
    stroke_m: float = 0.0                 # gas_spring_pressure: where
    temperature_k: float = 293.15         # gas_spring_pressure: referred to
    velocity_m_s: float = 0.0             # damping_force: where
    direction: str = "compression"        # damping_force
    area_m2: float = 0.0                  # damping_force: the gas piston's area (drawing)
    moving_mass_kg: float = 0.0           # damping_force: the rig's moving mass above the force cell
    sliding_m_s: tuple[float, float] = (0.02, 0.12)   # seal_friction: the sliding range extrapolated from

    def describe(self, conditions: str = "") -> str:
        """The definition in words (``conditions``: the experiment's, e.g. 14 ± 20 mm, 4 Hz)."""
        at = f" of the {conditions} cycle" if conditions else ""
        if self.kind == "gas_spring_pressure":
            return (f"gas pressure where the stroke passes {self.stroke_m * 1e3:g} mm{at}, compression and rebound "
                    f"averaged, referred to {self.temperature_k - CELSIUS:g} °C by the measured gas temperature")
        if self.kind == "damping_force":
            return (f"axle force at {self.velocity_m_s:g} m/s in {self.direction}{at}, less the gas force "
                    f"A·(p − p_atm) (A = {self.area_m2 * 1e6:g} mm²) and the moving mass's weight and inertia "
                    f"({self.moving_mass_kg:g} kg): the orifice's force with the seal friction"
                    + (", as a magnitude" if self.direction == "rebound" else ""))
        if self.kind == "seal_friction":
            lo, hi = self.sliding_m_s
            return (f"half the axle force's jump at the velocity reversals{at}, each side extrapolated to the "
                    f"reversal from {lo:g}…{hi:g} m/s")
        return f"energy dissipated per cycle{at}: the work loop ∮F dq of each whole cycle"


@dataclass(frozen=True)
class BudgetRow:
    """One row of a GUM budget: where the uncertainty comes from, its evaluation type
    (A or B), the standard uncertainty it contributes to the value (SI, the value's
    unit), and how it was found."""

    source: str
    type: str
    u: float
    basis: str

    def to_json(self, scale: float = 1.0) -> dict[str, object]:
        return {"source": self.source, "type": self.type, "u": self.u / scale, "basis": self.basis}


@dataclass(frozen=True)
class Calibration:
    """The transducers' calibration as standard uncertainties (GUM type B, from their
    certificates): per channel a relative gain and an offset (SI)."""

    gain: Mapping[str, float]
    offset: Mapping[str, float]

    def rows(self) -> list[tuple[str, float, float]]:
        return [(c, float(self.gain.get(c, 0.0)), float(self.offset.get(c, 0.0))) for c in CHANNELS]


@dataclass(frozen=True)
class Value:
    """A measurand's value (SI) with its budget; ``cycles`` the number of cycles measured."""

    value: float
    rows: tuple[BudgetRow, ...]
    cycles: int

    @property
    def u(self) -> float:
        """The combined standard uncertainty: the rows in quadrature (they are independent)."""
        return math.sqrt(sum(r.u**2 for r in self.rows))


class MeasurandError(ValueError):
    """A record that does not hold what a measurand needs (too few cycles, no crossing)."""


# ---- the record's kinematics ------------------------------------------------------------------
def kinematics(record: Record, harmonics: int = HARMONICS) -> tuple[np.ndarray, np.ndarray]:
    """Stroke velocity and acceleration [m/s, m/s²] in the full-amplitude cycles (NaN
    outside them), each cycle's from a least-squares fit of the stroke over the cycle and
    a quarter period either side (within the full cycles): a linear drift and ``harmonics`` harmonics of the
    stated frequency.  Differentiated raw, the stroke's noise would swamp the velocity
    points (0.01 mm at 2 kHz is 0.01 m/s, and 1 m/s² of acceleration); fitted cycle by
    cycle, the fit follows what a controller's stroke still does after its ramp (its
    mean settling, its amplitude) where one fit over the record would smear it."""
    if harmonics in record.cache:
        return record.cache[harmonics]
    period = 1.0 / record.frequency_hz
    w = 2 * np.pi * record.frequency_hz
    v, a = np.full(len(record.t), np.nan), np.full(len(record.t), np.nan)
    starts = full_cycles(record)
    for start in starts:
        # a quarter period either side, within the full cycles (the ramp would bend the first cycle's fit)
        lo, hi = max(start - period / 4, starts[0]), min(start + 1.25 * period, starts[-1] + period)
        fit = (record.t >= lo - 1e-9) & (record.t < hi - 1e-9)
        own = (record.t >= start - 1e-9) & (record.t < start + period - 1e-9)
        tau = record.t - (start + period / 2)
        cols = [[np.ones_like(tau), np.zeros_like(tau), np.zeros_like(tau)], [tau, np.ones_like(tau), 0 * tau]]
        for k in range(1, harmonics + 1):
            c, s_ = np.cos(k * w * tau), np.sin(k * w * tau)
            kw = k * w
            cols += [[c, -kw * s_, -kw**2 * c], [s_, kw * c, -kw**2 * s_]]
        D = np.column_stack([col[0][fit] for col in cols])
        coef = np.linalg.solve(D.T @ D, D.T @ record.stroke[fit])    # normal equations: well conditioned here
        v[own] = np.column_stack([col[1][own] for col in cols]) @ coef
        a[own] = np.column_stack([col[2][own] for col in cols]) @ coef
    record.cache[harmonics] = (v, a)
    return v, a


def full_cycles(record: Record) -> np.ndarray:
    """The start times of the whole cycles at full amplitude, counted back from the
    record's end, oldest first: the ramp of a transient capture and the first cycle after
    it left out."""
    period = 1.0 / record.frequency_hz
    t, q = record.t, record.stroke
    starts = []
    end = t[-1] + 0.5 * float(np.median(np.diff(t)))
    last = None
    while end - period >= t[0] - 1e-9:
        sel = (t >= end - period - 1e-9) & (t < end - 1e-9)
        swing = float(np.ptp(q[sel]))
        if last is None:
            last = swing
        elif swing < FULL_AMPLITUDE * last:
            break
        starts.append(end - period)
        end -= period
    # The first cycle at full amplitude still settles from the ramp (a controller's stroke
    # mean, the damper's own transient: 2 % off in the damping on the served plant): left out.
    return np.array(starts[::-1][SETTLING_CYCLES:] if len(starts) > SETTLING_CYCLES + 1 else starts[::-1])


def _cycle_of(times: np.ndarray, starts: np.ndarray, period: float) -> np.ndarray:
    """The index of the full cycle each time lies in, −1 outside them."""
    if not len(starts):
        return np.full(len(times), -1)
    j = np.floor((times - starts[0]) / period).astype(int)
    return np.where((j >= 0) & (j < len(starts)), j, -1)


def _crossings(x: np.ndarray, level: float, rising: bool | None) -> np.ndarray:
    """Indices i where x passes ``level`` between samples i and i+1 (rising, falling or both)."""
    a, b = x[:-1] - level, x[1:] - level     # NaN (outside the full cycles) crosses nothing
    up, down = (a < 0) & (b >= 0), (a > 0) & (b <= 0)
    return np.flatnonzero(up if rising is True else down if rising is False else up | down)


def _at(y: np.ndarray, x: np.ndarray, i: np.ndarray, level: float, quadratic: bool = False) -> np.ndarray:
    """y where x passes ``level`` between samples i and i+1: linear interpolation, or a
    quadratic through i−1, i, i+1, i+2 fitted by least squares (the interpolation row)."""
    frac = (level - x[i]) / (x[i + 1] - x[i])
    if not quadratic:
        return y[i] + frac * (y[i + 1] - y[i])
    k = np.clip(i, 1, len(y) - 3)
    s = frac + (i - k)                    # the crossing's place from sample k, in samples
    offs = np.array([-1.0, 0.0, 1.0, 2.0])
    V = np.vander(offs, 3, increasing=True)
    coef = np.linalg.lstsq(V, y[k[:, None] + offs.astype(int)].T, rcond=None)[0]
    return coef[0] + coef[1] * s + coef[2] * s**2


def _per_cycle(values: np.ndarray, cycle: np.ndarray, n: int) -> np.ndarray:
    """The mean of the events of each full cycle (NaN for a cycle without one)."""
    keep = cycle >= 0
    sums = np.bincount(cycle[keep], weights=values[keep], minlength=n)
    counts = np.bincount(cycle[keep], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


# ---- the measurands, each per cycle -----------------------------------------------------------
def per_cycle(d: Definition, record: Record, variant: str = "") -> np.ndarray:
    """The measurand of each full-amplitude cycle (SI).  ``variant`` computes it the
    other, equally right, way the interpolation/folding row compares against."""
    starts = full_cycles(record)
    period = 1.0 / record.frequency_hz
    if d.kind == "gas_spring_pressure":
        i = _crossings(record.stroke, d.stroke_m, None)
        quad = variant == "other"
        p = _at(record.pressure, record.stroke, i, d.stroke_m, quad)
        temp = _at(record.temperature, record.stroke, i, d.stroke_m, quad)
        t = _at(record.t, record.stroke, i, d.stroke_m)
        return _per_cycle(p * d.temperature_k / temp, _cycle_of(t, starts, period), len(starts))
    if d.kind == "damping_force":
        v, a = kinematics(record, HARMONICS + 2 if variant == "other" else HARMONICS)
        sign = 1.0 if d.direction == "compression" else -1.0
        level = sign * d.velocity_m_s
        i = _crossings(v, level, None)
        residual = (record.force - d.area_m2 * (record.pressure - P_ATM) - d.moving_mass_kg * (G + a))
        r, t = _at(residual, v, i, level), _at(record.t, v, i, level)
        return _per_cycle(sign * r, _cycle_of(t, starts, period), len(starts))
    if d.kind == "seal_friction":
        return _friction(d, record, starts, period, 3 if variant == "other" else 2)
    if d.kind == "cycle_energy":
        shift = 0.5 * period if variant == "other" else 0.0
        return _loops(record, starts + shift if shift else starts, period)
    raise MeasurandError(f"unknown measurand kind {d.kind!r} (kinds: {', '.join(KINDS)})")


def _friction(d: Definition, record: Record, starts: np.ndarray, period: float, order: int) -> np.ndarray:
    v, a = kinematics(record)
    i = _crossings(v, 0.0, None)
    t, rate = record.t, 1.0 / float(np.median(np.diff(record.t)))
    cycle = _cycle_of(t[i], starts, period)
    i, cycle = i[cycle >= 0], cycle[cycle >= 0]
    if not len(i):
        raise MeasurandError("no velocity reversal in the full-amplitude cycles")
    lo, hi = d.sliding_m_s
    accel = float(np.median(np.abs(a[i])))
    m_lo, m_hi = int(math.ceil(lo / accel * rate)), int(math.floor(hi / accel * rate))
    if m_hi - m_lo < order + 2:
        raise MeasurandError(f"the sliding range {lo:g}…{hi:g} m/s holds {max(m_hi - m_lo, 0)} samples per side "
                             f"at this record's rate and acceleration; {order + 2} needed")
    ok = (i - m_hi >= 0) & (i + 1 + m_hi < len(t))
    i, cycle = i[ok], cycle[ok]
    frac = -v[i] / (v[i + 1] - v[i])                 # the reversal's place after sample i, in samples
    offs = np.arange(m_lo, m_hi + 1)
    V = np.vander(offs.astype(float), order + 1, increasing=True)
    before = record.force[i[:, None] - offs[None, :] + 1]     # samples i+1−m … : |v| grows going back
    after = record.force[i[:, None] + offs[None, :]]
    cb = np.linalg.lstsq(V, before.T, rcond=None)[0]          # in the offset from sample i+1, backwards
    ca = np.linalg.lstsq(V, after.T, rcond=None)[0]           # in the offset from sample i
    xb, xa = 1 - frac, frac                                  # the reversal, in each side's coordinate
    fb = sum(cb[k] * (-xb) ** k for k in range(order + 1))
    fa = sum(ca[k] * xa**k for k in range(order + 1))
    jump = np.sign(v[i]) * (fb - fa) / 2                      # before: the friction opposes v[i]
    return _per_cycle(jump, cycle, len(starts))


def _loops(record: Record, starts: np.ndarray, period: float) -> np.ndarray:
    t, q, f = record.t, record.stroke, record.force
    out = np.full(len(starts), np.nan)
    for j, s in enumerate(starts):
        sel = (t >= s - 1e-9) & (t < s + period - 1e-9)
        if np.count_nonzero(sel) < 4 or t[sel][-1] < s + period * 0.95:
            continue
        qq, ff = np.append(q[sel], q[sel][0]), np.append(f[sel], f[sel][0])    # closed loop
        out[j] = float(np.sum(0.5 * (ff[1:] + ff[:-1]) * np.diff(qq)))
    return out


def value_of(d: Definition, record: Record, variant: str = "") -> float:
    """The measurand (SI): the mean over the full-amplitude cycles."""
    c = per_cycle(d, record, variant)
    c = c[np.isfinite(c)]
    if len(c) < 2:
        raise MeasurandError(f"{len(c)} whole cycle{'s' * (len(c) != 1)} at full amplitude measured; "
                             "the repeatability needs 2")
    return float(np.mean(c))


def sensitivities(d: Definition, record: Record, calibration: Calibration) -> dict[tuple[str, str], float]:
    """∂value/∂(channel's gain error, relative) and ∂value/∂(channel's offset, SI), by
    recomputing the value from the record with that calibration moved by its standard
    uncertainty (a central difference); what the metrology of the certificates needs to
    carry any calibration into this measurand."""
    out = {}
    for channel, u_gain, u_offset in calibration.rows():
        for which, h in (("gain", u_gain or 1e-4), ("offset", u_offset or _unit_offset(channel))):
            kw = {which: h}
            up = value_of(d, record.calibrated(channel, **kw))
            down = value_of(d, record.calibrated(channel, **{which: -h}))
            out[(channel, which)] = (up - down) / (2 * h)
    return out


def _unit_offset(channel: str) -> float:
    return {"stroke": 1e-5, "force": 1.0, "pressure": 100.0, "temperature": 0.01}[channel]


def measure(d: Definition, record: Record, calibration: Calibration) -> Value:
    """The measurand with its budget."""
    c = per_cycle(d, record)
    c = c[np.isfinite(c)]
    n = len(c)
    if n < 2:
        raise MeasurandError(f"{n} whole cycle{'s' * (n != 1)} at full amplitude measured; the repeatability "
                             "needs 2")
    value = float(np.mean(c))
    rows = [BudgetRow("repeatability", "A", _repeatability(c),
                      f"scatter of {n} cycles about their linear trend (the warming), standard error of the mean")]
    sens = sensitivities(d, record, calibration)
    for channel, u_gain, u_offset in calibration.rows():
        u = math.hypot(sens[(channel, "gain")] * u_gain, sens[(channel, "offset")] * u_offset)
        if u_gain or u_offset:
            rows.append(BudgetRow(f"calibration: {channel}", "B", u,
                                  f"gain u {100 * u_gain:.2g} %, offset u {u_offset:.3g} SI; sensitivities "
                                  f"{sens[(channel, 'gain')]:.3g}, {sens[(channel, 'offset')]:.3g}"))
    if d.kind == "gas_spring_pressure":
        rows.append(_temperature_row(d, record, value))
    other = value_of(d, record, "other")
    rows.append(BudgetRow(_FOLDING[d.kind], "B", abs(other - value) / math.sqrt(3),
                          f"recomputed {_OTHER[d.kind]}: difference {other - value:+.3g} SI, taken as the half-width "
                          "of a rectangular distribution"))
    return Value(value, tuple(rows), n)


_FOLDING = {"gas_spring_pressure": "interpolation to the stated stroke",
            "damping_force": "interpolation to the stated velocity",
            "seal_friction": "extrapolation to the reversal",
            "cycle_energy": "folding into cycles"}
_OTHER = {"gas_spring_pressure": "with a quadratic interpolation",
          "damping_force": f"with the stroke's fit of {HARMONICS + 2} harmonics instead of {HARMONICS}",
          "seal_friction": "with a cubic instead of a quadratic extrapolation",
          "cycle_energy": "with the cycles starting half a period later"}


def _repeatability(c: np.ndarray) -> float:
    n = len(c)
    if n >= 4:      # the warming's trend is not scatter: its residuals are, with n − 2 degrees of freedom
        x = np.arange(n) - (n - 1) / 2
        resid = c - np.polyval(np.polyfit(x, c, 1), x)
        return float(np.sqrt(np.sum(resid**2) / (n - 2)) / math.sqrt(n))
    return float(np.std(c, ddof=1) / math.sqrt(n))


def _temperature_row(d: Definition, record: Record, value: float) -> BudgetRow:
    """The correction p·T_ref/T uses the thermometer, which lags the gas: the gas's own
    temperature at a crossing is known only to within how the reading differs between
    the compression and the rebound pass of a cycle (rectangular)."""
    i = _crossings(record.stroke, d.stroke_m, None)
    temp = _at(record.temperature, record.stroke, i, d.stroke_m)
    rising = record.stroke[i + 1] > record.stroke[i]
    diff = abs(float(np.mean(temp[rising]) - np.mean(temp[~rising]))) if rising.any() and (~rising).any() else 0.0
    u_t = diff / math.sqrt(3)
    correction = float(np.mean(d.temperature_k / temp))
    return BudgetRow("temperature correction", "B", value * u_t / float(np.mean(temp)),
                     f"referred to {d.temperature_k - CELSIUS:g} °C by the mean factor {correction:.4f}; the gas "
                     f"temperature at the crossing known to ±{diff:.3g} K (the reading's difference between the "
                     "passes)")

