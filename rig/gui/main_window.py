"""The operator's main window: connection, alarm banner and E-STOP along the top; the
controller's state, the plan runner and manual control on the left; the live view,
the fit view and the session browser on the right; the session's log along the bottom.

The window is one more subscriber of the session's events: everything the rig side
(:class:`~rig.gui.station.Station`) has to say arrives in a queue that a timer drains
in the GUI thread, which also redraws the live plots from the DAQ's ring buffer, at
most :data:`REDRAW_HZ` times a second.
"""

from __future__ import annotations

import datetime as _dt
import os
import queue
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from PySide6 import QtCore, QtGui, QtWidgets

from identify.exit_codes import EXIT_INTERRUPTED
from identify.model import DEFAULT_ESTIMATE
from rig.drivers.daq import check_daq_address
from rig.drivers.estop import EstopDone, LatchChanged
from rig.drivers.registers import ControllerState
from rig.drivers.shaker import ShakerAddress, ShakerStatus
from rig.errors import BadInput
from rig.events import Event, Kind, Message, Phase
from rig.gui.browser import SessionBrowser
from rig.gui.controls import ControllerPanel, ManualPanel
from rig.gui.fit_view import FitView
from rig.gui.fitting import IdentifySettings
from rig.gui.live import LiveView
from rig.gui.messages import (
    ComparisonDone,
    FitDone,
    FitProgress,
    LinkState,
    Notice,
    SafeStopIncomplete,
    SessionClosed,
    SessionOpened,
    Snapshot,
)
from rig.gui.options import ConsoleOptions
from rig.gui.plan_panel import PlanPanel
from rig.gui.qc import QcDone, QcProgress, QcRequest, QcStarted, refused
from rig.gui.qc_panel import QcPanel
from rig.gui.simulated import SimulatedRig
from rig.gui.state_strip import COLOURS, RigState, StateStrip
from rig.gui.station import Station, session_options
from rig.gui.trip import TripLatch
from rig.planning.plans import comma_list, load_plan
from rig.qc.spec import load_spec
from rig.session.preparation import RunOptions
from rig.session.progress import describe

REDRAW_HZ = 30
BANNER_ALARM, BANNER_NO_ANSWER, BANNER_CLEAR = COLOURS[ControllerState.ALARM], "#e65100", "#2e7d32"
DRAIN_MAX = 5000                 # records taken from the queue per tick, so a flood cannot freeze the window
LOGGED_EVENTS = (Kind.SESSION_START, Kind.PHASE, Kind.EXPERIMENT_DONE, Kind.EXPERIMENT_FAILED, Kind.ALARM, Kind.LOG,
                 Kind.PACE_PROBE, Kind.HOLD, Kind.HOLD_END, Kind.CAPTURE_WINDOW, Kind.LINK, Kind.SESSION_END)
ESTOP_KEYS = ("Esc", "F12")
GIL_SWITCH_S = 0.0005
# A status read not answered for this long: the last one is not shown as the rig's state (a read
# waits on the link's lock while the session's command reconnects, up to reconnect_s, 20 s).
STALE_READ_S = 2.0
SILENT = f"no answer to the status read for {STALE_READ_S:g} s (it waits on the link)"


def application() -> QtWidgets.QApplication:
    # A frame of the live view calls back into Python dozens of times (pyqtgraph's items
    # paint in Python), each time waiting for the interpreter lock while a worker thread
    # computes (the session's settling prediction, the DAQ parser at 20x) for up to the
    # switch interval: at the default 5 ms a frame took 30-95 ms instead of 17 ms, and
    # 0.5 ms gives the window back its frames at the workers' cost of more switches.
    app = QtWidgets.QApplication.instance()
    if isinstance(app, QtWidgets.QApplication):
        return app
    sys.setswitchinterval(GIL_SWITCH_S)
    return QtWidgets.QApplication(sys.argv[:1])


