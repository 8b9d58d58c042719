"""The rig package's exceptions, one tree, sorted by what the operator must do.

``BadInput``   a file, address or argument that cannot be used: refused before
               anything moves or any session folder is written (exit 2);
``RigFault``   the rig itself failed or refused: a link that did not come back, an
               alarm, a controller or DAQ that answered wrongly (exit 3, after the
               safe stop when motion may have started).

Anything else raised inside the package is a bug: it still ends in the safe stop,
and the command line shows its traceback.
"""

from __future__ import annotations


class RigError(Exception):
    """Every anticipated error of the rig package; the message is one line for the operator."""


class BadInput(RigError):
    """Input refused before anything moved (names the file, field or argument)."""


class RigFault(RigError):
    """The rig failed or refused while the session was connected."""


class AddressError(BadInput):
    """An address of the controller or the DAQ that is not of a form the drivers speak."""
