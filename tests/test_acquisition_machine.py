"""The acquisition state machine and the session's error boundary, deterministically:
the rig package's drivers against the virtual rig in this process, on simulated time
(tests/virtual_rig_inprocess.py).  Faults, Ctrl-C and link outages are timed in
simulated seconds after a phase begins, so each lands where it is meant to whatever
the machine's load, and every run is the same."""

from __future__ import annotations

import errno
import json
import math
import re
import signal
import threading
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from identify.exit_codes import EXIT_ABORTED, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK
from identify.plans import STANDARD_SET
from rig.config import CHANNELS, load_rig_config
from rig.drivers.shaker import AlarmError
from rig.events import Event, Kind
from rig.session.acquisition import POLL_S, STATUS_POLL_S, Acquisition, ExperimentRecord, Interrupted, Recorder
from rig.session.outcome import ExitStatus
from rig.session.progress import describe
from simulator.controller import Alarm, State
from tests.virtual_rig_inprocess import SHAKER_URL, InProcessRig, quick_rig_config

J, N = (next(s for s in STANDARD_SET if s.letter == x) for x in "jn")   # 2 Hz: short experiments
SAFE_STOP_DONE = "safe stop done: stream stopped, STOP, hydraulics off"                 # it was not running
SAFE_STOP_FADED = "safe stop done: stream stopped, faded out, STOP, hydraulics off"     # it was
RESET = f"[Errno {errno.ECONNRESET}] Connection reset by peer"     # what the in-process client raises
LINK_LOST = f"Modbus link to {SHAKER_URL} lost ({RESET}); reconnecting"
LINK_GONE = f"Modbus link to {SHAKER_URL} lost and not back within 3 s ({RESET})"
# Once the safe stop found the link gone, each remaining step gets one quick try, said as the
# outage's length (not "within 0.5 s" beside "within 3 s", as if it had been waited for less).
LINK_STILL_GONE = re.escape(f"Modbus link to {SHAKER_URL} still not back, ") + r"\d+ s after it was lost " + \
    re.escape(f"({RESET})")
@pytest.fixture
def rig_config(tmp_path: Path) -> Path:
    return quick_rig_config(tmp_path)


@pytest.fixture
def vrig(rig_config: Path) -> Iterator[InProcessRig]:
    rig = InProcessRig(rig_config)
    rig.connect()
    yield rig
    rig.close()


def acquisition(vrig: InProcessRig) -> Acquisition:
    return Acquisition(vrig.shaker, vrig.daq, vrig.config, vrig.bus, vrig.clock)


def fault_time(vrig: InProcessRig, message: str) -> float:
    (t,) = [t for t, m in vrig.fault_log.entries if m == message]
    return t


def first_phase(vrig: InProcessRig, phase: str, experiment: str | None) -> float:
    return next(t for t, e, p in vrig.phases() if (e, p) == (experiment, phase))


def session_meta(out: Path) -> tuple[dict, dict]:
    return json.loads((out / "session.json").read_text()), json.loads((out / "dataset.json").read_text())


def assert_at_rest(vrig: InProcessRig, alarm: Alarm = Alarm.NONE) -> None:
    c = vrig.sim.controller
    assert (c.state, c.alarm, c.hydraulics_on) == (State.ALARM if alarm else State.OFF, alarm, False)
    assert not vrig.sim.daq.streaming


