"""Steady-state capture of one periodic experiment: a small explicit state machine.

    IDLE → MOVING (hydraulics on, static position, AT_STATIC)
         → SETTLING (RUN with the amplitude ramp; DAQ streaming; until the
                     cycle-to-cycle change of every channel is below its threshold)
         → CAPTURING (K whole periods without lost samples, or flagged)
         → STOPPING (fade out, STOP) → IDLE
    any state → ALARM when the controller trips

Each transition is published on the event bus; samples come from the DAQ reader
thread into a :class:`Recorder` and are examined by the acquisition thread, which
never waits on a subscriber.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identify.move_profile import MoveProfile
from identify.plans import ExperimentSpec
from rig.config import CHANNELS, RigConfig, SteadyStateCriteria
from rig.drivers.clock import WALL_CLOCK, Clock
from rig.drivers.daq import Daq, Samples
from rig.drivers.registers import ControllerState
from rig.drivers.shaker import AlarmError, Shaker, ShakerTimeout
from rig.errors import RigFault
from rig.events import EventBus, Kind, Phase
from rig.planning.criterion import (
    MIN_BLOCKS,
    block_cycles,
    blocks_bias,
    change_passes,
    drift_passes,
    first_block_sample,
)
from rig.planning.plans import transient_capture_s
from rig.planning.settling import Hold

POLL_S = 0.05
# Block means with lost samples (see block_means): harmonics of the excitation fitted
# beside the mean (the damper's force carries a few: v|v| and the friction's arctan),
# and the share of a block that may be missing before its mean is not trusted.
HARMONICS_IN_BLOCK_MEAN = 12
MAX_LOST_IN_BLOCK = 0.2
QUICK_RECONNECT_S = 0.5
# Seconds of a transient record (from RUN) at which qc run judges it as it grows: past the
# 1 s ramp, then each half second; the capture ends at the first that decides every
# characteristic.  Each judgement is a fit of the record so far.
JUDGED_AT_S = (1.5, 2.0, 2.5)
MOVE_TIMEOUT_S = 30.0           # beyond twice the move profile's duration: the controller is stuck
# A hold ends on the gas temperature of a line fitted through this much of the stream,
# or at the model's duration times this factor plus the margin, whichever comes first.
HOLD_TEMPERATURE_FIT_S = 0.25
HOLD_CAP_FACTOR = 2.0
HOLD_CAP_MARGIN_S = 5.0
PACE_PROBE_S = 0.2             # of this clock, streaming, to measure the links' pace
# Probes of PACE_PROBE_S each, and the median of their paces and timings: on a busy host
# one probe caught a simulator stalled or catching up (6.95 and 11.5 rig s/s at 10x).
PACE_PROBES = 5
PACE_PROBE_READS = 3           # status reads timed per probe (the median: one Modbus transaction)
# Streamed in the session, this much of this clock takes over from the probe's pace.
PACE_FROM_STREAMS_S = 2.0
# Between a hold's end and RUN the controller gets these beside the DAQ's stop and start:
# the status read that finds it AT_STATIC, and RUN's setpoints and mode.
HOLD_END_MODBUS_TRANSACTIONS = 3
# An experiment's, beside the DAQ's stop and start: the fade-out, STOP, the status read
# before the move, the move's setpoint and mode, RUN's setpoints and mode, the status read
# after STOP (what the sentence "At rest" is derived from).
EXPERIMENT_MODBUS_TRANSACTIONS = 8
STATUS_POLL_S = 0.02           # the controller's state polled this often while waiting for AT_STATIC
RESPONSE_MIN_MOVE_MM = 5.0       # shorter moves are too slow at their midpoint to time the stroke's delay
ARRIVED_MM = 0.2                # the stroke channel this near a static position: there (noise 0.01 mm)


@dataclass(frozen=True)
class PaceReading:
    """The links' rig seconds per second of the acquisition's clock (the host's on a rig
    or a served simulator), as measured in this session, and over what: the DAQ's
    sample count against that clock."""

    rig_s_per_s: float
    over: str

    def __str__(self) -> str:
        return (f"{self.rig_s_per_s:.3g} rig seconds per second of this computer's clock (the DAQ's sample count "
                f"over {self.over})")


class AcquisitionError(RigFault):
    """An experiment could not be captured (names the experiment and why)."""


class Interrupted(Exception):
    """The operator asked to stop (Ctrl-C)."""


@dataclass
class ExperimentRecord:
    """A captured periodic steady state (engineering units, as the CSV holds it)."""

    spec: ExperimentSpec
    label: str
    rate_hz: int
    index: np.ndarray            # sample numbers since START (gaps where samples were lost)
    values: np.ndarray           # (N, 4)
    settle_cycles: int
    settled: bool
    lost_samples: int            # inside the captured window
    stream_lost: int             # over the whole experiment's stream
    over_range: int
    recaptures: int              # windows captured again after one that lost samples
    flags: list[str] = field(default_factory=list)

    @property
    def time_s(self) -> np.ndarray:
        return self.index / self.rate_hz


@dataclass(frozen=True)
class Settled:
    """How settling ended: passed (or ``max_cycles``), after how many cycles, the sample
    after its last block (where the capture starts), and its samples seen and lost."""

    settled: bool
    cycles: int
    end: int
    seen: int
    missed: int


class Recorder:
    """Samples of the running experiment, addressed by their index (a lost sample is a
    hole).  Only samples from :meth:`forget_before`'s index on are kept: the settling
    blocks and capture windows are read in order, so memory stays bounded by a block
    plus the capture windows however long an experiment settles (a 0.04 Hz experiment
    held for 1500 cycles would otherwise keep 75 million samples)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.base = 0                      # index of the first sample held
        self.keep_from = 0                 # samples below this are no longer needed
        self.values = np.zeros((0, 4))
        self.present = np.zeros(0, dtype=bool)
        self.over = np.zeros(0, dtype=bool)
        self.end = 0

    def __call__(self, s: Samples) -> None:
        with self._lock:
            top = int(s.index[-1]) + 1
            if top - self.base > len(self.present):
                self._make_room(top)
            keep = s.index >= self.base    # a late block of an already forgotten stretch
            at = s.index[keep] - self.base
            self.values[at] = s.values[keep]
            self.present[at] = True
            self.over[at] = (s.flags[keep] & 1).astype(bool)
            self.end = max(self.end, top)

    def _make_room(self, top: int) -> None:
        """Drop what is forgotten and, where that is not enough, double the capacity."""
        drop = max(self.keep_from - self.base, 0)
        base, held = self.base + drop, len(self.present)
        size = held if top - base <= held else max(top - base, 2 * held, 65536)
        values, present, over = np.zeros((size, 4)), np.zeros(size, dtype=bool), np.zeros(size, dtype=bool)
        kept = held - drop
        values[:kept], present[:kept], over[:kept] = self.values[drop:], self.present[drop:], self.over[drop:]
        self.base, self.values, self.present, self.over = base, values, present, over

    def window(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            if a < self.base:
                raise ValueError(f"samples {a}…{self.base - 1} were forgotten")
            i, j = a - self.base, b - self.base
            return self.values[i:j].copy(), self.present[i:j].copy(), self.over[i:j].copy()

    def forget_before(self, index: int) -> None:
        """Samples below ``index`` will not be read again (their memory is reused)."""
        with self._lock:
            self.keep_from = max(self.keep_from, index)

    @property
    def held(self) -> int:
        """Samples of memory in use (for the bound's test)."""
        return len(self.present)


def block_means(values: np.ndarray, present: np.ndarray, index: np.ndarray,
                samples_per_period: float) -> np.ndarray | None:
    """The channels' means over a block of whole cycles (samples ``index``), or None when
    too much is missing.

    With every sample there, the plain mean.  With holes, the plain mean of what is left
    scatters with the periodic signal itself (its std × √(lost/N)), enough to keep a
    settled experiment from passing the criterion for tens of cycles.  A block of several
    cycles at a whole number of samples per period is folded: each phase's mean over the
    cycles that have it, then the mean over the phases, which holds for any harmonic
    content (the friction's arctan has harmonics far beyond a dozen, and a fit of a dozen
    left the noise-limited experiments' block means a quarter noisier with 1.6 % lost,
    and their settling as much longer).  Otherwise the constant term of a least-squares
    fit of the excitation's first harmonics."""
    if present.all():
        return values.mean(axis=0)
    if np.count_nonzero(~present) > MAX_LOST_IN_BLOCK * len(present):
        return None
    spp = round(samples_per_period)
    cycles = len(present) // spp if spp == samples_per_period else 0
    if cycles >= 2 and cycles * spp == len(present):
        have = present.reshape(cycles, spp)
        count = have.sum(axis=0)
        if count.all():
            folded = np.where(have[..., None], values.reshape(cycles, spp, -1), 0.0).sum(axis=0)
            return (folded / count[:, None]).mean(axis=0)
    phase = np.outer(2 * np.pi * index[present] / samples_per_period, np.arange(1, HARMONICS_IN_BLOCK_MEAN + 1))
    design = np.column_stack([np.ones(len(phase)), np.cos(phase), np.sin(phase)])
    coefficients, *_ = np.linalg.lstsq(design, values[present], rcond=None)
    return coefficients[0]


def _response_delay(rec: Recorder, commanded: int, arrived: int, from_m: float, to_m: float, rate_hz: float,
                    move: MoveProfile) -> float:
    """Rig seconds from a move's command to the stroke following the controller's profile,
    as the acquisition sees it: the stroke's crossing of the move's midpoint, where it is
    fastest, against the profile's (the link's delivery, the controller's reaction and the
    actuator's lag, all in one).  0 for a move too short to time."""
    distance_mm = (to_m - from_m) * 1e3
    if abs(distance_mm) < RESPONSE_MIN_MOVE_MM or arrived <= commanded:
        return 0.0
    values, present, _ = rec.window(max(commanded, rec.base), arrived + 1)
    past = np.flatnonzero(present & ((values[:, CHANNELS.index("stroke_mm")] - from_m * 1e3 - distance_mm / 2)
                                     * math.copysign(1.0, distance_mm) >= 0))
    if not len(past):
        return 0.0
    crossed = max(commanded, rec.base) + int(past[0])
    return max(0.0, (crossed - commanded) / rate_hz - move.duration_s(to_m - from_m) / 2)


def drift_cycles_left(ss: SteadyStateCriteria, cycles: int, bias_sigma: float, ratio: float) -> int | None:
    """Cycles until the drift criterion passes, the transient's bias decaying by ``ratio``
    per cycle (None: not seen to decay): what the operator waits for, said instead of a
    bias of hundreds of σ that means nothing at the rig."""
    assert ss.drift is not None
    floor = max(ss.min_cycles - cycles, 0)
    if bias_sigma < ss.drift.fraction:
        return floor
    if not 0.0 < ratio < 1.0 or not math.isfinite(bias_sigma):
        return None
    left = math.ceil(math.log(ss.drift.fraction / bias_sigma) / math.log(ratio))
    return int(min(max(left, floor), max(ss.max_cycles - cycles, 0)))


def _line_at_end(values: np.ndarray, present: np.ndarray) -> tuple[float, float]:
    """Slope per sample and value at the window's last sample of a straight line through
    the samples present (a noisy channel's trend, read where it is now)."""
    slope, at_end = np.polyfit(np.flatnonzero(present) - (len(values) - 1), values[present], 1)
    return float(slope), float(at_end)


class Acquisition:
    """Runs experiments on a connected shaker and DAQ, publishing events on ``bus``."""

    def __init__(self, shaker: Shaker, daq: Daq, config: RigConfig, bus: EventBus, clock: Clock = WALL_CLOCK) -> None:
        self.shaker, self.daq, self.config, self.bus, self.clock = shaker, daq, config, bus, clock
        self.phase = Phase.IDLE
        self.stop_requested = threading.Event()
        self.answer_s = 0.0    # seconds of this clock the commands between a hold's end and RUN take (measure_pace)
        self.overhead_s = 0.0  # and an experiment's polls and commands beyond the rig's own motion
        self.probed_pace = 1.0  # rig seconds per second of this clock, by the probe (measure_pace)
        self._streamed_samples, self._streamed_s = 0, 0.0   # the session's streams so far (current_pace)
        # A transient capture judged as it grows (qc run's stop-when-decided): called with the
        # record so far at each of JUDGED_AT_S; a reason ends the capture there.
        self.judge_partial: Callable[[ExperimentRecord], str | None] | None = None
        self.decided_within: str | None = None     # why the last transient capture ended early
        self._recorder: Recorder | None = None
        daq.subscribe(self._on_samples)

    def _on_samples(self, s: Samples) -> None:
        rec = self._recorder
        if rec is not None:
            rec(s)

    def _enter(self, phase: Phase, label: str | None, **data: Any) -> None:
        self.phase = phase
        self.bus.publish(Kind.PHASE, label, phase=phase.value, clock_s=self.clock.monotonic(), **data)

    def _check_stop(self) -> None:
        if self.stop_requested.is_set():
            raise Interrupted()

    def run_experiment(self, spec: ExperimentSpec, label: str, hold: Hold | None = None,
                       time_constant_s: float | None = None) -> ExperimentRecord:
        """Capture one experiment (by way of a conditioning ``hold``, if given;
        ``time_constant_s``: the gas's relaxation the model predicts there); raises
        :class:`AlarmError` (after entering ALARM), :class:`Interrupted`,
        :class:`AcquisitionError` or a link error, leaving the shaker to :meth:`safe_stop`."""
        try:
            return self._run_experiment(spec, label, hold, time_constant_s)
        except AlarmError as exc:
            self._enter(Phase.ALARM, label, message=str(exc))
            raise

    def _run_experiment(self, spec: ExperimentSpec, label: str, hold: Hold | None,
                        time_constant_s: float | None) -> ExperimentRecord:
        # A stop asked between experiments (an operator's E-STOP switched the hydraulics off)
        # must not be answered by switching them on again for the next one.
        self._check_stop()
        ss = self.config.steady_state
        static, amp = spec.static_position_mm * 1e-3, spec.amplitude_mm * 1e-3
        self._enter(Phase.MOVING, label, target_mm=spec.static_position_mm)
        st = self.shaker.status()
        if st.state is ControllerState.ALARM:
            raise AlarmError(st)
        if st.state is ControllerState.OFF:
            self.shaker.hydraulics(True)
        position = st.position_m
        lost0 = self.daq.counters.lost_samples   # the hold's stream and the experiment's
        transient = spec.capture == "transient"
        if transient:
            hold = None  # nothing to condition: the transient from RUN is what is captured
        if hold is not None:
            self._hold(hold, label, position, static)
            position = hold.position_m
        else:
            self.shaker.move_to(static)
        self._wait_state({ControllerState.AT_STATIC},
                         MOVE_TIMEOUT_S + 2 * self.config.move.duration_s(static - position))
        self._check_stop()

        self._enter(Phase.SETTLING, label)
        self._recorder = recorder = Recorder()
        streaming = self.clock.monotonic()
        self.daq.start()
        self.shaker.run(static, amp, spec.frequency_hz, spec.waveform, ss.ramp_time_s)
        captured = False
        try:
            if transient:
                record = self._capture_from_run(spec, label, recorder)
            else:
                settled = self._settle(spec, label, recorder, time_constant_s)
                self.bus.publish(Kind.LOG, label, message=(
                    f"steady state after {settled.cycles} cycles" if settled.settled else
                    f"no steady state within {ss.max_cycles} cycles: captured anyway, flagged"))
                self._enter(Phase.CAPTURING, label, cycles=settled.cycles)
                record = self._capture(spec, label, recorder, settled)
            captured = True
        finally:
            issued = self.daq.stop()
            self._recorder = None
            # Only a stream that ended as planned measures the pace: one cut by a dead
            # link counts the wait for it as streamed time (a killed simulator's last
            # stream said 2.13 rig seconds per second at 10x).
            if captured and not self.daq.reader_error:
                self._count_stream(issued, streaming)
        record.stream_lost = self.daq.counters.lost_samples - lost0
        self.bus.publish(Kind.LOG, label, message=f"DAQ: {issued} samples taken, {record.stream_lost} lost in the "
                                               f"stream, {record.lost_samples} in the captured window")
        self._enter(Phase.STOPPING, label)
        self.shaker.fade_out()
        self._wait_state({ControllerState.AT_STATIC}, 30.0 + 2 * ss.ramp_time_s)
        self.shaker.stop()
        st = self.shaker.status()   # "At rest" is said from this reading, not from the STOP sent
        self._enter(Phase.IDLE, label, controller=st.state, alarm=st.alarm)
        return record

    def _hold(self, hold: Hold, label: str, from_m: float, then_m: float) -> None:
        """The conditioning hold (the stroke coming from ``from_m``), then the move on to ``then_m``.

        The hold ends when the measured gas temperature reaches the one the model says
        brings the gas to the experiment's periodic state: a fixed time would land
        tenths of a kelvin off, the controller's and the link's latencies being a good
        part of a short hold.  So the DAQ streams from before the move, arrival is read
        off the stroke channel (not a status poll), a crossing due before the next look
        is waited for on the temperature's line, and the move on is commanded at once.
        The gas temperature measured up to that command is logged.  Bounded,
        in the DAQ's samples (the rig's own time at any link speed), should the damper
        not follow the model; the steady-state criterion decides the rest either way."""
        target_c = hold.end_temperature_k - 273.15
        # Said as what it is: the gas held compressed (or expanded) is far hotter (colder) than
        # during the experiment, and an operator who sees 15-25 °C on the trace afterwards must
        # not read the hold's target as a unit or sensor fault.
        self.bus.publish(Kind.HOLD, label, position_mm=hold.position_m * 1e3, experiment_mm=then_m * 1e3,
                         target_c=target_c, predicted_s=hold.duration_s, compressed=hold.position_m > then_m)
        rate = self.daq.rate_hz
        side = math.copysign(1.0, hold.arrival_temperature_k - hold.end_temperature_k)
        tail, step = round(HOLD_TEMPERATURE_FIT_S * rate), max(1, round(POLL_S * rate))
        gas = CHANNELS.index("gas_temperature_C")
        self._recorder = rec = Recorder()
        streaming = self.clock.monotonic()
        self.daq.start()
        t0 = self.clock.monotonic()
        try:
            self.shaker.move_to(hold.position_m)
            commanded = rec.end
            arrived = self._wait_for_stroke(rec, hold.position_m, label,
                                            MOVE_TIMEOUT_S + 2 * self.config.move.duration_s(hold.position_m - from_m))
            lead = _response_delay(rec, commanded, arrived, from_m, hold.position_m, rate, self.config.move)
            cap = arrived + round((HOLD_CAP_FACTOR * hold.duration_s + HOLD_CAP_MARGIN_S) * rate)
            while rec.end < cap:
                self._wait_samples(rec, min(rec.end + step, cap), label)
                end = rec.end
                if end - arrived < tail:
                    continue
                values, present, _ = rec.window(end - tail, end)
                rec.forget_before(end - tail)
                if np.count_nonzero(present) < tail // 2:
                    continue    # a hole in the stream: the next poll reads on
                slope, now_c = _line_at_end(values[:, gas], present)
                if (now_c - target_c) * side <= 0:
                    break
                to_go = (target_c - now_c) / slope / rate - lead if slope else math.inf
                pace = end / rate / max(self.clock.monotonic() - t0, 1e-9)   # rig seconds per clock second
                if to_go < POLL_S * pace:
                    self.clock.sleep(max(to_go, 0.0) / pace)
                    break
            self.shaker.move_to(then_m)
            left = rec.end
            values, present, _ = rec.window(max(left - tail, rec.base, arrived), left)
        finally:
            self._count_stream(self.daq.stop(), streaming)
            self._recorder = None
        left_c = _line_at_end(values[:, gas], present)[1] if np.count_nonzero(present) > 1 else math.nan
        self.bus.publish(Kind.HOLD_END, label, gas_c=left_c, target_c=target_c, held_s=(left - arrived) / rate,
                         predicted_s=hold.duration_s, lead_s=lead)

    def _wait_for_stroke(self, rec: Recorder, position_m: float, label: str, timeout_s: float) -> int:
        """Index of the first sample whose stroke is at ``position_m`` (within
        ARRIVED_MM); AcquisitionError after ``timeout_s`` of the rig's time without."""
        column, rate = CHANNELS.index("stroke_mm"), self.daq.rate_hz
        looked, limit = 0, rec.end + round(timeout_s * rate)
        while True:
            self._wait_samples(rec, min(rec.end + 1, limit), label)
            values, present, _ = rec.window(max(looked, rec.base), rec.end)
            near = np.abs(values[:, column] - position_m * 1e3) <= ARRIVED_MM
            hit = np.flatnonzero(present & near)
            if len(hit):
                return max(looked, rec.base) + int(hit[0])
            looked = rec.end
            if looked >= limit:
                raise AcquisitionError(f"experiment {label}: the stroke did not reach {position_m * 1e3:.1f} mm "
                                       f"within {timeout_s:.0f} s")

    def measure_pace(self) -> float:
        """Rig seconds per second of this clock: 1 on a rig, the speed of a simulator
        that runs faster than its time (from PACE_PROBES short streams of the DAQ's
        samples, the median; their counts, and what the line lost of them, are logged).

        Also :attr:`answer_s`: what the commands between a hold's end and RUN take of
        this clock (the DAQ's stop and start, timed here, and the status read and the
        two writes of RUN, timed as status reads), during which the gas, at rest, goes
        on relaxing: times the pace, the rig seconds by which a hold may land off.  And
        :attr:`overhead_s`: what an experiment's polls and commands add to the rig's
        own motion: the capture's end is seen half a poll late on average and the
        stream runs on while the DAQ stops; the two waits for AT_STATIC end half a
        status poll late; the DAQ's start and the controller's writes.  Milliseconds
        on a rig; at 50x, seconds of the rig's time per experiment.  Each timing is the
        median over the probes: a busy host's stall in one of them moves none."""
        lost0 = self.daq.counters.lost_samples
        samples, paces, starts, stops, reads = [], [], [], [], []
        for _ in range(PACE_PROBES):
            t0 = self.clock.monotonic()
            self.daq.start()
            t1 = self.clock.monotonic()
            self.clock.sleep(PACE_PROBE_S)
            t2 = self.clock.monotonic()
            issued = self.daq.stop()
            t3 = self.clock.monotonic()
            samples.append(issued)
            paces.append(issued / self.daq.rate_hz / max(t2 - t1, 1e-9))
            starts.append(t1 - t0)
            stops.append(t3 - t2)
            for _ in range(PACE_PROBE_READS):
                t = self.clock.monotonic()
                self.shaker.status()
                reads.append(self.clock.monotonic() - t)
        pace = self.probed_pace = max(1.0, float(np.median(paces)))
        modbus_s, start_s, stop_s = (float(np.median(x)) for x in (reads, starts, stops))
        daq_s = start_s + stop_s
        self.answer_s = daq_s + HOLD_END_MODBUS_TRANSACTIONS * modbus_s
        self.overhead_s = POLL_S / 2 + STATUS_POLL_S + daq_s + EXPERIMENT_MODBUS_TRANSACTIONS * modbus_s
        self.bus.publish(Kind.PACE_PROBE, None, samples=sum(samples), lost=self.daq.counters.lost_samples - lost0,
                         probes=len(paces), probe_s=PACE_PROBE_S, pace=pace, pace_min=min(paces), pace_max=max(paces),
                         daq_start_s=start_s, daq_stop_s=stop_s, status_read_s=modbus_s, answer_s=self.answer_s,
                         overhead_s=self.overhead_s)
        return pace

    def _count_stream(self, issued: int, since: float) -> None:
        self._streamed_samples += issued
        self._streamed_s += self.clock.monotonic() - since

    def current_pace(self) -> float:
        """The links' rig seconds per second as the session shows it: the probe's, until
        the session's own streams (seconds, not the probe's fifth) have taken
        PACE_FROM_STREAMS_S of this clock; then theirs (the samples the DAQ took against
        the time it was streaming), which a host busy for a while moves no more than
        the simulator's own average.  Streams that ended on a fault do not count."""
        return self.pace_reading().rig_s_per_s

    def pace_reading(self) -> PaceReading:
        """:meth:`current_pace` with where it was measured, for a sentence that says so."""
        if self._streamed_s < PACE_FROM_STREAMS_S:
            return PaceReading(self.probed_pace, f"the pace probe's {PACE_PROBES} short streams before the first "
                                                 "experiment")
        return PaceReading(max(1.0, self._streamed_samples / self.daq.rate_hz / self._streamed_s),
                           f"{self._streamed_s:.0f} s of this session's streams that ended as planned")

    def _wait_state(self, states: set[ControllerState], timeout_s: float) -> None:
        """Wait for a controller state in short slices, so that Ctrl-C is honoured."""
        deadline = self.clock.monotonic() + timeout_s
        while True:
            self._check_stop()
            try:
                self.shaker.wait_for(states, timeout_s=min(0.5, max(deadline - self.clock.monotonic(), 0.0)),
                                     poll_s=STATUS_POLL_S)
                return
            except ShakerTimeout:
                if self.clock.monotonic() > deadline:
                    raise

    def _settle(self, spec: ExperimentSpec, label: str, rec: Recorder, time_constant_s: float | None) -> Settled:
        """Compare the channel means of consecutive blocks of whole cycles until the
        steady-state criterion passes (or ``max_cycles``)."""
        ss, rate = self.config.steady_state, self.daq.rate_hz
        spp = rate / spec.frequency_hz                       # samples per period
        start = first_block_sample(ss, rate)                 # after the fade-in (+ the actuator's lag)
        drift = ss.drift if ss.criterion == "drift" else None
        m = block_cycles(ss, spec.frequency_hz)
        thresholds = np.array([ss.thresholds[c] for c in CHANNELS])
        fitted = [CHANNELS.index(c) for c in drift.noise] if drift is not None else []
        history: list[np.ndarray] = []                         # consecutive block means of the fitted channels
        block, prev_means, cycles = 0, None, 0
        seen = missed = 0                                      # samples of the settling blocks, and lost of them
        while True:
            a = start + int(round(block * m * spp))
            b = start + int(round((block + 1) * m * spp))
            self._wait_samples(rec, b, label)
            values, present, _ = rec.window(a, b)
            rec.forget_before(b)
            seen, missed = seen + len(present), missed + int(np.count_nonzero(~present))
            means = block_means(values, present, np.arange(a, b), spp)
            cycles = (block + 1) * m
            if means is None:
                # Too much of the block is missing to know its mean: it can neither pass
                # nor count as the reference of the next comparison (nor as a point of the
                # decay, whose cycles must follow each other).
                history.clear()
                self.bus.publish(Kind.LOG, label, message=f"settling block ending at cycle {cycles}: "
                                                          f"{np.count_nonzero(~present)} samples lost, not compared")
            elif drift is not None:
                history = (history + [means[fitted]])[-drift.fit_cycles:]
                if len(history) >= MIN_BLOCKS:
                    fit = blocks_bias(drift, np.array(history), m, spec.frequency_hz, spp, spec.periods,
                                      time_constant_s)
                    # the cycle-to-cycle change too: what the console and the GUI show of settling
                    change = np.abs(means - prev_means) if prev_means is not None else np.full(len(CHANNELS), np.nan)
                    self.bus.publish(Kind.PROGRESS, label, phase=Phase.SETTLING.value, cycles=cycles,
                                     change={c: float(x) for c, x in zip(CHANNELS, change, strict=True)},
                                     bias_sigma=fit.bias_sigma, ratio=fit.ratio, bias_limit_sigma=drift.fraction,
                                     cycles_left=drift_cycles_left(ss, cycles, fit.bias_sigma, fit.ratio),
                                     drift={c: float(x) for c, x in zip(drift.noise, fit.drift, strict=True)})
                    if drift_passes(ss, cycles, fit):
                        return Settled(True, cycles, b, seen, missed)
            elif prev_means is not None:
                change = np.abs(means - prev_means)
                self.bus.publish(Kind.PROGRESS, label, phase=Phase.SETTLING.value, cycles=cycles,
                                 change={c: float(x) for c, x in zip(CHANNELS, change, strict=True)})
                if change_passes(ss, cycles, change, thresholds):
                    return Settled(True, cycles, b, seen, missed)
            if cycles >= ss.max_cycles:
                return Settled(False, cycles, b, seen, missed)
            prev_means, block = means, block + 1

    def _capture(self, spec: ExperimentSpec, label: str, rec: Recorder, settled: Settled) -> ExperimentRecord:
        """The captured window: ``spec.periods`` whole periods right after the last
        settling block, captured again (up to ``max_recaptures``) after a burst of lost
        samples, the best kept."""
        ss, rate = self.config.steady_state, self.daq.rate_hz
        n = int(math.ceil(spec.periods * rate / spec.frequency_hz))
        loss = settled.missed / settled.seen if settled.seen else 0.0    # the line's steady loss while settling
        best: tuple[int, np.ndarray, np.ndarray, int, np.ndarray] | None = None
        attempts, steady = 0, True
        for attempt in range(ss.max_recaptures + 1):
            attempts = attempt + 1
            a = settled.end + attempt * n  # windows follow the last settling block back to back
            self._wait_samples(rec, a + n, label, capture=(a, n))
            values, present, over = rec.window(a, a + n)
            rec.forget_before(a + n)
            lost = int(np.count_nonzero(~present))
            if best is None or lost < best[3]:
                best = (a, values, present, lost, over)
            # A window is captured again for a burst (a stall, an overflow), not for the
            # line's steady loss, which the next window would lose as much of: at 1.6 %
            # every window of the 0.04 Hz experiment loses ~2400 samples, and two more
            # of them cost 150 s of rig time for nothing.
            expected = loss * n
            steady = lost <= expected + 3 * math.sqrt(expected)
            if lost:
                self.bus.publish(Kind.CAPTURE_WINDOW, label, window=attempts, lost=lost, steady_loss=loss,
                                 kept=steady, again=not steady and attempt < ss.max_recaptures)
            if lost == 0 or steady:
                break
        assert best is not None  # the loop ran at least once
        a, values, present, lost, over = best
        flags = []
        if not settled.settled:
            flags.append(f"steady state not reached within {ss.max_cycles} cycles")
        if lost and steady:
            flags.append(f"{lost} samples lost in the captured window (rows absent; the line's steady loss, "
                         f"{loss:.2%} while settling)")
        elif lost:
            flags.append(f"{lost} samples lost in the captured window (rows absent; best of {attempts} windows)")
        index = a + np.flatnonzero(present)
        return ExperimentRecord(spec, label, rate, index, values[present], settled.cycles, settled.settled, lost, 0,
                                int(np.count_nonzero(over[present])), attempts - 1, flags)

    def _capture_from_run(self, spec: ExperimentSpec, label: str, rec: Recorder) -> ExperimentRecord:
        """The plan's ``capture = "transient"``: no settling, every sample from RUN (the
        DAQ's start, just before it) on, the amplitude ramp and the plan's periods at full
        amplitude.  Samples lost here cannot be captured again (the transient is gone):
        their rows are absent and declared, and a transient fit refuses the record."""
        rate = self.daq.rate_hz
        n = int(round(transient_capture_s(spec, self.config.steady_state.ramp_time_s, rate) * rate))
        self._enter(Phase.CAPTURING, label, cycles=0)
        self.bus.publish(Kind.LOG, label, message=f"transient capture: {n / rate:.2f} s from RUN, no settling")
        self.decided_within = None
        end = self._judged_while_capturing(spec, label, rec, n, rate) if self.judge_partial else n
        self._wait_samples(rec, end, label, capture=(0, n))
        record = self._from_run(spec, label, rec, end, rate)
        rec.forget_before(end)
        return record

    def _judged_while_capturing(self, spec: ExperimentSpec, label: str, rec: Recorder, n: int, rate: int) -> int:
        """Capture while the record so far is judged beside it (one judgement at a time,
        on its own thread: a fit never holds the rig up), each from the first point of
        :data:`JUDGED_AT_S` the record has reached since the last; the sample count at
        which the capture ends: ``n``, or what the DAQ had delivered when a judgement
        decided (every sample kept; the verdict is made again on the whole record).  A
        judgement still running when the record is whole is left to finish unheard."""
        judge = self.judge_partial
        assert judge is not None
        points = [round(s * rate) for s in JUDGED_AT_S if round(s * rate) < n]
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="judge-partial")
        running: tuple[int, Future[str | None]] | None = None
        try:
            while rec.end < n:
                if running is not None and running[1].done():
                    at, future = running
                    running = None
                    reason = future.result()
                    if reason:
                        end = min(max(rec.end, at), n)
                        self.decided_within = f"{reason} after {at / rate:g} s of the record"
                        self.bus.publish(Kind.LOG, label, message=f"transient capture ended at {end / rate:.2f} s "
                                                                  f"of {n / rate:.2f} s: {self.decided_within}")
                        return end
                reached = [p for p in points if p <= rec.end]
                if running is None and reached:
                    at = reached[-1]
                    points = [p for p in points if p > at]
                    running = (at, pool.submit(judge, self._from_run(spec, label, rec, at, rate)))
                self._wait_samples(rec, min(rec.end + max(int(POLL_S * rate), 1), n), label, capture=(0, n))
            return n
        finally:
            pool.shutdown(wait=False, cancel_futures=True)

    @staticmethod
    def _from_run(spec: ExperimentSpec, label: str, rec: Recorder, end: int, rate: int) -> ExperimentRecord:
        """The samples from RUN to ``end`` as a transient capture's record."""
        values, present, over = rec.window(0, end)
        lost = int(np.count_nonzero(~present))
        flags = [f"{lost} samples lost in the transient capture (rows absent; it cannot be fitted as a transient)"
                 ] if lost else []
        return ExperimentRecord(spec, label, rate, np.flatnonzero(present), values[present], 0, False, lost, 0,
                                int(np.count_nonzero(over[present])), 0, flags)

    def _wait_samples(self, rec: Recorder, end: int, label: str, capture: tuple[int, int] | None = None) -> None:
        """Wait until the DAQ index reaches ``end``, watching the controller for alarms."""
        last_status = 0.0
        while rec.end < end:
            self._check_stop()
            if self.daq.reader_error:
                raise AcquisitionError(f"experiment {label}: {self.daq.reader_error}")
            now = self.clock.monotonic()
            if now - last_status > 0.2:
                st = self.shaker.status()
                if st.state is ControllerState.ALARM:
                    raise AlarmError(st)
                last_status = now
                if capture:
                    a, n = capture
                    self.bus.publish(Kind.PROGRESS, label, phase=Phase.CAPTURING.value,
                                     fraction=min(max((rec.end - a) / n, 0.0), 1.0))
            self.clock.sleep(POLL_S)

    def safe_stop(self, reason: str) -> list[str]:
        """Bring the rig to rest whatever happened: stop the stream, fade out, STOP,
        hydraulics off.  Each step is tried even if an earlier one fails; the steps
        that failed are returned (and logged), so that the record can say so."""
        self._enter(Phase.STOPPING, None, reason=reason)
        steps: list[tuple[str, Callable[[], object]]] = [("DAQ stop", self.daq.stop)]
        done = ["stream stopped"]                              # what the record says was done, in order
        st, patience = None, self.shaker.reconnect_s
        try:
            st = self.shaker.status()
        except Exception as exc:  # noqa: BLE001 — link gone: report, keep trying the rest
            self.bus.publish(Kind.LOG, None, message=f"safe stop: status unreadable ({exc})")
            # The link had its whole reconnect time just now: each remaining step gets one
            # quick try, so the record is written while the controller's watchdog takes over.
            patience = QUICK_RECONNECT_S
        veto = self.shaker.veto("fade out")
        if st is not None and st.state is ControllerState.RUNNING and veto is not None:
            self.bus.publish(Kind.LOG, None, message=f"safe stop: no fade ({veto})")
        elif st is not None and st.state is ControllerState.RUNNING:
            steps.append(("fade out", self.shaker.fade_out))
            at_rest = {ControllerState.AT_STATIC, ControllerState.ALARM}
            steps.append(("wait at static", lambda: self.shaker.wait_for(at_rest, 30.0)))
            done.append("faded out")
        steps += [("stop", self.shaker.stop), ("hydraulics off", lambda: self.shaker.hydraulics(False))]
        done += ["STOP", "hydraulics off"]
        failed = []
        with self.shaker.link_patience(patience):
            for name, step in steps:
                try:
                    step()
                except Exception as exc:  # noqa: BLE001 — every step is tried; each failure is on record
                    failed.append(f"{name}: {exc}")
                    self.bus.publish(Kind.LOG, None, message=f"safe stop: {name} failed ({exc})")
        self.bus.publish(Kind.LOG, None, message=f"safe stop done: {', '.join(done)}" if not failed
                         else f"safe stop incomplete: {len(failed)} of {len(steps)} steps failed")
        self._enter(Phase.IDLE, None, **self._read_state(patience))
        return failed

    def _read_state(self, patience_s: float) -> dict[str, Any]:
        """The controller's state as read after a stop (``controller``: None where it could
        not be read, with ``unread``: why), so that the sentence after it says what the
        controller said, not what the program asked of it."""
        try:
            with self.shaker.link_patience(patience_s):
                st = self.shaker.status()
        except Exception as exc:  # noqa: BLE001 — unread is a fact to say, not an error to raise
            return {"controller": None, "unread": str(exc)}
        return {"controller": st.state, "alarm": st.alarm}
