"""QC mode's rig side (no Qt here): one unit's test is ``python -m rig qc run`` itself, as a
child process, so that the console's verdict is the command line's to the byte (the same
checks, session, identification, judgement, record and report) and the identification,
which holds Python's interpreter lock for seconds, never stalls the window.

The verdict comes from the child's exit status (:data:`rig.qc.run.EXIT_BY_VERDICT`); the
report's path and the characteristics from the summary it prints.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from identify.exit_codes import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_INTERRUPTED
from rig.qc.judge import Outcome
from rig.qc.run import EXIT_BY_VERDICT

VERDICT_BY_EXIT = {code: outcome for outcome, code in EXIT_BY_VERDICT.items()}
# What the operator is told to do: an INCONCLUSIVE unit is neither passed nor failed, it is tested again.
SHOWN = {Outcome.PASS: "PASS", Outcome.FAIL: "FAIL", Outcome.INCONCLUSIVE: "RETEST"}
_REPORT = re.compile(r"^report (?P<report>.+); record (?P<uid>\S+) in (?P<db>.+)$")
_PERIODS = re.compile(r"--periods (\d+)")


@dataclass(frozen=True)
class QcRequest:
    serial: str
    spec: str = "default"
    out: Path = Path("qc")             # the station's folder: a session folder per unit, and the records
    operator: str | None = None
    periods: int | None = None         # a retest's: more than the spec's


@dataclass(frozen=True)
class QcDone:
    """How one unit's test ended, as the QC panel shows it."""

    serial: str
    exit_code: int
    shown: str                         # PASS, FAIL, RETEST, ABORTED, REFUSED or ERROR
    report: Path | None = None
    summary: list[str] = field(default_factory=list)    # the characteristics, likely causes, remedy
    reason: str = ""                   # why there is no verdict (refused, aborted, error)
    retest_periods: int | None = None  # RETEST: the periods of the retest


def qc_command(request: QcRequest, shaker: str, daq: str, config_files: dict[str, str | None]) -> list[str]:
    cmd = [sys.executable, "-m", "rig", "qc", "run", "--spec", request.spec, "--serial", request.serial,
           "--shaker", shaker, "--daq", daq, "--out", str(request.out)]
    if request.operator:
        cmd += ["--operator", request.operator]
    if request.periods:
        cmd += ["--periods", str(request.periods)]
    for option, path in config_files.items():
        if path:
            cmd += ["--" + option.replace("_", "-"), path]
    return cmd


def outcome(request: QcRequest, exit_code: int, stdout: str, stderr_tail: list[str]) -> QcDone:
    lines = [line for line in stdout.splitlines() if line.strip()]
    report = None
    for line in lines:
        if match := _REPORT.match(line):
            report = Path(match["report"])
    verdict = VERDICT_BY_EXIT.get(exit_code)
    if verdict is not None and report is not None:
        summary = [line.strip() for line in lines[1:] if not _REPORT.match(line)]
        periods = _PERIODS.search(" ".join(summary)) if verdict is Outcome.INCONCLUSIVE else None
        return QcDone(request.serial, exit_code, SHOWN[verdict], report, summary,
                      retest_periods=int(periods[1]) if periods else None)
    last = next((line for line in reversed(stderr_tail) if line.strip()), f"exit status {exit_code}")
    if exit_code == EXIT_BAD_INPUT:
        return QcDone(request.serial, exit_code, "REFUSED", reason=last)
    if exit_code in (EXIT_ABORTED, EXIT_INTERRUPTED):
        return QcDone(request.serial, exit_code, "ABORTED", _latest_report(request), reason=last)
    return QcDone(request.serial, exit_code, "ERROR", _latest_report(request), reason=last)


def _latest_report(request: QcRequest) -> Path | None:
    """An aborted or failed run's report (it says why there is no verdict): the unit's newest session's."""
    reports = sorted(Path(request.out).glob(f"{request.serial}-*/qc-report.html"), key=lambda p: p.parent.name)
    return reports[-1] if reports else None
