"""The controller's state as last read, and manual control: hydraulics, a static
position, a manual sine and a (fading) stop.  Every command is checked against the
rig's limits by :class:`~rig.gui.manual.ManualControl` before anything is written; a refusal
is shown here with its reasons and nothing is sent."""

from __future__ import annotations

from collections.abc import Callable

from PySide6 import QtWidgets

from rig.drivers.registers import ControllerState
from rig.drivers.shaker import ShakerStatus
from rig.gui.manual import ManualControl
from rig.gui.messages import Snapshot
from rig.gui.units import supply_text

STATE_COLOURS = {ControllerState.OFF: "#666666", ControllerState.IDLE: "#1f77b4", ControllerState.MOVING: "#ff7f0e",
                 ControllerState.AT_STATIC: "#1f77b4", ControllerState.RUNNING: "#2ca02c",
                 ControllerState.ALARM: "#b00020"}


class ControllerPanel(QtWidgets.QGroupBox):
    def __init__(self, watchdog_s: float, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__("Controller", parent)
        self.watchdog_s = watchdog_s
        # Two columns: the state strip above says the state from afar; this is the detail,
        # and the plan table below needs the height.
        grid = QtWidgets.QGridLayout(self)
        grid.setVerticalSpacing(2)
        self.fields: dict[str, QtWidgets.QLabel] = {}
        for i, (key, title) in enumerate((("state", "State"), ("position", "Position"), ("alarm", "Alarm"),
                                          ("force", "Force"), ("supply", "Hydraulic pressure"),
                                          ("cycles", "Cycles"), ("watchdog", "Watchdog"))):
            label = QtWidgets.QLabel("–")
            label.setObjectName(f"controller_{key}")
            label.setWordWrap(True)         # a long reason wraps in its column: the window still fits 1280 px
            self.fields[key] = label
            row, col = divmod(i, 2)
            grid.addWidget(QtWidgets.QLabel(title), row, 2 * col)
            grid.addWidget(label, row, 2 * col + 1, 1, 3 if key == "watchdog" else 1)
        grid.setColumnStretch(1, 1)
        grid.setColumnStretch(3, 1)

    def show_snapshot(self, snap: Snapshot) -> None:
        f = self.fields
        st = snap.status
        if st is None:
            # the reason in one line is the strip's and the banner's; the driver's words in the tooltip
            f["state"].setText("no answer" if snap.error else "not connected")
            f["state"].setStyleSheet("color: #b00020; font-weight: bold" if snap.error else "")
            f["state"].setToolTip(snap.error or "")
            # Nothing read: no number from an older read is shown beside it as if it were now.
            for key in ("position", "alarm", "force", "cycles", "supply", "watchdog"):
                f[key].setText("–")
                f[key].setStyleSheet("")
            if snap.error:
                # Not read, but what the controller should do on its own is known: said as such.
                f["watchdog"].setText(f"not read; without a link it should stop the shaker within "
                                      f"{self.watchdog_s:g} s")
                f["watchdog"].setStyleSheet("color: #b00020")
            return
        f["state"].setToolTip("")
        f["state"].setText(st.state)
        f["state"].setStyleSheet(f"color: {STATE_COLOURS.get(st.state, '#000')}; font-weight: bold")
        f["alarm"].setText(st.alarm)
        f["alarm"].setStyleSheet("color: #b00020; font-weight: bold" if st.state is ControllerState.ALARM else "")
        f["position"].setText(f"{st.position_m * 1e3:.2f} mm")
        f["force"].setText(f"{st.force_n / 1e3:.2f} kN")
        f["cycles"].setText(f"{st.cycles} since RUN" if st.state is ControllerState.RUNNING else str(st.cycles))
        f["supply"].setText(supply_text(st))
        # Who feeds it, from which links were read: the session's while one runs, else the console's.
        feeder = "the session's link" if snap.session else "the console's link"
        f["watchdog"].setText(f"{self.watchdog_s:g} s, fed by {feeder}" if snap.heartbeat_ok
                              else "HEARTBEAT FAILING: the controller will trip")
        f["watchdog"].setStyleSheet("" if snap.heartbeat_ok else "color: #b00020; font-weight: bold")

    def show_trip(self, trip: str | None, status: ShakerStatus | None) -> None:
        """The console's latch (E-STOP, an alarm not yet reset) over the registers: after an
        E-STOP the controller reads OFF with no alarm, and a panel saying "State OFF, Alarm
        none" under a red strip would contradict it until the reset is confirmed."""
        if trip is None or status is None:
            return
        f = self.fields
        state = f"ALARM latched by this console (the controller reads {status.state})"
        if f["state"].text() == state:          # a style sheet is costly: this runs on every tick
            return
        f["state"].setText(state)
        f["state"].setStyleSheet(f"color: {STATE_COLOURS[ControllerState.ALARM]}; font-weight: bold")
        f["alarm"].setText(f"{trip}, until Reset… is confirmed")
        f["alarm"].setStyleSheet(f"color: {STATE_COLOURS[ControllerState.ALARM]}; font-weight: bold")


def _spin(low: float, high: float, value: float, suffix: str, decimals: int = 2) -> QtWidgets.QDoubleSpinBox:
    box = QtWidgets.QDoubleSpinBox()
    # The operator may type anything the box can hold: the rig's limits are checked on the
    # command, with reasons, rather than silently clamped here.
    box.setRange(low, high)
    box.setDecimals(decimals)
    box.setValue(value)
    box.setSuffix(f" {suffix}")
    return box


class ManualPanel(QtWidgets.QGroupBox):
    def __init__(self, control: ManualControl, status: Callable[[], ShakerStatus | None],
                 parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__("Manual control", parent)
        self.control, self.status = control, status
        lim = control.config.limits
        layout = QtWidgets.QVBoxLayout(self)

        hyd = QtWidgets.QHBoxLayout()
        self.hyd_on = QtWidgets.QPushButton("Hydraulics ON")
        self.hyd_on.setObjectName("hydraulicsOnButton")
        self.hyd_off = QtWidgets.QPushButton("Hydraulics OFF")
        self.hyd_off.setObjectName("hydraulicsOffButton")
        self.hyd_on.clicked.connect(lambda: self._do(control.hydraulics(True, self.status())))
        self.hyd_off.clicked.connect(lambda: self._do(control.hydraulics(False, self.status())))
        hyd.addWidget(self.hyd_on)
        hyd.addWidget(self.hyd_off)
        layout.addLayout(hyd)

        move = QtWidgets.QHBoxLayout()
        self.position = _spin(-300, 300, 133.0, "mm")
        self.position.setObjectName("positionBox")
        self.move_button = QtWidgets.QPushButton("Move")
        self.move_button.setObjectName("moveButton")
        self.move_button.clicked.connect(self.request_move)
        move.addWidget(QtWidgets.QLabel("Move to (sent on Move)"))
        move.addWidget(self.position, 1)
        move.addWidget(self.move_button)
        layout.addLayout(move)

        sine = QtWidgets.QGridLayout()
        self.sine_static = _spin(-300, 300, 133.0, "mm")
        self.sine_amplitude = _spin(0, 300, 10.0, "mm")
        self.sine_frequency = _spin(0, 100, 1.0, "Hz", 3)
        for row, (title, box) in enumerate((("Static", self.sine_static), ("Amplitude", self.sine_amplitude),
                                            ("Frequency", self.sine_frequency))):
            sine.addWidget(QtWidgets.QLabel(title), row, 0)
            sine.addWidget(box, row, 1)
        self.sine_button = QtWidgets.QPushButton("Start sine")
        self.sine_button.setObjectName("sineButton")
        self.sine_button.clicked.connect(self.request_sine)
        sine.addWidget(self.sine_button, 0, 2, 3, 1)
        layout.addLayout(sine)
        limits = QtWidgets.QLabel(f"Limits: stroke {lim.stroke_low_m * 1e3:g}…{lim.stroke_high_m * 1e3:g} mm, "
                                  f"≤ {lim.max_frequency_hz:g} Hz, peak velocity ≤ {lim.max_velocity_m_s:g} m/s")
        limits.setWordWrap(True)
        layout.addWidget(limits)

        self.stop_button = QtWidgets.QPushButton("Stop (fade out)")
        self.stop_button.setObjectName("stopButton")
        self.stop_button.clicked.connect(lambda: self._do(control.fade_stop(self.status())))
        layout.addWidget(self.stop_button)
        self.refusal = QtWidgets.QLabel("")
        self.refusal.setObjectName("refusalLabel")
        self.refusal.setWordWrap(True)
        self.refusal.setStyleSheet("color: #b00020")
        layout.addWidget(self.refusal)

    def request_move(self) -> None:
        self._do(self.control.move(self.position.value() * 1e-3, self.status()))

    def request_sine(self) -> None:
        self._do(self.control.sine(self.sine_static.value() * 1e-3, self.sine_amplitude.value() * 1e-3,
                                   self.sine_frequency.value(), self.status()))

    def _do(self, problems: list[str]) -> None:
        self.refusal.setText("Refused, nothing sent: " + "; ".join(problems) if problems else "")