# ----- the state machine ----------------------------------------------------------------------------------
def test_the_pace_probe_times_the_commands_a_hold_and_an_experiment_add(vrig):
    """On the simulated clock the links answer at once: the pace is the rig's own, the
    commands between a hold's end and RUN take no time, and an experiment adds only
    the acquisition's polls (the capture's end seen half a poll late, two waits for
    AT_STATIC half a status poll late each)."""
    acq = acquisition(vrig)
    assert acq.measure_pace() == pytest.approx(1.0, rel=0.01)
    assert acq.answer_s == 0.0
    assert acq.overhead_s == pytest.approx(POLL_S / 2 + STATUS_POLL_S)
    (probe,) = [e for _, e in vrig.events if e.kind == Kind.PACE_PROBE]
    assert (probe.data["answer_s"], probe.data["probes"]) == (0.0, 5)
    assert probe.data["overhead_s"] == pytest.approx(0.045) and probe.data["pace"] == acq.probed_pace
    # and people read it in a sentence made from those fields
    assert re.search(r"from a hold's end to RUN 0\.0 ms, 0\.00 s of the rig's time; an experiment's polls and "
                     r"commands 45\.0 ms", describe(probe))


class _BusyHostLinks:
    """A simulator at 10x seen from a busy host, on an injected clock: each probe's
    stream and DAQ start take what the host lets them (one probe caught the simulator
    stalled, one caught it catching up, one DAQ start waited 300 ms for the CPU)."""

    rate_hz = 2000.0
    PACES = [10.0, 10.0, 6.95, 10.0, 11.5]
    STARTS_S = [0.004, 0.3, 0.004, 0.004, 0.004]

    def __init__(self) -> None:
        self.now, self.probe = 0.0, 0
        self.counters = type("Counters", (), {"lost_samples": 0})()

    # the clock
    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds

    # the DAQ
    def subscribe(self, _callback) -> None:
        pass

    def start(self) -> None:
        self.now += self.STARTS_S[self.probe]
        self.started = self.now

    def stop(self) -> int:
        issued = round(self.PACES[self.probe] * self.rate_hz * (self.now - self.started))
        self.now += 0.004
        self.probe += 1
        return issued

    # the controller
    def status(self) -> None:
        self.now += 0.001


def test_the_pace_is_the_median_of_several_probes_which_one_stalled_probe_does_not_move():
    from rig.events import EventBus

    links = _BusyHostLinks()
    acq = Acquisition(links, links, load_rig_config(), EventBus(), links)
    assert acq.measure_pace() == pytest.approx(10.0)
    assert acq.current_pace() == pytest.approx(10.0)
    # the median DAQ start (4 ms), not the 300 ms one: a hold's end to RUN is its
    # start and stop and three status reads
    assert acq.answer_s == pytest.approx(0.004 + 0.004 + 3 * 0.001)


def test_the_session_corrects_the_probed_pace_from_its_own_streams():
    """Once the session has streamed PACE_FROM_STREAMS_S, the pace shown (the rig time
    a session says it took) is the samples its DAQ took against the time it streamed."""
    from rig.events import EventBus
    from rig.session.acquisition import PACE_FROM_STREAMS_S

    links = _BusyHostLinks()
    links.PACES = [6.95] * 5       # every probe on a starved simulator
    acq = Acquisition(links, links, load_rig_config(), EventBus(), links)
    assert acq.measure_pace() == pytest.approx(6.95)
    since = links.now
    links.now += PACE_FROM_STREAMS_S / 2
    acq._count_stream(round(10.0 * links.rate_hz * PACE_FROM_STREAMS_S / 2), since)
    assert acq.current_pace() == pytest.approx(6.95)      # too short a stream to say
    since = links.now
    links.now += PACE_FROM_STREAMS_S
    acq._count_stream(round(10.0 * links.rate_hz * PACE_FROM_STREAMS_S), since)
    assert acq.current_pace() == pytest.approx(10.0)


