"""``python -m rig qc run|judge|history``: pass/fail runs on production dampers.

``run``      the spec's plan on the rig, identification, the verdict with its
             uncertainty, a record in the database and a report in the session folder
``judge``    judge stored data again (a new spec or model): a new record referring to
             the first
``history``  the records, capability (n, mean, std, Cp, Cpk, pass/fail counts) per
             characteristic, individuals control charts

Exit status: 0 PASS, 1 FAIL, 4 INCONCLUSIVE (retest with more periods), 2 bad input,
3 aborted after the safe stop (no verdict), 130 interrupted after the safe stop,
70 an internal error.  ``history``: 0, or 2 for bad input.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
from pathlib import Path

from rig.errors import BadInput

# The commands import what they need when they run: `python -m rig run` does not pay
# for the database driver and matplotlib.


def _positive_int(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number of at least 1")
    return int(text)


def cmd_run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from rig.qc.run import QcOptions, qc_run

    opt = QcOptions(spec=args.spec, serial=args.serial, shaker=args.shaker, daq=args.daq, out=Path(args.out),
                    db=args.db, operator=args.operator, rig_id=args.rig_id, periods=args.periods,
                    reset_alarm=args.reset_alarm, rig_config=args.rig_config, calibration=args.calibration,
                    register_map=args.register_map)
    return qc_run(opt, Console(stderr=True, soft_wrap=True))


def cmd_judge(args: argparse.Namespace) -> int:
    from rig.qc.run import qc_judge

    return qc_judge(Path(args.session), args.spec, args.db, args.operator)


def _since(text: str | None) -> str | None:
    """An ISO date or time as the UTC ISO text the records hold (a naive time is local)."""
    if text is None:
        return None
    try:
        t = _dt.datetime.fromisoformat(text)
    except ValueError:
        raise BadInput(f"--since {text!r}: not an ISO date or time (2026-11-23 or 2026-11-23T14:00)") from None
    if len(text) == 10:
        t = t.replace(tzinfo=_dt.UTC)
    return (t if t.tzinfo else t.astimezone()).astimezone(_dt.UTC).isoformat(timespec="seconds")


def cmd_history(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from rig.qc.history import capability, control_charts, fmt
    from rig.qc.records import Records

    since = _since(args.since)
    records = Records.open(args.db)
    try:
        found = records.find(serial=args.serial, since=since)
    finally:
        records.close()
    if args.json:
        print(json.dumps([r.to_json() for r in found], indent=2))
    else:
        console = Console(soft_wrap=True)
        if not console.is_terminal:
            console = Console(soft_wrap=True, width=200)   # a pipe or a file: whole rows, not 80 columns
        table = Table(title=f"QC records in {records.name} ({len(found)})")
        for col in ("serial", "measured (UTC)", "verdict", "status", "spec", "failed", "operator", "rig"):
            table.add_column(col)
        for r in found:
            failed = ", ".join(c.name for c in r.characteristics if c.outcome == "FAIL")
            table.add_row(r.serial, (r.started or "—")[:19], r.verdict or "—", r.status,
                          f"{r.spec_name} {r.spec_version}" + (" (re-judged)" if r.rejudges else ""), failed,
                          r.operator, r.rig)
        console.print(table)
        caps = Table(title="Capability (latest judgement of each complete run; Cp, Cpk with σ = MR̄/1.128)")
        for col in ("characteristic", "unit", "n", "mean", "std", "Cp", "Cpk", "limits", "pass", "fail",
                    "inconclusive"):
            caps.add_column(col, justify="left" if col in ("characteristic", "unit", "limits") else "right")
        for c in capability(found):
            caps.add_row(c.name, c.unit, str(c.n), fmt(c.mean), fmt(c.std, 3), fmt(c.cp, 3), fmt(c.cpk, 3),
                         f"{fmt(c.low)} … {fmt(c.high)}", str(c.passed), str(c.failed), str(c.inconclusive))
        console.print(caps)
    if args.chart:
        for path in control_charts(found, Path(args.chart)):
            print(f"chart {path}", file=sys.stderr if args.json else sys.stdout)   # stdout stays JSON
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The ``qc`` command and its subcommands, under ``python -m rig``."""
    qc = sub.add_parser("qc", help="quality control: pass/fail runs on production dampers",
                        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    qsub = qc.add_subparsers(dest="qc_command", required=True)

    run = qsub.add_parser("run", help="test one unit: plan, identification, verdict, record, report")
    run.add_argument("--spec", default="default", help="default or QC.toml")
    run.add_argument("--serial", required=True, help="the unit's serial number (format set by the spec)")
    run.add_argument("--shaker", required=True, help="tcp://HOST:PORT or rtu:///dev/DEVICE")
    run.add_argument("--daq", required=True, help="device path, socket://HOST:PORT or any pyserial URL")
    run.add_argument("--out", required=True, help="the station's folder: a session folder per unit goes in it")
    run.add_argument("--db", help="records database URL: sqlite:///FILE or postgresql://USER@HOST:PORT/DB "
                                  "(default: OUT/qc-records.sqlite)")
    run.add_argument("--operator", help="who runs the test (default: the login name)")
    run.add_argument("--rig-id", help="this rig's name in the records (default: the host name)")
    run.add_argument("--periods", type=_positive_int, help="periods per experiment (the retest of an INCONCLUSIVE)")
    run.add_argument("--reset-alarm", action="store_true", help="clear an alarm latched before the run")
    run.add_argument("--rig-config", help="limits TOML (the spec's steady-state criteria replace its own)")
    run.add_argument("--calibration", help="DAQ calibration TOML of this rig")
    run.add_argument("--register-map", help="register map TOML")
    run.set_defaults(func=cmd_run)

    judge = qsub.add_parser("judge", help="judge stored data again: a new record referring to the first")
    judge.add_argument("session", help="session folder (or any dataset folder)")
    judge.add_argument("--spec", default="default", help="default or QC.toml")
    judge.add_argument("--db", help="records database URL (default: qc-records.sqlite beside the session folder)")
    judge.add_argument("--operator", help="for data without an earlier record (default: the login name)")
    judge.set_defaults(func=cmd_judge)

    history = qsub.add_parser("history", help="records, capability per characteristic, control charts")
    history.add_argument("--db", required=True, help="records database URL (or an SQLite file)")
    history.add_argument("--serial", help="one unit only")
    history.add_argument("--since", help="measured on or after this ISO date or time")
    history.add_argument("--json", action="store_true", help="print the records as a JSON list")
    history.add_argument("--chart", metavar="DIR", help="write an individuals control chart (PNG) per characteristic")
    history.set_defaults(func=cmd_history)
