"""The command-line parser of the project's three CLIs: a usage error is one line.

argparse prints the whole usage (ten lines for ``simulator serve``) before the line that
says what is wrong, and a user's mistake is answered in one line everywhere else; the
usage stays one ``--help`` away."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from identify.exit_codes import EXIT_BAD_INPUT


class OneLineParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are ``PROG: error: MESSAGE (PROG --help)``
    and exit 2; sub-commands get the same class."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message} (see {self.prog} --help)\n")
        sys.exit(EXIT_BAD_INPUT)