def test_settles_then_captures_the_planned_whole_periods(vrig):
    record = acquisition(vrig).run_experiment(J, "261122j")

    assert [(e, p) for _, e, p in vrig.phases()] == \
        [("261122j", p) for p in ("moving", "settling", "capturing", "stopping", "idle")]
    # settled at the first comparison whose changes were all below the thresholds
    ss = vrig.config.steady_state
    progress = [e.data for _, e in vrig.events if e.kind == "progress" and e.data["phase"] == "settling"]
    below = [all(p["change"][c] < ss.thresholds[c] for c in CHANNELS) for p in progress]
    assert len(below) >= 2 and below[-1] and not any(below[:-1])
    assert record.settled and record.settle_cycles == progress[-1]["cycles"] >= 20
    assert f"steady state after {record.settle_cycles} cycles" in vrig.messages()
    # the window: 3 whole periods right after the last settling block, nothing lost
    rate, spp = 2000, 1000
    start = math.ceil((ss.ramp_time_s + 0.5) * rate)
    assert np.array_equal(record.index, start + record.settle_cycles * spp + np.arange(3 * spp))
    assert (record.lost_samples, record.stream_lost, record.recaptures, record.flags) == (0, 0, 0, [])
    stroke = record.values[:, 0]
    assert stroke.min() == pytest.approx(133 - 10, abs=0.3) and stroke.max() == pytest.approx(133 + 10, abs=0.3)
    # the fade-out took the ramp time before the shaker was stopped at its static position
    assert first_phase(vrig, "idle", "261122j") - first_phase(vrig, "stopping", "261122j") >= ss.ramp_time_s
    c = vrig.sim.controller
    assert (c.state, c.alarm) == (State.IDLE, Alarm.NONE) and c.position_m == pytest.approx(0.133, abs=1e-4)


def run_n_alone(rig_config: Path) -> tuple[ExperimentRecord, list[tuple[float, str | None, str]]]:
    rig = InProcessRig(rig_config)
    try:
        rig.connect()
        return acquisition(rig).run_experiment(N, "261122n"), rig.phases()
    finally:
        rig.close()


def test_a_run_is_the_same_whatever_the_load(rig_config):
    quiet, phases_quiet = run_n_alone(rig_config)
    stop = threading.Event()

    def compete() -> None:                              # takes the interpreter from the rig's threads
        while not stop.is_set():
            sum(range(10_000))

    hog = threading.Thread(target=compete)
    hog.start()
    try:
        loaded, phases_loaded = run_n_alone(rig_config)
    finally:
        stop.set()
        hog.join()
    assert phases_loaded == phases_quiet                # every transition at the same simulated time
    assert np.array_equal(loaded.index, quiet.index) and np.array_equal(loaded.values, quiet.values)


def test_samples_lost_in_the_capture_window_are_captured_again(vrig):
    vrig.when("capturing", 0.5, lambda: vrig.inject("overflow=300"))
    record = acquisition(vrig).run_experiment(J, "261122j")

    windows = [e.data for _, e in vrig.events if e.kind == Kind.CAPTURE_WINDOW]
    assert [(w["window"], w["lost"], w["kept"], w["again"]) for w in windows] == [(1, 300, False, True)]
    assert (record.recaptures, record.lost_samples, record.stream_lost, record.flags) == (1, 0, 300, [])
    first_window = math.ceil((vrig.config.steady_state.ramp_time_s + 0.5) * 2000) + record.settle_cycles * 1000
    assert np.array_equal(record.index, first_window + 3000 + np.arange(3000))   # the second window, whole
    assert vrig.sim.daq.lost["overflow"] == 300


def test_a_window_that_keeps_losing_samples_is_kept_and_flagged(vrig):
    vrig.when("capturing", 0.0, lambda: vrig.inject("drop=0.01"))
    record = acquisition(vrig).run_experiment(J, "261122j")

    assert record.recaptures == vrig.config.steady_state.max_recaptures == 2
    assert record.lost_samples > 0 and len(record.index) == 3000 - record.lost_samples
    assert record.flags == [f"{record.lost_samples} samples lost in the captured window (rows absent; best of 3 "
                            "windows)"]
    windows = [e.data for _, e in vrig.events if e.kind == Kind.CAPTURE_WINDOW]
    assert [(w["window"], w["lost"] > 0, w["kept"], w["again"]) for w in windows] == \
        [(1, True, False, True), (2, True, False, True), (3, True, False, False)]


