"""The console's latched trip (no Qt here): an E-STOP pressed, an alarm seen, a session's
safe stop that did not complete, each latched until the operator confirms the reset;
and the banner and Reset… that follow from it and from the controller as last read.

The banner never says two things that contradict each other, nor offers a reset it
cannot check: Reset… is offered only while something is latched *and* the controller is
read (a reset is confirmed against what the controller says; with the controller not
answering the banner says what to do instead).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

from rig.drivers.estop import EstopDone
from rig.drivers.registers import ControllerState
from rig.drivers.shaker import ShakerStatus
from rig.gui.state_strip import CHECK_RIG, hydraulics_on, short_link_error
from rig.gui.units import supply_text


@dataclass(frozen=True)
class Banner:
    text: str
    alarm: bool                  # latched or read tripped: shown red
    read: bool                   # the controller answered the last status read
    reset: bool                  # Reset… offered
    reset_why: str               # Reset…'s tooltip: what it does, or why it is not offered


class TripLatch:
    def __init__(self, watchdog_s: float) -> None:
        self.watchdog_s = watchdog_s
        self.estop_text: str | None = None      # the console's E-STOP, pressed
        self.alarm_latched: str | None = None   # an alarm seen (a trip outside a session has no event of its own)
        self.unsafe_stop: str | None = None     # a session's safe stop did not complete

    @property
    def latched(self) -> bool:
        return bool(self.estop_text or self.alarm_latched or self.unsafe_stop)

    def estop_pressed(self, at: _dt.datetime) -> None:
        self.estop_text = f"E-STOP at {at:%H:%M:%S}: STOP and hydraulics off sent"

    def estop_done(self, item: EstopDone) -> tuple[str, bool]:
        """The log's sentence for a press's end, and whether it is an error."""
        took = f"{item.elapsed_s * 1e3:.0f} ms"
        if item.failures:
            self.estop_text = f"E-STOP INCOMPLETE ({took}): {'; '.join(item.failures)}"
            return self.estop_text, True
        return (f"E-STOP done in {took} from the press: STOP and hydraulics off written and answered by the "
                f"controller ({item.line}); the registers read next say what it does"), False

    def seen(self, status: ShakerStatus | None, was: ShakerStatus | None) -> str | None:
        """A trip newly read (latched here); the log's sentence for it."""
        if status is None or status.state is not ControllerState.ALARM:
            return None
        if was is not None and was.state is ControllerState.ALARM:
            return None
        self.alarm_latched = status.alarm
        return f"controller tripped: {status.alarm}"

    def safe_stop_incomplete(self, failures: tuple[str, ...], at: _dt.datetime) -> str:
        steps = ", ".join(f.split(":", 1)[0] for f in failures)
        self.unsafe_stop = f"{steps} not confirmed at {at:%H:%M:%S}"
        return f"SAFE STOP INCOMPLETE: {steps} not confirmed; {CHECK_RIG}"

    def confirm_text(self, status: ShakerStatus | None) -> str:
        """What the reset's confirmation names."""
        if self.unsafe_stop:
            return f"The safe stop did not complete ({self.unsafe_stop}); {CHECK_RIG}"
        return self.estop_text or (f"alarm: {status.alarm}" if status else "alarm")

    def reset(self) -> None:
        self.estop_text = self.alarm_latched = self.unsafe_stop = None

    def banner(self, st: ShakerStatus | None, link_error: str | None) -> Banner:
        """The banner's line and Reset…, from the latch and the controller as last read."""
        # What the actuator does now, from the registers: held only with pressure behind it.
        bar = supply_text(st) if st is not None else ""
        held = (f"hydraulics OFF ({bar}): the actuator is not held" if st is not None and not hydraulics_on(st)
                else f"the controller holds the position ({bar})" if st is not None
                else "the controller's state is not known (no answer)")
        alarm_read = st is not None and st.state is ControllerState.ALARM
        alarm = self.latched or alarm_read
        unread = ("the controller is not answering: Reset… waits until it is read again (Connect), so that the "
                  "reset is checked against what it says")
        if self.unsafe_stop:
            now = f" The controller now reads {st.state}, {held}." if st is not None else \
                " The controller is not answering: nothing confirms the rig at rest."
            text = f"SAFE STOP DID NOT COMPLETE ({self.unsafe_stop}): {CHECK_RIG}.{now}" + (
                " Reset… once it is safe" if st is not None else "")
        elif self.estop_text:
            text = f"{self.estop_text} — {held}." + (" Reset… once the rig is safe" if st is not None else "")
        elif alarm:
            which = st.alarm if st is not None and alarm_read else \
                f"{self.alarm_latched}, latched here (the controller reads {st.state if st else 'nothing: no answer'})"
            text = f"ALARM: {which} — {held}; find the cause" + (", then Reset…" if st is not None else "")
        elif link_error:
            # The software E-STOP reaches the rig through the controller's Modbus port too.
            text = (f"Controller not answering: {short_link_error(link_error)}. Its watchdog should stop the "
                    f"shaker {self.watchdog_s:g} s after the link is lost. The E-STOP button goes over Modbus too "
                    "and may not reach it: use the hard-wired E-stop if the rig moves")
        elif st is None:
            text = "No alarm known: the controller is not read (not connected)"
        else:
            text = "No alarm"
        reset = alarm and st is not None
        why = ("clear a latched trip (asks for confirmation)" if reset else unread if alarm else "nothing is latched")
        return Banner(text, alarm, st is not None, reset, why)
