"""The identify package's exceptions, one tree, sorted by what the user must do.

``InputError``        a file, model, parameter or option that cannot be used: the
                      message names it (command lines exit 2);
``ComputationError``  the numerics did not get there: no periodic solution, an
                      estimator that did not converge, a failed integration (exit 1).

Anything else is a bug, and the command lines show its traceback.
"""

from __future__ import annotations


class IdentifyError(Exception):
    """Every anticipated error of the identify package."""


class InputError(IdentifyError, ValueError):
    """Input that cannot be used (names the file and place, or the option)."""


class ComputationError(IdentifyError, RuntimeError):
    """A computation that did not converge or failed on valid input."""
