"""The E-STOP on its own (rig.drivers.estop): the two writes on its own line by byte replay and
against the in-process simulator, also while another thread holds the main link in a
slow transaction; the latch that keeps motion commands in the program until the
operator confirms a reset.

Nothing here waits on the wall clock for a result: the threads are synchronised on
events (a wall-clock timeout only guards against a hang), and the press-to-answer time
is measured on a fake clock that each request on the E-STOP's line advances by a slow
line's transaction time; a wait behind the main link would hang, not just be slow.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

from rig.config import DEFAULT_RIG_CONFIG
from rig.drivers.estop import BUDGET_S, EStop, EStopLatched, LatchChanged, MotionLatch
from rig.drivers.registers import load_register_map
from rig.drivers.shaker import Shaker
from rig.gui.messages import Notice
from rig.gui.station import Station
from rig.session.acquisition import Acquisition
from rig.session.run import RunOptions
from tests.conftest import HANG_S
from tests.test_rig_drivers import LIMITS, ModbusReplay
from tests.virtual_rig_inprocess import SHAKER_URL, InProcessModbusClient, InProcessRig

# Each request on the E-STOP's line takes this long on the fake clock: a slow line (a
# Modbus RTU request and its answer at 115200 Bd take about 2 ms; the rest is room for a
# slow controller).  Two of them must fit the budget with nothing else added.
TRANSACTION_S = 0.1
MAP = load_register_map()
CONNECT = ("0001 0000 000d 01 10 0006 0003 06 fc18 6978 1388", "0001 0000 0006 01 10 0006 0003")  # the limits
STOP = ("0002 0000 0009 01 10 0000 0001 02 0000", "0002 0000 0006 01 10 0000 0001")              # mode = 0
HYDRAULICS_OFF = ("0003 0000 0006 01 05 0000 0000", "0003 0000 0006 01 05 0000 0000")            # coil 0 off
STATUS = ("0001 0000 0006 01 04 0000 0007", "0001 0000 0011 01 04 0e 0004 0000 33f4 01f4 0000 0834 007b")  # RUNNING


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0
        self._lock = threading.Lock()

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        with self._lock:
            self.t += seconds


class TimedClient:
    """A pymodbus-like client whose every request takes :data:`TRANSACTION_S` on ``clock``."""

    def __init__(self, client: Any, clock: FakeClock) -> None:
        self._client, self._clock = client, clock

    def connect(self) -> bool:
        return self._client.connect()

    def close(self) -> None:
        self._client.close()

    def __getattr__(self, name: str) -> Any:
        request = getattr(self._client, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            self._clock.advance(TRANSACTION_S)
            return request(*args, **kwargs)
        return timed


class HeldClient:
    """A client whose next status read does not return until :attr:`release` is set: a
    slow transaction, holding the driver's link while it lasts."""

    def __init__(self, client: Any) -> None:
        self._client = client
        self.entered, self.release = threading.Event(), threading.Event()

    def connect(self) -> bool:
        return self._client.connect()

    def close(self) -> None:
        self._client.close()

    def read_input_registers(self, *args: Any, **kwargs: Any) -> Any:
        self.entered.set()
        assert self.release.wait(HANG_S), "the slow transaction was never released"
        return self._client.read_input_registers(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._client, name)


def held(shaker: Shaker, client: HeldClient) -> threading.Thread:
    """Another thread in a slow status read on ``shaker``, returned once it holds the link."""
    thread = threading.Thread(target=shaker.status, name="slow-transaction", daemon=True)
    thread.start()
    assert client.entered.wait(HANG_S)
    return thread


@pytest.fixture
def vrig() -> Iterator[InProcessRig]:
    rig = InProcessRig(DEFAULT_RIG_CONFIG)
    rig.connect()
    yield rig
    rig.close()


def test_both_writes_go_out_on_the_estop_line_byte_for_byte_while_the_main_link_is_held():
    replay = ModbusReplay([CONNECT, STOP, HYDRAULICS_OFF])
    main_replay = ModbusReplay([STATUS])
    clock = FakeClock()
    main_client = HeldClient(ModbusTcpClient("127.0.0.1", port=main_replay.port, timeout=1, retries=0))
    main = Shaker(f"tcp://127.0.0.1:{main_replay.port}", LIMITS, MAP, client=main_client)
    assert main_client.connect()
    estop = EStop(LIMITS, MAP, fallback=lambda: main, clock=clock)
    url = f"tcp://127.0.0.1:{replay.port}"
    estop.open(url, client=TimedClient(ModbusTcpClient("127.0.0.1", port=replay.port, timeout=1, retries=0), clock))
    slow = held(main, main_client)
    try:
        estop.press()
        done = estop.wait(HANG_S)
        assert done is not None, "the E-STOP's writes were never answered"
        assert slow.is_alive()                          # answered while the main link was still held
        assert (done.failures, done.line) == ([], "E-STOP line")
        assert done.elapsed_s == pytest.approx(2 * TRANSACTION_S) and done.within_budget
        assert 2 * TRANSACTION_S <= BUDGET_S
    finally:
        main_client.release.set()
        slow.join(HANG_S)
        estop.close()
        main.close()
    replay.check()
    main_replay.check()


