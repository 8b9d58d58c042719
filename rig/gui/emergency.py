"""The console's E-STOP (no Qt here): :class:`rig.drivers.estop.EStop` — on a press,
mode STOP and hydraulics off on a Modbus connection of its own, opened in advance and
used for nothing else, its latch then vetoing every motion command of the console's
and the session's links until the operator confirms the reset — and, on the same
press, the running session told to stop (its safe stop then finds the rig at rest)."""

from __future__ import annotations

from collections.abc import Callable

from rig.config import RigConfig
from rig.drivers.estop import EStop, EstopDone, MotionLatch
from rig.drivers.registers import RegisterMap
from rig.drivers.shaker import Shaker
from rig.errors import RigError
from rig.events import Message
from rig.gui.messages import Notice

PRESSED = "E-STOP pressed by the operator: STOP and hydraulics off"


class EmergencyStop:
    def __init__(self, config: RigConfig, register_map: RegisterMap, active_shaker: Callable[[], Shaker | None],
                 stop_session: Callable[[str], None], post: Callable[[Message], None]) -> None:
        self.post, self.stop_session = post, stop_session
        # Posts EstopDone, and LatchChanged on every trip and reset (the window's motion controls follow it).
        self.estop = EStop(config.limits, register_map, fallback=active_shaker, on_done=post)
        self.estop.subscribe(post)

    @property
    def latch(self) -> MotionLatch:
        return self.estop.latch

    @property
    def latched(self) -> bool:
        return self.estop.latched

    def press(self) -> None:
        """STOP and hydraulics off at once, no fade, on the E-STOP's thread and line; a
        session (plain or QC) is told to stop too."""
        self.estop.press()
        self.stop_session(PRESSED)

    def wait(self, timeout_s: float | None = None) -> EstopDone | None:
        """The last press's outcome once both writes are answered (None on timeout)."""
        return self.estop.wait(timeout_s)

    def confirm_reset(self) -> None:
        self.estop.confirm_reset()

    def refuse(self, what: str) -> bool:
        """True (and the refusal posted) while the latch holds."""
        if not self.estop.latched:
            return False
        self.post(Notice(f"{what} refused, nothing sent: {self.estop.latch.reason}: confirm the reset first",
                         "refused"))
        return True

    def open_line(self, url: str | None) -> None:
        """The E-STOP's own line to ``url``; where none can be opened, the operator is told
        (the E-STOP then uses the session's or the console's link)."""
        if not url:
            return
        try:
            self.estop.open(url)
        except RigError as exc:
            self.post(Notice(f"E-STOP line to {url} not opened ({exc}); the E-STOP will use the session's link"))

    def close(self) -> None:
        self.estop.close()
