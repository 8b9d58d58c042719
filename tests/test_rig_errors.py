"""The rig's error paths in-process, on an injected clock: lost Modbus links raised as
OSError, subscriber failures, and the exception tree the CLI maps to exit codes."""

from __future__ import annotations

import logging
import threading
from types import SimpleNamespace

import pytest

from rig.config import load_rig_config
from rig.drivers.shaker import Shaker, ShakerAddress, ShakerLinkError
from rig.errors import AddressError, BadInput, RigFault
from rig.events import FIELDS, EventBus, Kind, Phase


class StepClock:
    """Simulated time that passes only when somebody sleeps."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class FlakyClient:
    """A pymodbus-like client whose requests raise ``ConnectionResetError`` until
    ``down_until`` (simulated seconds); the inputs table reads an idle controller."""

    def __init__(self, clock: StepClock, down_until: float) -> None:
        self.clock, self.down_until = clock, down_until
        self.requests = 0

    def connect(self) -> bool:
        return True

    def close(self) -> None:
        pass

    def _answer(self, **fields):
        self.requests += 1
        if self.clock.now < self.down_until:
            raise ConnectionResetError(104, "Connection reset by peer")
        return SimpleNamespace(isError=lambda: False, **fields)

    def read_input_registers(self, address, count, device_id):
        return self._answer(registers=[1, 0, 13300, 500, 0, 2100, 123][:count])

    def write_registers(self, address, values, device_id):
        return self._answer(registers=values)

    def write_coil(self, address, value, device_id):
        return self._answer(bits=[value])


def shaker(clock: StepClock, client: FlakyClient, events: list[str], reconnect_s: float = 5.0) -> Shaker:
    limits = load_rig_config().limits
    return Shaker("tcp://127.0.0.1:1", limits, reconnect_s=reconnect_s,
                  on_event=lambda notice: events.append(notice.message), client=client, clock=clock)


def test_a_connection_reset_within_the_reconnect_time_is_a_lost_and_found_link():
    clock, events = StepClock(), []
    client = FlakyClient(clock, down_until=2.0)
    status = shaker(clock, client, events).status()
    assert status.state == "IDLE" and status.position_m == pytest.approx(0.133)
    assert events == ["Modbus link to tcp://127.0.0.1:1 lost ([Errno 104] Connection reset by peer); reconnecting",
                      "Modbus link to tcp://127.0.0.1:1 back"]
    assert 2.0 <= clock.now < 3.1                       # backed off, on the injected clock


def test_a_connection_reset_beyond_the_reconnect_time_is_a_rig_fault():
    clock, events = StepClock(), []
    with pytest.raises(ShakerLinkError, match=r"lost and not back within 5 s \(\[Errno 104\]"):
        shaker(clock, FlakyClient(clock, down_until=1e9), events).hydraulics(False)
    assert isinstance(ShakerLinkError("x"), RigFault)
    assert 5.0 <= clock.now < 6.1


@pytest.mark.parametrize("url, ok", [("tcp://127.0.0.1:5020", True), ("rtu:///dev/ttyUSB0", True),
                                     ("tpc://127.0.0.1:5020", False), ("tcp://127.0.0.1", False),
                                     ("tcp://:5020", False), ("tcp://127.0.0.1:99999", False), ("", False)])
def test_shaker_addresses_are_checked_by_form(url, ok):
    if ok:
        assert ShakerAddress.parse(url).url == url
    else:
        says = "port '99999' is not a TCP port" if url.endswith("99999") else "expected tcp://HOST:PORT or rtu:///"
        with pytest.raises(AddressError, match=says):
            ShakerAddress.parse(url)
    assert issubclass(AddressError, BadInput)


def test_a_failing_queued_subscriber_is_logged_and_the_others_still_get_every_event(caplog):
    bus, got, done = EventBus(), [], threading.Event()

    def broken(event):
        raise RuntimeError(f"display broke on {event.kind}")

    def fine(event):
        got.append(event.kind)
        if event.kind == "session-end":
            done.set()

    bus.subscribe(broken)
    bus.subscribe(fine)
    with caplog.at_level(logging.ERROR, logger="rig.events"):
        bus.publish(Kind.SESSION_START, shaker="tcp://rig:502", daq="socket://rig:4001", identity="DAQ4,test")
        bus.publish(Kind.PHASE, phase=Phase.IDLE, clock_s=0.0)
        bus.publish(Kind.SESSION_END, message="complete", exit_code=0, exit_status="complete")
        assert done.wait(10)
        bus.close()
    assert got == ["session-start", "phase", "session-end"]
    first, total = caplog.records
    assert "failed on a 'session-start' event" in first.getMessage() and "display broke" in first.exc_text
    assert "failed on 3 events in all" in total.getMessage()


def test_a_failing_inline_subscriber_reaches_the_publisher():
    bus = EventBus()
    bus.subscribe(lambda event: (_ for _ in ()).throw(OSError("disk full")), inline=True)
    with pytest.raises(OSError, match="disk full"):
        bus.publish(Kind.LOG, message="written")


def test_event_kinds_and_their_fields_are_declared_once():
    bus = EventBus()
    with pytest.raises(TypeError, match="publish takes a Kind, not str 'captured'"):
        bus.publish("captured")  # mypy refuses it in checked code; this test body is not checked
    with pytest.raises(TypeError, match="experiment-done event without samples, lost, flags"):
        bus.publish(Kind.EXPERIMENT_DONE, "261122j", file="261122j.csv")
    assert set(FIELDS) == set(Kind)


def test_the_recorder_holds_a_bounded_stretch_however_long_the_stream():
    import numpy as np

    from rig.drivers.daq import Samples
    from rig.session.acquisition import Recorder

    rec, block = Recorder(), 10_000
    for k in range(300):                                 # 3 million samples, read block by block
        index = np.arange(k * block, (k + 1) * block)
        rec(Samples(index, np.column_stack([index, -index, index, -index]).astype(float),
                    np.zeros(block, dtype=np.uint8)))
        if k:
            values, present, _ = rec.window((k - 1) * block, k * block)
            assert present.all() and values[0, 0] == (k - 1) * block and values[-1, 1] == -(k * block - 1)
            rec.forget_before(k * block)
    assert rec.end == 300 * block and rec.held <= 4 * 65536
    with pytest.raises(ValueError, match="were forgotten"):
        rec.window(0, 10)
    # A late block of a forgotten stretch is ignored; the holes of a lost sample stay holes.
    rec(Samples(np.array([5, 3 * 10**6 + 7]), np.ones((2, 4)), np.zeros(2, dtype=np.uint8)))
    _, present, _ = rec.window(3 * 10**6, 3 * 10**6 + 8)
    assert present.tolist() == [False] * 7 + [True]


def test_block_means_with_holes_are_those_of_the_whole_block():
    import numpy as np

    from rig.session.acquisition import MAX_LOST_IN_BLOCK, block_means

    spp, cycles = 50_000, 1                              # a 0.04 Hz cycle at 2 kHz
    phase = 2 * np.pi * np.arange(spp * cycles) / spp
    signal = np.column_stack([133 + 127 * np.sin(phase + 0.3), 800 * np.sin(phase) * np.abs(np.sin(phase)),
                              9 + np.cos(phase), 20 + 0 * phase])
    index = np.arange(spp * cycles)
    whole = block_means(signal, np.ones(len(phase), dtype=bool), index, spp)
    holes = np.random.default_rng(1).random(len(phase)) < 0.016  # 1.6 % lost, as with corrupt + drop
    plain = signal[~holes].mean(axis=0)
    fitted = block_means(signal, ~holes, index, spp)
    assert fitted is not None and whole is not None
    # The plain mean of what is left misses by far more than the stroke threshold (0.02 mm)...
    assert abs(plain[0] - whole[0]) > 0.02 or abs(plain[1] - whole[1]) > 5.0
    # ... the harmonic fit misses by less than a hundredth of each channel's threshold.
    thresholds = np.array(list(load_rig_config().steady_state.thresholds.values()))
    assert np.all(np.abs(fitted - whole) < 0.01 * thresholds), fitted - whole
    stalled = np.ones(len(phase), dtype=bool)
    stalled[: int((MAX_LOST_IN_BLOCK + 0.01) * len(phase))] = False
    assert block_means(signal, stalled, index, spp) is None


def test_block_means_of_several_cycles_with_holes_hold_for_any_harmonic_content():
    """d (1 Hz, 20 mm) in blocks of 5 cycles: the friction's arctan(2000 q̇) switches within a
    few milliseconds, harmonics far beyond the dozen a fit would take.  The folded mean of
    a block with 1.6 % of its samples lost is the whole block's, to well below the noise
    of a block mean (2 N / √10000 for the force); the fit of 12 harmonics is not."""
    import numpy as np

    from rig.session.acquisition import HARMONICS_IN_BLOCK_MEAN, block_means

    spp, cycles = 2000, 5
    index = np.arange(spp * cycles) + 777                        # a block starts anywhere in the cycle
    phase = 2 * np.pi * index / spp
    velocity = 0.02 * 2 * np.pi * np.cos(phase)
    signal = np.column_stack([229 + 20 * np.sin(phase), 8437 + 200 * np.sin(phase) + 80 * np.arctan(2000 * velocity),
                              17.5 + 0.4 * np.sin(phase), 22 + 0 * phase])
    whole = block_means(signal, np.ones(len(index), dtype=bool), index, spp)
    present = np.random.default_rng(2).random(len(index)) >= 0.016
    folded = block_means(signal, present, index, spp)
    assert whole is not None and folded is not None
    block_noise_n = 2.0 / np.sqrt(len(index))
    assert abs(folded[1] - whole[1]) < 0.01 * block_noise_n, folded[1] - whole[1]
    k = np.outer(phase[present], np.arange(1, HARMONICS_IN_BLOCK_MEAN + 1))
    design = np.column_stack([np.ones(len(k)), np.cos(k), np.sin(k)])
    harmonic_fit = np.linalg.lstsq(design, signal[present, 1], rcond=None)[0][0]
    assert abs(harmonic_fit - whole[1]) > 0.2 * block_noise_n   # what folding is for
