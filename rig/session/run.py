"""A whole session, in four steps that can each be read and tested on their own, each in
a module of its own:

``prepare``    (:mod:`rig.session.preparation`) every file, address, plan and argument
               checked; nothing written, nothing sent (:class:`~rig.errors.BadInput` → exit 2);
``connect``    (:mod:`rig.session.links`) both links opened and the controller's state
               read; a dead link or a latched alarm ends here, still with nothing written (exit 3);
``run``        (:mod:`rig.session.runner`, through :mod:`rig.session.lifecycle`) the
               session folder, then every planned experiment.  From here on the
               actuator may move, so *whatever* ends this step (the plan done, an
               alarm, a lost link, Ctrl-C/SIGTERM/SIGHUP, a bug) goes through
``tear down``  the safe stop (fade if running, STOP, hydraulics off), the session's
               status written as it is, the links closed.

``rig run`` in a terminal is :mod:`rig.session.terminal`; the identification after it
:mod:`rig.session.fitting`.  This module is where callers have always found them.

How a session ended is data, :class:`~rig.session.outcome.RunResult` (in the spirit of
Bluesky's ``RunEngineResult``): an :class:`~rig.session.outcome.ExitStatus` (complete,
ended, aborted, failed, interrupted), whether the plan was cut short, the reason and the
exception, and the safe stop's failures (``panicked``: the watchdog is the last guard).
The status sentence of session.json is rendered from them, and stored beside them.

Exit status: 0 every experiment captured (or skipped by ``--on-alarm skip``);
1 identification did not converge; 2 bad input, refused before anything moved or
was written; 3 aborted (alarm, lost link, controller or DAQ fault, a latched alarm
at start) after the safe stop; 130 interrupted by the operator (or SIGTERM/SIGHUP)
after the safe stop; 70 an internal error (a bug: traceback shown) after the safe stop.
"""

from identify.exit_codes import EXIT_OK
from rig.session.fitting import fit_session, identify_session
from rig.session.lifecycle import SessionContext, run_lifecycle
from rig.session.links import Links, close_links, connect, open_links, probe_timing
from rig.session.outcome import RunResult
from rig.session.preparation import AlarmLatched, PlanRefused, Prepared, RunOptions, prepare
from rig.session.runner import SessionRunner
from rig.session.terminal import execute, resume_command, run_session, terminal_progress

__all__ = ["EXIT_OK", "AlarmLatched", "Links", "PlanRefused", "Prepared", "RunOptions", "RunResult", "SessionContext",
           "SessionRunner", "close_links", "connect", "execute", "fit_session", "identify_session", "open_links",
           "prepare", "probe_timing", "resume_command", "run_lifecycle", "run_session", "terminal_progress"]
