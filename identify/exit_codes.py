"""The exit statuses of the project's commands (``identify``, ``rig``, ``rig qc``), defined once.

0 done; 1 identification did not converge; 2 bad input (one line naming it; nothing moved
or written); 3 the rig failed or refused, after the safe stop; 70 an internal error (a
bug: traceback shown), after the safe stop; 130 interrupted, after the safe stop.
"""

EXIT_OK = 0
EXIT_NOT_CONVERGED = 1
EXIT_BAD_INPUT = 2
EXIT_ABORTED = 3
EXIT_INTERNAL = 70          # EX_SOFTWARE of sysexits.h
EXIT_INTERRUPTED = 130      # 128 + SIGINT, as a shell reports Ctrl-C