def test_an_estop_while_settling_raises_the_alarm_at_the_next_status_poll(vrig):
    acq = acquisition(vrig)
    vrig.when("settling", 3.0, lambda: vrig.inject("estop"))
    with pytest.raises(AlarmError, match=r"^shaker alarm: emergency stop \(stroke 1[23]\d\.\d\d mm"):
        acq.run_experiment(J, "261122j")
    assert [p for _, _, p in vrig.phases()] == ["moving", "settling", "alarm"]
    assert not vrig.sim.daq.streaming                  # the stream is stopped on the way out
    assert acq.safe_stop("alarm") == []
    assert_at_rest(vrig, Alarm.EMERGENCY_STOP)


# ----- the session's error boundary -------------------------------------------------------------------------
def test_an_alarm_aborts_the_session_after_the_safe_stop(vrig, tmp_path):
    vrig.when("settling", 3.0, lambda: vrig.inject("estop"))
    result = vrig.run_session(tmp_path / "s", ["j", "n"])

    (alarm,) = vrig.messages("alarm")
    assert alarm.startswith("shaker alarm: emergency stop (")
    assert (result.status, result.exit_code, result.error) == (f"aborted: {alarm}", EXIT_ABORTED, None)
    assert (result.exit_status, result.interrupted, result.reason) == (ExitStatus.ABORTED, True, alarm)
    assert isinstance(result.exception, AlarmError)
    # seen at the next status poll (every 0.2 s), and the safe stop began at once
    assert 0 <= round(first_phase(vrig, "stopping", None) - fault_time(vrig, "fault: emergency stop pressed"), 6) \
        <= 0.25
    assert SAFE_STOP_DONE in (tmp_path / "s" / "session.log").read_text()
    assert_at_rest(vrig, Alarm.EMERGENCY_STOP)
    meta, manifest = session_meta(tmp_path / "s")
    assert meta["status"] == result.status and manifest["experiments"] == []
    assert meta["outcome"] == {"exit_status": "aborted", "exit_code": EXIT_ABORTED, "interrupted": True,
                               "reason": alarm, "exception": f"AlarmError: {alarm}", "before_motion": False,
                               "skipped": [], "safe_stop_failures": []}
    assert "261122n" not in {e for _, e, _ in vrig.phases()}


def test_with_on_alarm_skip_the_next_experiment_is_captured(vrig, tmp_path):
    vrig.when("settling", 3.0, lambda: vrig.inject("estop"), experiment="261122j")
    result = vrig.run_session(tmp_path / "s", ["j", "n"], on_alarm="skip")

    assert (result.status, result.exit_code) == \
        ("ended: 1 of 2 experiments captured, skipped after alarms: 261122j", EXIT_OK)
    assert (result.exit_status, result.interrupted, result.skipped) == (ExitStatus.ENDED, False, ["261122j"])
    (alarm,) = vrig.messages("alarm")
    assert vrig.messages("experiment-failed") == [f"261122j skipped after the alarm ({alarm})"]
    assert [m for _, m in vrig.fault_log.entries if "reset" in m] == ["alarm emergency_stop reset"]
    meta, manifest = session_meta(tmp_path / "s")
    assert meta["status"] == result.status
    assert [(e["label"], e["steady_state"], e["lost_samples"]) for e in manifest["experiments"]] == \
        [("261122n", True, 0)]
    assert_at_rest(vrig)


