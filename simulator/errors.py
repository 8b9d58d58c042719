"""The simulator's exceptions: everything a user of ``python -m simulator`` can get
wrong, each with a one-line message (the command line exits 2).  Anything else is a
bug and keeps its traceback."""

from __future__ import annotations


class SimulatorError(Exception):
    """Input the simulator cannot use (names the option or file and why)."""


class UsageError(SimulatorError, ValueError):
    """An option or an endpoint that cannot be used."""
