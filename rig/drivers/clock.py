"""Time as the drivers and the acquisition see it.

Every wait in the acquisition path goes through a :class:`Clock`, so that tests can
run the state machine against an in-process simulator on a simulated clock, and so
that no test has to synchronise on real sleeps.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def monotonic(self) -> float:
        """Seconds from an arbitrary origin, never going back."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass (the rig goes on meanwhile)."""
        ...


class WallClock:
    """The host's clock: what runs against a real rig or a served simulator."""

    @staticmethod
    def monotonic() -> float:
        return time.monotonic()

    @staticmethod
    def sleep(seconds: float) -> None:
        time.sleep(seconds)


WALL_CLOCK = WallClock()