def test_ctrl_c_fades_out_and_switches_the_hydraulics_off(vrig, tmp_path):
    # A real SIGINT, raised in this (the main) thread: the session's own handler must turn it into a
    # stop request; one that reached the handler outside the session would be a miss, not a crash of pytest.
    vrig.when("settling", 3.0, lambda: signal.raise_signal(signal.SIGINT))
    missed = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: missed.append(signum))
    try:
        result = vrig.run_session(tmp_path / "s", ["j"])
    finally:
        signal.signal(signal.SIGINT, previous)
    assert missed == []

    assert (result.status, result.exit_code, result.safe_stop_failures) == \
        ("interrupted (SIGINT)", EXIT_INTERRUPTED, [])
    assert (result.exit_status, result.reason, result.exception) == (ExitStatus.INTERRUPTED, "SIGINT", None)
    asked = first_phase(vrig, "settling", "261122j") + 3.0
    stopping, idle = first_phase(vrig, "stopping", None), first_phase(vrig, "idle", None)
    assert 0 <= round(stopping - asked, 6) <= 0.05       # honoured at the next poll
    assert idle - stopping >= vrig.config.steady_state.ramp_time_s   # faded out, not dropped
    assert vrig.messages("alarm") == [] and vrig.messages()[-1] == SAFE_STOP_FADED
    assert_at_rest(vrig)
    meta, manifest = session_meta(tmp_path / "s")
    assert meta["status"] == "interrupted (SIGINT)" and manifest["experiments"] == []
    assert (meta["outcome"]["exit_status"], meta["outcome"]["reason"]) == ("interrupted", "SIGINT")


def test_a_modbus_link_back_within_the_reconnect_time_is_ridden_through(vrig, tmp_path):
    vrig.when("settling", 3.0, lambda: vrig.client.cut(1.0))   # shorter than the watchdog's 2 s, too
    result = vrig.run_session(tmp_path / "s", ["j"])

    assert (result.status, result.exit_code) == ("complete", EXIT_OK)
    log = vrig.messages()
    assert log.count(LINK_LOST) == 1 and log.count(f"Modbus link to {SHAKER_URL} back") == 1
    assert log.index(LINK_LOST) < log.index(f"Modbus link to {SHAKER_URL} back")
    _, manifest = session_meta(tmp_path / "s")
    assert [(e["steady_state"], e["lost_samples"], e["stream_lost_samples"]) for e in manifest["experiments"]] == \
        [(True, 0, 0)]
    assert_at_rest(vrig)


def test_a_modbus_link_gone_for_good_aborts_and_the_watchdog_stops_the_shaker(vrig, tmp_path):
    vrig.when("settling", 3.0, lambda: vrig.client.cut(600.0))
    result = vrig.run_session(tmp_path / "s", ["j"])

    assert result.exit_code == EXIT_ABORTED
    assert all(re.fullmatch(f"{step}: {LINK_STILL_GONE}", failure) is not None
               for step, failure in zip(("stop", "hydraulics off"), result.safe_stop_failures, strict=True))
    assert re.fullmatch(re.escape(f"aborted: {LINK_GONE}; safe stop incomplete (") + f"stop: {LINK_STILL_GONE}; "
                        f"hydraulics off: {LINK_STILL_GONE}" + re.escape("): the controller's watchdog stops the "
                                                                         "shaker once this program has let go"),
                        result.status), result.status
    log = vrig.messages()
    unreadable = re.escape("safe stop: status unreadable (") + LINK_STILL_GONE + r"\)"
    assert any(re.fullmatch(unreadable, line) for line in log), log
    assert vrig.messages("log")[-1] == \
        "safe stop incomplete: 2 of 3 steps failed"
    # then the state is read once more, and what is said is that it could not be
    idle = [e for _, e in vrig.events if e.kind == "phase" and e.data["phase"] == "idle"]
    assert idle[-1].data["controller"] is None and re.match(LINK_STILL_GONE, idle[-1].data["unread"])
    assert not vrig.sim.daq.streaming                  # the DAQ, on its own link, was stopped
    c = vrig.sim.controller
    assert (c.state, c.alarm, c.hydraulics_on) == (State.ALARM, Alarm.WATCHDOG, False)   # no heartbeat got through
    assert session_meta(tmp_path / "s")[0]["status"] == result.status