def test_without_its_own_line_the_estop_uses_the_active_link():
    replay = ModbusReplay([CONNECT, STOP, HYDRAULICS_OFF])
    link = Shaker(f"tcp://127.0.0.1:{replay.port}", LIMITS, MAP, reconnect_s=0.5)
    link.connect(heartbeat=False)
    estop = EStop(LIMITS, MAP, fallback=lambda: link)
    estop.press()
    done = estop.wait(HANG_S)
    estop.close()
    link.close()
    replay.check()
    assert done is not None and (done.failures, done.line) == ([], "session/console link")


def test_with_no_link_at_all_the_estop_says_so():
    estop = EStop(LIMITS, MAP)
    estop.press()
    done = estop.wait(HANG_S)
    estop.close()
    assert done is not None and not done.within_budget
    assert done.failures == ["STOP: no controller address", "hydraulics off: no controller address"]


def running(vrig: InProcessRig) -> None:
    """Hydraulics on, at 133 mm, a 10 mm 2 Hz sine faded in: the rig moving."""
    vrig.shaker.move_to(0.133, switch_on=True)
    vrig.shaker.wait_for({"AT_STATIC"}, 30.0)
    vrig.shaker.run(0.133, 0.010, 2.0, "sine", 1.0)
    vrig.shaker.wait_for({"RUNNING"}, 30.0)
    vrig.clock.sleep(2.0)


def test_estop_stops_the_simulated_rig_while_the_main_link_is_held_and_latches_motion(vrig):
    running(vrig)
    clock = FakeClock()
    changes: list[LatchChanged] = []
    held_client = HeldClient(vrig.client)
    main = Shaker(SHAKER_URL, LIMITS, MAP, client=held_client, clock=vrig.clock)
    estop = EStop(LIMITS, MAP, fallback=lambda: main, clock=clock)
    main.interlock = estop.latch
    estop.subscribe(changes.append)
    estop.open(SHAKER_URL, client=TimedClient(InProcessModbusClient(vrig.sim.controller, vrig.clock), clock))
    slow = held(main, held_client)
    try:
        estop.press()
        done = estop.wait(HANG_S)
        assert done is not None and slow.is_alive()
        assert (done.failures, done.line) == ([], "E-STOP line")
        assert done.elapsed_s == pytest.approx(2 * TRANSACTION_S) and done.within_budget
    finally:
        held_client.release.set()
        slow.join(HANG_S)
    vrig.clock.sleep(1.0)
    st = vrig.shaker.status()
    assert (st.state, vrig.sim.controller.read_coils(0, 1)[0]) == ("OFF", False)
    position = st.position_m

    # Latched: every motion command is refused before anything is sent, on any link sharing the latch.
    holding = vrig.sim.controller.read_holding(0, 6)
    for command in (lambda: main.hydraulics(True), lambda: main.move_to(0.133, switch_on=True),
                    lambda: main.run(0.133, 0.010, 2.0), main.fade_out):
        with pytest.raises(EStopLatched, match="refused, nothing sent: E-STOP pressed at"):
            command()
    assert vrig.sim.controller.read_holding(0, 6) == holding
    assert vrig.sim.controller.read_coils(0, 1)[0] is False
    main.stop()                                     # the safe commands still go out
    main.hydraulics(False)
    vrig.clock.sleep(1.0)
    assert vrig.shaker.status().position_m == pytest.approx(position, abs=1e-4)    # held, not moving

    estop.confirm_reset()
    main.hydraulics(True)
    assert vrig.sim.controller.read_coils(0, 1)[0] is True
    assert [c.latched for c in changes] == [True, False]
    estop.close()


def test_the_console_refuses_motion_and_sessions_while_latched_and_not_after_the_reset(tmp_path):
    posted: list[object] = []
    station = Station(None, None, posted.append)
    try:
        station.emergency.press()
        assert station.emergency.wait(HANG_S) is not None
        assert station.emergency.latched
        (refusal,) = station.manual.hydraulics(True, None)
        assert refusal.startswith("E-STOP pressed at") and refusal.endswith("confirm the reset first")
        assert station.manual.hydraulics(False, None) == ["not connected"]       # switching off is never vetoed
        assert station.sessions.run_plan(RunOptions(plan="standard", shaker=None, daq=None, out=tmp_path / "s"),
                                        False) is False
        assert not (tmp_path / "s").exists()
        assert any(isinstance(p, Notice) and p.text.startswith("session refused, nothing sent: E-STOP")
                   for p in posted)
        assert [p.latched for p in posted if isinstance(p, LatchChanged)] == [True]
        station.emergency.confirm_reset()
        assert station.manual.hydraulics(True, None) == ["not connected"]
        assert [p.latched for p in posted if isinstance(p, LatchChanged)] == [True, False]
    finally:
        station.close()


def test_a_sessions_safe_stop_after_an_estop_does_not_fade(vrig):
    """A fade is a move to the static position: once latched, the safe stop goes straight to
    STOP and hydraulics off, and says why it did not fade (not a failed step)."""
    running(vrig)
    latch = MotionLatch()
    vrig.shaker.interlock = latch
    latch.trip("E-STOP pressed at 10:00:00")
    assert Acquisition(vrig.shaker, vrig.daq, vrig.config, vrig.bus, vrig.clock).safe_stop("E-STOP") == []
    assert "safe stop: no fade (fade out refused, nothing sent: E-STOP pressed at 10:00:00; the operator must " \
           "confirm the reset first)" in vrig.messages()
    assert "safe stop done: stream stopped, STOP, hydraulics off" in vrig.messages()
    assert vrig.sim.controller.read_holding(0, 1) == [0] and vrig.sim.controller.read_coils(0, 1) == [False]
