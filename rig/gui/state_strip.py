"""The rig's state as an operator reads it from across the room: one strip in large type
and colour with the controller's state word, HYDRAULICS ON or OFF and the alarm; and
which motion controls that state allows, with the reason for each one it does not.

Both are driven by the controller's registers (state, alarm, supply pressure) and by
the console's own trip latch: an E-STOP or an alarm stays latched here until the
operator confirms the reset, even after the controller itself has gone quiet (the
console's E-STOP leaves the controller OFF, with no alarm register set).
"""

from __future__ import annotations

from dataclasses import dataclass

from PySide6 import QtCore, QtGui, QtWidgets

from rig.drivers.registers import ControllerState
from rig.drivers.shaker import ShakerStatus
from rig.gui.units import supply_text

# Supply pressure from which the hydraulics count as on: the register is the one
# reading that tells, whatever the coil was last written (a lost supply reads 0 bar).
HYDRAULICS_ON_PA = 10e5
MOTION = ("hydraulics_on", "move", "sine", "run_plan", "resume", "qc_test")
NEED_HYDRAULICS = ("move", "sine")
MANUAL = ("hydraulics_on", "move", "sine")
COLOURS: dict[str, str] = {ControllerState.ALARM: "#c62828", ControllerState.RUNNING: "#2e7d32",
                           ControllerState.MOVING: "#ef6c00", ControllerState.AT_STATIC: "#1565c0",
                           ControllerState.IDLE: "#1565c0", ControllerState.OFF: "#616161"}
NO_LINK_COLOUR = "#ef6c00"
LINK_ERROR_CHARS = 90          # a link error in the strip, the banner and the panel (the driver's text: the log)
UNSAFE_WORD = "SAFE STOP INCOMPLETE"
CHECK_RIG = "hydraulics may still be ON: check the rig; use the hard-wired E-stop if it moves"


def short_link_error(text: str | None) -> str | None:
    """A link error as one short line: the driver's own words (pymodbus' exception, in
    parentheses after ours) go to the log only, so that a line on screen stays readable
    and the window fits 1280 px."""
    if text is None:
        return None
    head = text.splitlines()[0].split(" (", 1)[0].strip() if text.strip() else text
    return head if len(head) <= LINK_ERROR_CHARS else head[:LINK_ERROR_CHARS - 1].rsplit(" ", 1)[0] + " …"


def hydraulics_on(status: ShakerStatus) -> bool:
    return status.hydraulic_pressure_pa >= HYDRAULICS_ON_PA


@dataclass(frozen=True)
class RigState:
    """What the strip and the controls are decided from (no Qt)."""

    status: ShakerStatus | None          # None: no answer from the controller
    trip: str | None = None              # the console's latch: E-STOP or an alarm not yet reset
    link_error: str | None = None
    connected: bool = False
    session_running: bool = False
    unsafe: str | None = None            # a session's safe stop did not complete (latched until Reset…)

    @property
    def word(self) -> str:
        if self.unsafe is not None:
            return UNSAFE_WORD
        if self.trip is not None or (self.status is not None and self.status.state is ControllerState.ALARM):
            return ControllerState.ALARM
        if self.status is None:
            return "NOT READ" if self.link_error else "NOT CONNECTED"
        return self.status.state

    def strip_text(self) -> str:
        parts = [self.word]
        st = self.status
        if self.unsafe is not None and (st is None or hydraulics_on(st)):
            # No reading says the hydraulics are off: the rig may still be live.
            return "   ·   ".join(parts + ["HYDRAULICS MAY BE ON", "CHECK THE RIG"])
        if self.trip is not None:
            parts.append(self.trip)
        elif st is not None and st.state is ControllerState.ALARM:
            parts.append(st.alarm)
        if st is None:
            parts.append("HYDRAULICS ?" + (f" ({short_link_error(self.link_error)})" if self.link_error else ""))
        else:
            parts.append(f"HYDRAULICS {'ON' if hydraulics_on(st) else 'OFF'}  {supply_text(st)}")
            if self.trip is not None and st.state is not ControllerState.ALARM:
                parts.append(f"controller {st.state}")
        return "   ·   ".join(parts)

    def colour(self) -> str:
        return COLOURS[ControllerState.ALARM] if self.word in (ControllerState.ALARM, UNSAFE_WORD) \
            else COLOURS.get(self.word, NO_LINK_COLOUR)

    def blocked(self) -> dict[str, str]:
        """Each motion control that is not allowed now, with the reason its tooltip gives."""
        why: dict[str, str] = {}
        st = self.status
        if self.unsafe is not None:
            return dict.fromkeys(MOTION, f"the last safe stop did not complete ({self.unsafe}): check the rig, "
                                         "then Reset…")
        if self.trip is not None:
            reason = f"{self.trip}: latched until Reset… is confirmed"
            return dict.fromkeys(MOTION, reason)
        if st is not None and st.state is ControllerState.ALARM:
            return dict.fromkeys(MOTION, f"controller in ALARM ({st.alarm}): find the cause, then Reset…")
        if self.session_running:
            why.update(dict.fromkeys(MOTION, "a session is running: it commands the rig until it ends (Abort)"))
        elif not self.connected or st is None:
            # A session needs the controller as much as a manual command does: with no reading of
            # its state (hydraulics, alarm) nothing is started on it.
            why.update(dict.fromkeys(MOTION, "the controller is not read" + (
                f" ({short_link_error(self.link_error)})" if self.link_error else " (not connected)")))
        elif not hydraulics_on(st):
            why.update(dict.fromkeys(NEED_HYDRAULICS, "hydraulics OFF: switch them on first"))
        return why


class StateStrip(QtWidgets.QLabel):
    """The strip itself: up to 26 pt bold, white on the state's colour, the whole window wide.
    A long text (an E-STOP's time and the controller's word beside the alarm) takes a
    smaller size rather than being cut at both ends."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setObjectName("stateStrip")
        self.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.setMinimumHeight(56)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Fixed)
        self._shown: tuple[str, str] | None = None
        self._styled: tuple[tuple[str, str], int] | None = None
        self.show_state(RigState(None))

    def show_state(self, state: RigState) -> None:
        text, colour = state.strip_text(), state.colour()
        if (text, colour) == self._shown:       # a style sheet is costly to apply: only on a change
            return
        self._shown = (text, colour)
        self.setText(text)
        self.setToolTip(text)
        self._restyle()

    def resizeEvent(self, event: QtGui.QResizeEvent) -> None:  # noqa: N802 (Qt's name)
        super().resizeEvent(event)
        self._restyle()

    def _fitting_pt(self) -> int:
        font = QtGui.QFont(self.font())
        font.setBold(True)
        for pt in range(26, 11, -2):
            font.setPointSize(pt)
            if QtGui.QFontMetrics(font).horizontalAdvance(self.text()) <= self.width() - 40:
                return pt
        return 12

    def _restyle(self) -> None:
        if self._shown is None:
            return
        pt = self._fitting_pt()
        if (self._shown, pt) == self._styled:
            return
        self._styled = (self._shown, pt)
        self.setStyleSheet(f"background: {self._shown[1]}; color: white; font-size: {pt}pt; font-weight: bold; "
                           "padding: 4px 12px; border-radius: 6px")