class MainWindow(QtWidgets.QMainWindow):
    def __init__(self, args: ConsoleOptions) -> None:
        super().__init__()
        if args.simulate and (args.shaker or args.daq):
            raise BadInput("gui: either --simulate or --shaker/--daq, not both")
        if (args.unit or args.faults) and not args.simulate:
            raise BadInput("gui: --unit and --fault choose what the simulated rig plays: give --simulate too")
        # What the command line names is checked as `rig run` checks it: a typo is one line
        # and exit 2 before any window or simulator, not a message inside the window.
        load_plan(args.plan).select(comma_list(args.experiments))
        if args.shaker:
            ShakerAddress.parse(args.shaker)
        if args.daq:
            check_daq_address(args.daq)
        self.simulated = SimulatedRig(args) if args.simulate else None
        shaker, daq = args.shaker, args.daq
        if self.simulated is not None:
            shaker, daq = self.simulated.modbus_url, self.simulated.daq_url
        # Everything the rig side says, one typed record each (rig.events.Message), handled by type.
        self.queue: queue.Queue[Message] = queue.Queue()
        self._handlers: dict[type[Message], Callable[[Any], None]] = {
            Event: self._on_event, Snapshot: self._on_snapshot, Notice: self._on_notice,
            LinkState: self._on_link_state, SessionOpened: self._on_session_opened,
            SessionClosed: self._on_session_closed, FitProgress: self._on_fit_progress, FitDone: self._on_fit_done,
            ComparisonDone: self._on_comparison_done, EstopDone: self._on_estop_done,
            LatchChanged: self._on_latch_changed, QcStarted: self._on_qc_started, QcProgress: self._on_qc_progress,
            QcDone: self._on_qc_done, SafeStopIncomplete: self._on_safe_stop_incomplete}
        try:
            self.station = Station(shaker, daq, self.queue.put, rig_config=args.rig_config,
                                   calibration=args.calibration, register_map=args.register_map)
        except BaseException:
            if self.simulated:
                self.simulated.stop()
            raise
        self.status: ShakerStatus | None = None
        self.trip = TripLatch(self.station.config.limits.watchdog_timeout_s)   # latched until the operator resets
        self.link_error: str | None = None
        self.interrupted_by: int | None = None      # SIGINT or SIGTERM closed the window (exit 130)
        self._closing = False
        self._last_redraw = 0.0
        self._last_read = time.monotonic()          # when the last status snapshot was taken
        self._last_table = 0.0
        self.setWindowTitle("Damper rig — operator console" + (" — SIMULATED RIG" if self.simulated else ""))
        self._build(args, shaker, daq)
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self._tick)
        self.timer.start(int(1000 / REDRAW_HZ))
        if shaker and daq:
            self.connect_rig()

    @classmethod
    def from_args(cls, argv: Sequence[str]) -> MainWindow:
        """The window for the command line's arguments (``gui`` itself may be left out),
        not shown, no event loop run."""
        options = ConsoleOptions.parse(argv)
        application()
        return cls(options)

    # ----- layout ----------------------------------------------------------------------------------
    def _build(self, args: ConsoleOptions, shaker: str | None, daq: str | None) -> None:
        """The window: the header (links, E-STOP, banner), the state strip, the controls
        beside the views, the log."""
        header = self._build_header(args, shaker, daq)
        self.strip = StateStrip()
        split = QtWidgets.QSplitter()
        split.addWidget(self._build_controls(args))
        split.addWidget(self._build_views(args))
        split.setStretchFactor(0, 0)
        split.setStretchFactor(1, 1)
        split.setSizes([520, 1080])
        self.log = QtWidgets.QPlainTextEdit()
        self.log.setObjectName("logView")
        self.log.setReadOnly(True)
        self.log.setMaximumBlockCount(5000)
        self.log.setFixedHeight(110)
        central = QtWidgets.QWidget()
        layout = QtWidgets.QVBoxLayout(central)
        layout.addLayout(header)
        layout.addWidget(self.strip)
        layout.addWidget(split, 1)
        log_title = QtWidgets.QLabel(f"Log — each line stamped with the wall clock, HH:MM:SS {_local_zone()}")
        log_title.setObjectName("logTitle")
        log_title.setStyleSheet("color: #555")
        layout.addWidget(log_title)
        layout.addWidget(self.log)
        self.setCentralWidget(central)
        self.resize(1600, 1000)
        self._motion = {"hydraulics_on": self.manual.hyd_on, "move": self.manual.move_button,
                        "sine": self.manual.sine_button, "run_plan": self.plan.run_button,
                        "resume": self.plan.resume_button, "qc_test": self.qc.test_button}
        self._tooltips = {name: button.toolTip() for name, button in self._motion.items()}
        self._show_banner()

    def _build_header(self, args: ConsoleOptions, shaker: str | None, daq: str | None) -> QtWidgets.QHBoxLayout:
        """The links' addresses and Connect, the SIMULATED line, the alarm banner with Reset…, the E-STOP."""
        top = QtWidgets.QHBoxLayout()
        self.shaker_edit = QtWidgets.QLineEdit(shaker or "")
        self.shaker_edit.setPlaceholderText("tcp://HOST:PORT or rtu:///dev/DEVICE")
        self.daq_edit = QtWidgets.QLineEdit(daq or "")
        self.daq_edit.setPlaceholderText("/dev/ttyUSB0 or socket://HOST:PORT")
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.connect_button.setObjectName("connectButton")
        self.connect_button.clicked.connect(self._toggle_connection)
        self.link_label = QtWidgets.QLabel("not connected")
        self.link_label.setObjectName("linkLabel")
        for w in (QtWidgets.QLabel("Controller"), self.shaker_edit, QtWidgets.QLabel("DAQ"), self.daq_edit,
                  self.connect_button):
            top.addWidget(w)
        self.estop_button = QtWidgets.QPushButton("E-STOP\n(" + " / ".join(ESTOP_KEYS) + ")")
        self.estop_button.setObjectName("estopButton")
        self.estop_button.setMinimumSize(150, 64)
        self.estop_button.setStyleSheet("QPushButton { background: #d50000; color: white; font-size: 18pt; "
                                        "font-weight: bold; border: 3px solid #7f0000; border-radius: 8px; }"
                                        "QPushButton:pressed { background: #7f0000; }")
        self.estop_button.clicked.connect(self.estop)
        self.estop_button.setToolTip("The console's E-STOP: STOP and hydraulics off over Modbus. It does not replace "
                                     "the hard-wired E-stop, the one that always reaches the rig.")
        for key in ESTOP_KEYS:
            shortcut = QtGui.QShortcut(QtGui.QKeySequence(key), self)
            shortcut.setContext(QtCore.Qt.ShortcutContext.ApplicationShortcut)
            shortcut.setAutoRepeat(False)     # a key held down is one press, not a stream of them
            shortcut.activated.connect(self.estop)

        self.banner = QtWidgets.QLabel("No alarm")
        self.banner.setObjectName("alarmBanner")
        self.banner.setMinimumHeight(34)
        self.banner.setWordWrap(True)
        self.reset_button = QtWidgets.QPushButton("Reset…")
        self.reset_button.setObjectName("resetButton")
        self.reset_button.clicked.connect(lambda: self.reset_alarm(confirm=True))
        banner_row = QtWidgets.QHBoxLayout()
        banner_row.addWidget(self.banner, 1)
        banner_row.addWidget(self.reset_button)
        self.sim_label = QtWidgets.QLabel(self.simulated.line if self.simulated is not None else "")
        self.sim_label.setObjectName("simulatedLabel")
        self.sim_label.setStyleSheet("background: #fff3cd; color: #7a5200; font-weight: bold; padding: 3px")
        self.sim_label.setVisible(self.simulated is not None)

        head = QtWidgets.QVBoxLayout()
        head.addLayout(top)
        head.addWidget(self.link_label)
        head.addWidget(self.sim_label)
        head.addLayout(banner_row)
        header = QtWidgets.QHBoxLayout()
        header.addLayout(head, 1)
        header.addWidget(self.estop_button)
        return header

    def _build_controls(self, args: ConsoleOptions) -> QtWidgets.QWidget:
        """The controller's panel above the Plan, Manual and QC tabs."""
        st = self.station
        self.controller = ControllerPanel(st.config.limits.watchdog_timeout_s)
        self.plan = PlanPanel(st.config, args.plan, args.experiments, Path(args.out))
        self.plan.runRequested.connect(self.run_plan)
        self.plan.abortRequested.connect(self.abort)
        self.plan.resumeRequested.connect(self.resume)
        self.manual = ManualPanel(st.manual, lambda: self.status)
        self.left_tabs = QtWidgets.QTabWidget()
        self.left_tabs.addTab(self.plan, "Plan")
        manual_page = QtWidgets.QWidget()
        manual_layout = QtWidgets.QVBoxLayout(manual_page)
        manual_layout.addWidget(self.manual)
        manual_layout.addStretch(1)
        self.left_tabs.addTab(manual_page, "Manual")
        self.qc = QcPanel(Path(args.out))
        self.qc.testRequested.connect(self.run_qc)
        self.qc.abortRequested.connect(self.abort)
        self.left_tabs.addTab(self.qc, "QC")
        left = QtWidgets.QWidget()
        left_layout = QtWidgets.QVBoxLayout(left)
        left_layout.setContentsMargins(0, 0, 0, 0)
        left_layout.addWidget(self.controller)
        left_layout.addWidget(self.left_tabs, 1)
        return left

    def _build_views(self, args: ConsoleOptions) -> QtWidgets.QTabWidget:
        """The Live, Fit and Sessions views."""
        st = self.station

        self.live = LiveView(st.config.daq_rate_hz, st.config.min_span,
                             self.simulated.asked_pace if self.simulated is not None else 1.0)
        self.fit_view = FitView()
        self.fit_view.compareRequested.connect(self.compare)
        self.browser = SessionBrowser(Path(args.out))
        self.browser.refitRequested.connect(self.refit)
        self.browser.resumeRequested.connect(self.resume)
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.setObjectName("mainTabs")
        self.tabs.addTab(self.live, "Live")
        self.tabs.addTab(self.fit_view, "Fit")
        self.tabs.addTab(self.browser, "Sessions")
        return self.tabs

    # ----- operator actions ------------------------------------------------------------------------
    def connect_rig(self) -> None:
        self.link_label.setText("connecting…")
        self.station.connect(self.shaker_edit.text().strip() or None, self.daq_edit.text().strip() or None)

    def _toggle_connection(self) -> None:
        if self.station.manual.shaker is not None:
            self.station.manual.disconnect()
        else:
            self.connect_rig()

    def estop(self) -> None:
        self.station.emergency.press()
        self.trip.estop_pressed(_dt.datetime.now())
        self._say("E-STOP pressed", "error")
        self._show_banner()

    def rig_state(self) -> RigState:
        # The E-STOP's latch (rig.drivers.estop) holds every motion command in the drivers; the strip and
        # the controls show it, and an alarm seen, until the operator confirms the reset.
        latch = self.station.emergency.latch
        trip = latch.reason if latch.latched else "E-STOP" if self.trip.estop_text else self.trip.alarm_latched
        running = self.station.sessions.running
        return RigState(self.status, trip, self.link_error, self.station.manual.shaker is not None or running,
                        running, self.trip.unsafe_stop)

    def _show_state(self) -> None:
        """The strip and which motion controls are allowed, from the same state."""
        state = self.rig_state()
        self.strip.show_state(state)
        self.controller.show_trip(state.trip, state.status)
        blocked = state.blocked()
        for name, button in self._motion.items():
            reason = blocked.get(name)
            if reason is not None:
                button.setEnabled(False)
                button.setToolTip(f"Disabled: {reason}")
            elif button.toolTip() != self._tooltips[name] or not button.isEnabled():
                button.setEnabled(True)
                button.setToolTip(self._tooltips[name])
        # A session holds the links until its safe stop: the console's own are taken back after it.
        self.connect_button.setEnabled(not state.session_running)
        editable = not state.session_running and self.station.manual.shaker is None    # the addresses in use
        self.shaker_edit.setReadOnly(not editable)
        self.daq_edit.setReadOnly(not editable)
        self.browser.resume_button.setEnabled(self.browser.resumable and "resume" not in blocked)
        self.browser.resume_button.setToolTip(f"Disabled: {blocked['resume']}" if "resume" in blocked else "")

    def reset_alarm(self, confirm: bool = True) -> None:
        if confirm:
            what = self.trip.confirm_text(self.status)
            answer = QtWidgets.QMessageBox.question(
                self, "Reset the trip?", f"{what}\n\nReset only once the cause is known and the rig is safe. Reset?")
            if answer != QtWidgets.QMessageBox.StandardButton.Yes:
                return
        self.trip.reset()
        self.station.emergency.confirm_reset()
        if self.status is not None and self.status.state is ControllerState.ALARM:
            self.manual._do(self.station.manual.reset_alarm())
        self._show_banner()

    def run_plan(self) -> None:
        identify = IdentifySettings() if self.plan.identify.isChecked() else None
        opt = session_options(self.plan.plan.text().strip() or "standard", *self.station.urls,
                              self.plan.run_folder(), self.plan.letters(), self.station, identify)
        self._start(opt, identify)

    def resume(self, folder: str) -> None:
        identify = IdentifySettings() if self.plan.identify.isChecked() else None
        opt = session_options("standard", *self.station.urls, Path(folder), None, self.station, identify,
                              resume=True)
        self._start(opt, identify)

    def _start(self, opt: RunOptions, identify: IdentifySettings | None) -> None:
        if self.station.sessions.run_plan(opt, identify is not None):
            self.plan.set_running(True)
            self._say(f"session {'resumed' if opt.resume else 'starting'}: {opt.out}")

    def run_qc(self, request: QcRequest) -> None:
        # The spec's own checks, before the console lets go of its links: a typo costs nothing.
        try:
            if not request.serial:
                raise BadInput("enter the unit's serial number first")
            load_spec(request.spec).check_serial(request.serial)
        except BadInput as exc:
            self.qc.show_done(refused(request, str(exc)))
            return
        if self.station.sessions.run_qc(request):
            self.plan.set_running(True)
            self._say(f"QC of unit {request.serial} starting (spec {request.spec}; the same test as "
                      "python -m rig qc run)")

    def abort(self) -> None:
        self.station.abort()
        self.plan.show_stopping("Abort pressed")
        self._say("Abort: safe stop requested (fade out, STOP, hydraulics off)")

    def refit(self, folder: Path, settings: IdentifySettings) -> None:
        self.fit_view.progress.setText(f"re-fitting {settings.model}…")
        self.station.fits.refit(folder, settings)
        self.tabs.setCurrentWidget(self.fit_view)

    def compare(self) -> None:
        result, folder = self.fit_view.result, self.fit_view.folder
        if folder is None:
            return
        estimate = result.estimated if result is not None and result.model == "2dof" else DEFAULT_ESTIMATE["2dof"]
        self.fit_view.progress.setText("fitting 1-dof and 2-dof to the stroke…")
        self.station.fits.compare(folder, IdentifySettings("2dof", None, list(estimate)))

    # ----- what the rig says -----------------------------------------------------------------------
    def _tick(self) -> None:
        for _ in range(DRAIN_MAX):
            try:
                item = self.queue.get_nowait()
            except queue.Empty:
                break
            self._handle(item)
        now = time.monotonic()
        if self.status is not None and now - self._last_read > STALE_READ_S:
            self._controller_silent()
        self._show_state()
        if self.tabs.currentWidget() is self.live and now - self._last_redraw >= 0.9 / REDRAW_HZ:
            self.live.set_excitation(*self._excitation())
            if self.live.refresh(self.station.live_daq()):
                self._last_redraw = now
        if now - self._last_table >= 0.5:
            self._last_table = now
            self.plan.refresh()

    def _excitation(self) -> tuple[object, float | None, str]:
        """The excitation running now, as (a key that changes when a new one starts, its
        frequency, why there is none); (None, None, why) when the controller was not read
        running (moving, at rest, tripped, not answering)."""
        if self.status is None:
            return None, None, "the controller's state is not read" if self.link_error else "no excitation running"
        if self.status.state is not ControllerState.RUNNING:
            return None, None, "no excitation running"
        progress = self.plan.progress
        current = progress.current if progress is not None and self.station.sessions.running else None
        if current is not None:
            if current.status in ("settling", "capturing") and current.spec is not None:
                return current.label, current.spec.frequency_hz, ""
            return None, None, "no excitation running"
        manual = self.station.manual
        if manual.frequency_hz:
            return ("manual", manual.runs), manual.frequency_hz, ""
        return None, None, "no excitation running"

    def _handle(self, item: Message) -> None:
        # One dispatch on the record's type: a type without a handler is a bug, raised here.
        self._handlers[type(item)](item)

    def _on_event(self, item: Event) -> None:
        self.plan.apply(item)
        if item.kind == Kind.PHASE and item.data.get("phase") == Phase.STOPPING and item.experiment is None:
            # the session's own safe stop (an abort, a lost link, the plan's end): no time left is shown
            self.plan.show_stopping(str(item.data.get("reason") or "the plan ended"))
        if item.kind in LOGGED_EVENTS:
            self._log_event(item)

    def _controller_silent(self) -> None:
        """No snapshot for a while though the controller was being read: what it said last
        is no longer its state (the DAQ line keeps its last counts: the same read is late)."""
        self._say(f"controller not read: {SILENT}", "error")
        self.status, self.link_error = None, SILENT
        if self.plan.progress is not None:
            self.plan.progress.unread = SILENT
        self.controller.show_snapshot(Snapshot(None, SILENT))
        self._show_banner()

    def _on_snapshot(self, item: Snapshot) -> None:
        self._last_read = item.time
        was = self.status
        if item.error is not None and item.error != self.link_error:
            # the driver's own words, once, here; the strip, the banner and the panel say it in one line
            self._say(f"controller not read: {item.error}", "error")
        self.status = item.status
        self.link_error = item.error
        st = item.status
        tripped = self.trip.seen(st, was)      # a trip outside a session (a manual sine) has no event to log it
        if tripped is not None:
            self._say(tripped, "error")
        if self.plan.progress is not None and self.station.sessions.running:
            # The stream's sample count read with the status drives every count shown, in this
            # frame, as long as the controller was read running (cycles are not counted on a
            # stream whose excitation nobody has read).
            running = item.status is not None and item.status.state is ControllerState.RUNNING
            self.plan.progress.unread = item.error
            if running and self.plan.progress.observe(item.samples, item.time) is not None:
                self.plan.refresh()
        self.controller.show_snapshot(item)
        self.live.show_health(item)
        self._show_banner(item.error)

    def _on_notice(self, item: Notice) -> None:
        self._say(item.text, item.level)

    def _on_link_state(self, item: LinkState) -> None:
        self.link_label.setText(("connected: " if item.connected else "") + item.text)
        if item.simulated and self.simulated is None:   # reached by address, but it says it is a simulator
            self.sim_label.setText("SIMULATED RIG: the controller or the DAQ identifies itself as a simulator "
                                   "(not hardware; QC records from it are marked simulated)")
            self.sim_label.setVisible(True)
            self.setWindowTitle("Damper rig — operator console — SIMULATED RIG")
        self.connect_button.setText("Disconnect" if item.connected else "Connect")
        if not item.connected:
            # Nothing read any more on these links: the panel and the DAQ line must not go on
            # showing their last reading as if it were live.
            self.status, self.link_error = None, None
            self.controller.show_snapshot(Snapshot(None, None))
            self.live.show_health(Snapshot(None, None))
        self._show_banner()

    def _on_session_opened(self, item: SessionOpened) -> None:
        # A QC test's experiments fill the plan table too (the QC tab stays in front).
        self.plan.show_progress(item.progress)
        self.plan.set_running(True)
        self.qc.test_button.setEnabled(False)
        self.tabs.setCurrentWidget(self.live)
        self._say(f"{'QC ' if item.qc else ''}session folder {item.path}")

    def _on_session_closed(self, item: SessionClosed) -> None:
        self.plan.set_running(False)
        self.qc.set_running(False)
        if item.result is not None:
            self.plan.session_ended(item.result.session.path)
        # The session's own end (its status) is already in the log from its event: the folder here.
        text = f"session folder {item.result.session.path} closed" if item.result is not None else item.text
        self._say(text, "info" if item.result is not None and item.result.exit_code == 0 else "error")
        if item.result is None:
            self.plan.eta.setText(item.text.splitlines()[0])
        if self._closing:
            QtCore.QTimer.singleShot(0, self.close)

    def _on_safe_stop_incomplete(self, item: SafeStopIncomplete) -> None:
        """A session's safe stop left steps undone: no reading says the rig is at rest, so
        the banner and the strip say so, latched until the operator confirms the reset."""
        self._say(self.trip.safe_stop_incomplete(item.failures, _dt.datetime.now()), "error")
        self._show_banner()

    def _on_fit_progress(self, item: FitProgress) -> None:
        self.fit_view.show_progress(item.title, item.iteration, item.objective)

    def _on_fit_done(self, item: FitDone) -> None:
        self.fit_view.show_result(item.title, item.result, item.folder)
        self.tabs.setCurrentWidget(self.fit_view)
        self._say(f"{item.title}: {'converged' if item.result.converged else 'NOT converged'}")

    def _on_comparison_done(self, item: ComparisonDone) -> None:
        self.fit_view.show_comparison(item.results)

    def _on_estop_done(self, item: EstopDone) -> None:
        text, failed = self.trip.estop_done(item)
        self._say(text, "error" if failed else "info")
        self._show_banner()

    def _on_latch_changed(self, item: LatchChanged) -> None:
        self._show_state()      # the strip and the motion controls follow the latch

    def _on_qc_started(self, item: QcStarted) -> None:
        # The status poll reads the QC session's own links from here on: the strip, the
        # panel and the live view go on showing the rig as read.
        self.qc.show_started(item.request)
        self.left_tabs.setCurrentWidget(self.qc)

    def _on_qc_progress(self, item: QcProgress) -> None:
        self.qc.show_progress(item)

    def _on_qc_done(self, item: QcDone) -> None:
        self.qc.show_done(item)
        self.plan.set_running(False)
        self._say(f"QC of unit {item.serial}: {item.shown}" + (f" ({item.reason})" if item.reason else "")
                  + (f"; report {item.report}" if item.report else ""),
                  "info" if item.shown in ("PASS", "FAIL", "RETEST") else "error")

    def _show_banner(self, link_error: str | None = None) -> None:
        banner = self.trip.banner(self.status, link_error or self.link_error)
        colour = BANNER_ALARM if banner.alarm else BANNER_NO_ANSWER if not banner.read else BANNER_CLEAR
        self.banner.setText(banner.text)
        self.banner.setStyleSheet(f"background: {colour if banner.alarm else 'transparent'}; color: "
                                  f"{'white' if banner.alarm else colour}; font-size: "
                                  f"{'14pt' if banner.alarm else '10pt'}; font-weight: bold; padding: 4px")
        self.reset_button.setEnabled(banner.reset)
        self.reset_button.setToolTip(banner.reset_why)

    def _log_event(self, e: Event) -> None:
        text = f"{e.experiment}: {describe(e)}" if e.experiment else describe(e)
        self._say(text, "error" if e.kind in (Kind.ALARM, Kind.EXPERIMENT_FAILED) else "info",
                  time.strftime("%H:%M:%S", time.localtime(e.time)))

    def _say(self, text: str, level: str = "info", stamp: str | None = None) -> None:
        stamp = stamp or time.strftime("%H:%M:%S")
        colour = {"refused": "#b00020", "error": "#b00020"}.get(level, "#000000")
        escaped = text.replace("&", "&amp;").replace("<", "&lt;").replace("\n", "<br>")
        self.log.appendHtml(f'<span style="color:{colour}">{stamp} {escaped}</span>')

    # ----- closing: a safe stop first --------------------------------------------------------------
    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        if self.station.sessions.running:
            event.ignore()
            if not self._closing:
                self._closing = True
                self.station.sessions.closing = True
                self.station.abort("the window was closed")
                self._say("closing: safe stop of the running session first; the window closes after it")
            return
        self.timer.stop()
        self.station.close()
        if self.simulated is not None:
            self.simulated.stop()
        event.accept()


def _local_zone() -> str:
    """The local time zone's name as the clock stamps are in it (UTC offset beside it)."""
    now = _dt.datetime.now().astimezone()
    offset = f"UTC{now:%z}"
    return "UTC" if offset == "UTC+0000" else f"{now.tzname()} ({offset})"


def run_gui(args: ConsoleOptions) -> int:
    if (sys.platform.startswith("linux") and not os.environ.get("QT_QPA_PLATFORM")
            and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))):
        # Qt would abort the process (exit 134) with a page about platform plugins.
        raise BadInput("gui: no display (neither DISPLAY nor WAYLAND_DISPLAY is set): run it in a desktop "
                       "session, or with QT_QPA_PLATFORM=offscreen for screenshots")
    app = application()
    window = MainWindow(args)
    # Ctrl-C or SIGTERM in the terminal close the window, which is a safe stop; the
    # window's timer gives Python the chance to run the handler.  The exit status then
    # says so (130, as README's exit table and `rig run` have it).
    def interrupted(signum: int, _frame: object) -> None:
        window.interrupted_by = signum
        window.close()

    previous = {sig: signal.signal(sig, interrupted) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        window.show()
        code = app.exec()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return EXIT_INTERRUPTED if window.interrupted_by is not None else code