def test_a_bug_in_the_acquisition_still_ends_in_the_safe_stop(vrig, tmp_path, monkeypatch):
    def broken_window(self: Recorder, a: int, b: int) -> None:
        raise TypeError("injected bug")

    monkeypatch.setattr(Recorder, "window", broken_window)   # first called once the first block is in
    result = vrig.run_session(tmp_path / "s", ["j"])

    assert (result.status, result.exit_code) == ("aborted: internal error: TypeError: injected bug", EXIT_INTERNAL)
    assert isinstance(result.error, TypeError) and str(result.error) == "injected bug"
    assert result.exit_status is ExitStatus.FAILED and result.exception is result.error
    assert [p for _, _, p in vrig.phases()] == ["moving", "settling", "stopping", "idle"]
    stopping, idle = first_phase(vrig, "stopping", None), first_phase(vrig, "idle", None)
    assert idle - stopping >= vrig.config.steady_state.ramp_time_s    # it was running: faded out
    log = (tmp_path / "s" / "session.log").read_text()
    assert "aborting on an internal error: TypeError: injected bug" in log and SAFE_STOP_FADED in log
    assert_at_rest(vrig)
    assert session_meta(tmp_path / "s")[0]["status"] == result.status


def shipped_config(tmp_path: Path, criterion: str, holds: bool = False) -> Path:
    """The default rig configuration with ``criterion`` selected: the real thresholds and
    drift settings, not the tests' relaxed ones (conditioning holds only if asked)."""
    from rig.config import DEFAULT_RIG_CONFIG

    path = tmp_path / f"rig-{criterion}{'-holds' if holds else ''}.toml"
    text = re.sub(r'(?m)^criterion = "\w+"', f'criterion = "{criterion}"', DEFAULT_RIG_CONFIG.read_text())
    path.write_text(text if holds else text.replace("max_hold_s = 300.0", "max_hold_s = 0.0"))
    return path


@pytest.mark.slow
@pytest.mark.parametrize(("letter", "criterion"), [("a", "change"), ("j", "change"), ("a", "drift"), ("j", "drift")])
def test_lost_samples_do_not_stretch_settling(tmp_path, letter, criterion):
    """Line faults while settling: neither criterion (the default change thresholds, or
    rig.planning.criterion's drift bound) may pass early nor, because the holes make the block
    means scatter, keep waiting (a took 109 cycles instead of 8, j 380 instead of 110)."""
    from identify.plans import STANDARD_SET, select

    config = shipped_config(tmp_path, criterion)

    def settle_cycles(faults: list[str]) -> tuple[int, int, list[float]]:
        rig = InProcessRig(config)
        rig.connect()
        try:
            for fault in faults:
                rig.when("settling", 0.0, partial(rig.inject, fault))
            (spec,) = select(STANDARD_SET, [letter])
            record = acquisition(rig).run_experiment(spec, f"261122{letter}")
            bounds = [e.data["bias_sigma"] for _, e in rig.events
                      if e.kind == "progress" and e.data["phase"] == "settling" and "bias_sigma" in e.data]
            return record.settle_cycles, record.stream_lost, bounds
        finally:
            rig.close()

    ss = load_rig_config(config).steady_state
    assert ss.criterion == criterion
    clean, none_lost, _ = settle_cycles([])
    faulted, lost, bounds = settle_cycles(["corrupt=0.001", "drop=0.0005"])
    assert none_lost == 0 and lost > 3000
    assert clean <= faulted <= 1.2 * clean, (clean, faulted)
    if ss.drift is not None:
        assert bounds[-1] < ss.drift.fraction <= min(bounds[:-1])


