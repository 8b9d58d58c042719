"""QC mode's rig side (no Qt here): one unit's test is ``python -m rig qc run`` itself, as a
child process, so that the console's verdict is the command line's to the byte (the same
checks, session, identification, judgement, record and report) and the identification,
which holds Python's interpreter lock for seconds, never stalls the window.

The verdict comes from the child's exit status (:data:`rig.qc.run.EXIT_BY_VERDICT`); the
report's path and the characteristics from the summary it prints (one row per
characteristic, cells separated by " | ", as rig.qc.present formats them); the progress
from its session lines (the announced rig time, each experiment's phases and capture).
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from identify.exit_codes import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_INTERRUPTED
from rig.events import Message, Phase
from rig.qc.judge import Outcome
from rig.qc.run import EXIT_BY_VERDICT

VERDICT_BY_EXIT = {code: outcome for outcome, code in EXIT_BY_VERDICT.items()}
# What the operator is told to do: an INCONCLUSIVE unit is neither passed nor failed, it is tested again.
SHOWN = {Outcome.PASS: "PASS", Outcome.FAIL: "FAIL", Outcome.INCONCLUSIVE: "RETEST"}
_REPORT = re.compile(r"^report (?P<report>.+); record (?P<uid>\S+) in (?P<db>.+)$")
_ANNOUNCED = re.compile(r"^session: (?P<n>\d+) experiments?, about (?P<m>\d+):(?P<s>\d\d) min:s of rig time")
_STEP = re.compile(r"^\[\s*(?P<i>\d+)/(?P<n>\d+)\]\s+(?P<label>\S+)\s+(?P<what>.*)$")
_CAPTURED = re.compile(r"[Cc]aptured (?P<pct>\d+) %")
PHASES = {p.value for p in Phase}
_PERIODS = re.compile(r"--periods (\d+)")


@dataclass(frozen=True)
class QcRequest:
    serial: str
    spec: str = "default"
    out: Path = Path("qc")             # the station's folder: a session folder per unit, and the records
    operator: str | None = None
    periods: int | None = None         # a retest's: more than the spec's


@dataclass(frozen=True)
class QcRow:
    """One characteristic as the summary prints it (rig.qc.present), each cell with its unit."""

    outcome: str
    title: str
    value: str           # value ± k·σ
    limits: str
    acceptance: str
    sigma: str = ""


@dataclass(frozen=True)
class QcProgress(Message):
    """How far a unit's test is: the fraction of the plan's rig time done and what is left."""

    fraction: float
    rig_left_s: float | None
    text: str            # what it does now: "experiment 2 of 3 (v): settling"


class ProgressReader:
    """Reads the QC run's session lines (stderr) into :class:`QcProgress`: the rig time
    announced at the start, the experiments begun (by label: a file is written after the
    next experiment has begun), those captured, the running one's capture."""

    def __init__(self) -> None:
        self.total_s: float | None = None
        self.count = 0
        self.begun: list[str] = []
        self.done = 0
        self.current = 0.0     # the running experiment's captured fraction

    def feed(self, line: str) -> QcProgress | None:
        line = line.strip()
        if m := _ANNOUNCED.match(line):
            self.total_s, self.count = int(m["m"]) * 60.0 + int(m["s"]), int(m["n"])
            return self._progress("session started: the first experiment")
        m = _STEP.match(line)
        if m is None or not self.count:
            return None
        label, what = m["label"], m["what"].strip()
        if what.startswith("Written to ") or (what.startswith("captured ") and not _CAPTURED.search(what)):
            self.done = min(self.done + 1, self.count)
            return self._progress(f"experiment {len(self.begun)} of {self.count} ({self.begun[-1]})"
                                  if self.begun else "")
        words = what.lower().rstrip(".").split()
        phase = next((w for w in words[:2] if w in PHASES), "")
        if not phase and not _CAPTURED.search(what):
            return None
        if label not in self.begun:
            self.begun.append(label)
            self.current = 0.0
        if pct := _CAPTURED.search(what):
            self.current = int(pct["pct"]) / 100
            phase = "capturing"
        return self._progress(f"experiment {len(self.begun)} of {self.count} ({label}): {phase}")

    def _progress(self, text: str) -> QcProgress:
        running = max(len(self.begun) - 1, 0) + self.current
        fraction = min(max(self.done, running) / self.count, 1.0) if self.count else 0.0
        left = None if self.total_s is None else self.total_s * (1.0 - fraction)
        return QcProgress(fraction, left, text)


@dataclass(frozen=True)
class QcDone(Message):
    """How one unit's test ended, as the QC panel shows it."""

    serial: str
    exit_code: int
    shown: str                         # PASS, FAIL, RETEST, ABORTED, REFUSED or ERROR
    report: Path | None = None
    summary: list[str] = field(default_factory=list)    # the characteristics, likely causes, remedy
    rows: list[QcRow] = field(default_factory=list)
    causes: list[str] = field(default_factory=list)     # likely causes, in full
    remedy: str = ""
    simulated: bool = False            # the record says a peer named itself a simulator
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
        rows = []
        for line in summary:
            cells = [c.strip() for c in line.split(" | ")]
            if len(cells) == 6:
                rows.append(QcRow(cells[0], cells[1], cells[2], cells[3].removeprefix("limits "),
                                  cells[4].removeprefix("accept "), cells[5].removeprefix("σ ")))
        causes = [line.removeprefix("likely cause: ") for line in summary if line.startswith("likely cause: ")]
        remedy = next((line.removeprefix("remedy: ") for line in summary if line.startswith("remedy: ")), "")
        return QcDone(request.serial, exit_code, SHOWN[verdict], report, summary,
                      retest_periods=int(periods[1]) if periods else None, rows=rows, causes=causes, remedy=remedy,
                      simulated="SIMULATED" in lines[0])
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
