"""The console's rig side, piece by piece (no window, no rig): the status poller reads
whichever links hold the rig and says whose they are, the session worker hands a stop
to the runner (also one asked for before the runner existed), the E-STOP stops the
session too, manual control refuses with its reasons; and the console's exit status
after Ctrl-C is 130, as README's exit table says."""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import dataclass, field
from types import SimpleNamespace

import pytest

from identify.exit_codes import EXIT_INTERRUPTED
from rig.drivers.shaker import ShakerLinkError
from rig.gui.emergency import PRESSED
from rig.gui.manual import Heartbeat
from rig.gui.messages import Notice, Snapshot
from rig.gui.station import Station
from rig.gui.status_poller import StatusPoller
from tests.conftest import HANG_S


@dataclass
class FakeShaker:
    state: str = "IDLE"
    fail: bool = False
    interlock: object = None

    def status(self, patience_s: float | None = None) -> SimpleNamespace:
        if self.fail:
            raise ShakerLinkError("controller at tcp://x:1 not answering")
        return SimpleNamespace(state=self.state, alarm="none", position_m=0.133, hydraulic_pressure_pa=2e7)


@dataclass
class FakeDaq:
    streaming: bool = True
    parser: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(received=1234, next_index=1200))
    counters: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(
        lost_samples=1, crc_errors=2, over_range=3, overflow_flags=4))


@dataclass
class FakeRunner:
    """What the worker reaches of a SessionRunner: its links and request_stop."""

    links: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(shaker=FakeShaker(), daq=FakeDaq()))
    stops: list[str] = field(default_factory=list)
    said: list[str] = field(default_factory=list)

    @property
    def bus(self) -> SimpleNamespace:
        return SimpleNamespace(publish=lambda kind, **data: self.said.append(data["message"]))

    def request_stop(self, reason: str) -> None:
        self.stops.append(reason)


@pytest.fixture
def station():
    posted: list[object] = []
    st = Station(None, None, posted.append)
    st.posted = posted
    yield st
    st.close()


def test_the_poller_reads_the_links_that_hold_the_rig_and_says_whose():
    shaker, daq = FakeShaker("RUNNING"), FakeDaq()
    links = [(shaker, daq, True)]
    poller = StatusPoller(lambda: links[-1], lambda m: None, lambda: True, period_s=3600)
    try:
        snap = poller.read()
        assert isinstance(snap, Snapshot) and snap.status.state == "RUNNING" and snap.error is None
        assert (snap.session, snap.streaming, snap.received, snap.samples) == (True, True, 1234, 1200)
        assert (snap.lost, snap.crc_errors, snap.over_range, snap.overflow_flags) == (1, 2, 3, 4)
        daq.streaming = False
        assert poller.read().streaming is False                # between experiments a session does not stream
        links.append((FakeShaker(fail=True), None, False))
        snap = poller.read()
        assert snap.status is None and "not answering" in snap.error and not snap.session and not snap.streaming
        links.append((None, None, False))
        assert poller.read() is None                           # no links: nothing to say about the rig
    finally:
        poller.close()


def test_the_worker_hands_a_stop_to_the_runner_even_one_asked_for_before_it_existed(station):
    runner = FakeRunner()
    station.sessions.request_stop("Abort pressed by the operator")     # while the links are being opened
    station.sessions._runner_changed(runner)
    assert runner.stops == ["Abort pressed by the operator"]
    assert runner.said == ["Abort pressed by the operator: safe stop"]       # in session.log when asked
    assert station.links() == (runner.links.shaker, runner.links.daq, True)   # the poller reads the session's
    station.sessions.request_stop("the window was closed")
    assert runner.stops[-1] == "the window was closed"
    station.sessions._runner_changed(None)
    assert station.links() == (None, None, False)


def test_the_estop_stops_the_running_session_too(station):
    runner = FakeRunner()
    station.sessions._runner_changed(runner)
    station.emergency.press()
    assert runner.stops == [PRESSED]
    assert station.emergency.wait(HANG_S) is not None and station.emergency.latched
    station.sessions._runner_changed(None)


def test_manual_control_refuses_with_its_reasons_and_sends_nothing(station):
    manual = station.manual
    assert manual.hydraulics(True, None) == ["not connected"]
    assert manual.move(0.5, None) == ["not connected", "static position 500.00 mm outside the stroke limits "
                                      f"{station.config.limits.stroke_low_m * 1e3:.1f}…"
                                      f"{station.config.limits.stroke_high_m * 1e3:.1f} mm"]
    busy = threading.Event()
    station.sessions._thread = threading.Thread(target=busy.wait)      # a session running
    station.sessions._thread.start()
    try:
        assert manual.hydraulics(True, None) == ["a session is running: abort it first"]
        assert manual.reset_alarm() == ["a session is running: abort it first"]
    finally:
        busy.set()
        station.sessions._thread.join()
    refusals = [p.text for p in station.posted if isinstance(p, Notice) and p.level == "refused"]
    assert len(refusals) == 4 and all("refused, nothing sent" in text for text in refusals), refusals


def test_the_heartbeat_follows_the_links_notices():
    from rig.events import LinkCondition

    beat = Heartbeat()
    beat.follow(LinkCondition.HEARTBEAT_FAILING)
    assert not beat.ok
    beat.follow(LinkCondition.LOST)
    assert not beat.ok
    beat.follow(LinkCondition.HEARTBEAT_BACK)
    assert beat.ok


def test_ctrl_c_closes_the_console_with_exit_status_130(qtbot, tmp_path):
    from PySide6 import QtCore, QtWidgets

    from rig.gui.main_window import MainWindow, run_gui
    from rig.gui.options import ConsoleOptions

    app = QtWidgets.QApplication.instance()
    before = signal.getsignal(signal.SIGINT)
    seen: list[MainWindow] = []

    def interrupt_once_connected() -> None:
        windows = [w for w in app.topLevelWidgets() if isinstance(w, MainWindow) and w.isVisible()]
        if windows and windows[0].status is not None:     # the console reads the rig: Ctrl-C in its terminal
            seen.append(windows[0])
            os.kill(os.getpid(), signal.SIGINT)
        else:
            QtCore.QTimer.singleShot(20, interrupt_once_connected)

    QtCore.QTimer.singleShot(0, interrupt_once_connected)
    assert run_gui(ConsoleOptions.parse(["--simulate", "--speed", "50", "--out", str(tmp_path)])) == EXIT_INTERRUPTED
    assert seen and seen[0].interrupted_by == signal.SIGINT and not seen[0].isVisible()
    assert signal.getsignal(signal.SIGINT) is before          # the handler is the console's only while it runs