@pytest.mark.slow
def test_a_stall_while_settling_does_not_pass_the_drift_criterion_early(tmp_path):
    """The serial line stalls for 3 s early in j's settling: the DAQ's FIFO overflows and
    the blocks around it lose samples; the criterion starts its fit again after them
    instead of reading the gap as a settled stretch."""
    from identify.plans import STANDARD_SET, select

    config = shipped_config(tmp_path, "drift")

    def run(faults: list[str]) -> int:
        rig = InProcessRig(config)
        rig.connect()
        try:
            for fault in faults:
                rig.when("settling", 10.0, partial(rig.inject, fault))
            (spec,) = select(STANDARD_SET, ["j"])
            return acquisition(rig).run_experiment(spec, "261122j").settle_cycles
        finally:
            rig.close()

    clean, stalled = run([]), run(["stall=3"])
    assert clean <= stalled <= 1.2 * clean, (clean, stalled)


def hold_before(config: Path, letters: str) -> tuple[list, list]:
    """The plan of ``letters`` on ``config`` (from rest at 0 mm): its experiments and their
    predicted durations, each with its conditioning hold."""
    from identify.plans import select
    from rig.planning.plans import Plan, estimate_experiment_durations

    specs = select(STANDARD_SET, list(letters))
    return specs, estimate_experiment_durations(Plan("t", tuple(specs)), load_rig_config(config))


@pytest.mark.slow
def test_a_conditioning_hold_lands_the_gas_and_settling_is_short(tmp_path):
    """c after j: the move up compresses the gas by ~90 K, which relaxes slowly where the wall
    area is small (335 s on the change criterion).  The planned hold, above c's position,
    ends on the measured gas temperature the model asks for, and the drift criterion
    settles c in a fraction of the cycles it needs from a direct move."""
    config = shipped_config(tmp_path, "drift", holds=True)
    specs, planned = hold_before(config, "jc")
    hold = planned[1].hold
    assert hold is not None and hold.position_m > specs[1].static_position_mm * 1e-3

    def settle_c(with_hold: bool) -> tuple[int, list[Event]]:
        rig = InProcessRig(config)
        rig.connect()
        try:
            acq = acquisition(rig)
            acq.run_experiment(specs[0], "261122j", planned[0].hold, planned[0].time_constant_s)
            record = acq.run_experiment(specs[1], "261122c", hold if with_hold else None, planned[1].time_constant_s)
            return record.settle_cycles, [e for _, e in rig.events if e.kind in (Kind.HOLD, Kind.HOLD_END)
                                          and e.experiment == "261122c"]
        finally:
            rig.close()

    held, log = settle_c(True)
    direct, none = settle_c(False)
    assert none == [] and [e.kind for e in log] == [Kind.HOLD, Kind.HOLD_END], log
    end = log[1].data
    assert end["gas_c"] == pytest.approx(hold.end_temperature_k - 273.15, abs=0.2)
    assert end["target_c"] == pytest.approx(hold.end_temperature_k - 273.15) and end["held_s"] > 0
    # The simulator's actuator tracks its setpoint through a 25 Hz second-order loop: a
    # delay of about 9 ms, which the gas, changing ~1 K/s at the hold, would turn into
    # a landing error the drift criterion waits out for tens of cycles.
    assert 3 <= end["lead_s"] * 1e3 <= 30, end
    assert held < 0.6 * direct, (held, direct)


def test_ctrl_c_during_a_conditioning_hold_ends_in_the_safe_stop(tmp_path):
    config = shipped_config(tmp_path, "change", holds=True)
    specs, planned = hold_before(config, "jc")
    assert planned[1].hold is not None
    vrig = InProcessRig(config)
    vrig.connect()
    try:
        acq = acquisition(vrig)
        acq.run_experiment(specs[0], "261122j")
        vrig.when("moving", 1.0, acq.stop_requested.set, experiment="261122c")
        with pytest.raises(Interrupted):
            acq.run_experiment(specs[1], "261122c", planned[1].hold)
        assert [e.experiment for _, e in vrig.events if e.kind == Kind.HOLD] == ["261122c"]
        assert acq.safe_stop("interrupted") == []
        assert vrig.messages()[-1] == SAFE_STOP_DONE
        assert_at_rest(vrig)
    finally:
        vrig.close()
