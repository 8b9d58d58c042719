"""``python -m rig qc run|judge|history``: pass/fail runs on production dampers.

``run``      the spec's plan on the rig, identification, the verdict with its
             uncertainty, a record in the database and a report in the session folder
``judge``    judge stored data again (a new spec or model): a new record referring to
             the first
``history``  the records, capability (n, mean, std, Cp, Cpk, pass/fail counts) per
             characteristic, individuals control charts
``sync``     a station's queued records to the database (and runs a killed process
             left on the rig recorded as ABORTED)

Exit status: 0 PASS, 1 FAIL, 4 INCONCLUSIVE (retest with more periods), 2 bad input,
3 aborted after the safe stop (no verdict), 130 interrupted after the safe stop,
70 an internal error; a record the database did not take is queued in the station's
folder, and the exit status is the verdict's all the same.  ``history``: 0; 1 when
``--chart DIR`` wrote no chart (every record left out, the line says which and why:
simulated, aborted); 2 for bad input.  ``sync``: 0 when nothing is left queued, 3 when
records stay queued (the database unreachable), 2 for bad input.  ``history`` and
``judge`` open an existing records database only (2 when there is none); ``run`` creates
its own.  A database URL never carries a password (refused, 2): see docs/qc.md,
"Station set-up".
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
from pathlib import Path

from rig.errors import BadInput
from rig.qc import DEFAULT_SPEC

# The commands import what they need when they run: `python -m rig run` does not pay
# for the database driver and matplotlib.

EXIT_NOTHING_CHARTED = 1   # history --chart DIR wrote no chart (every record left out; the line says why)


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

    return qc_judge(Path(args.session), args.spec, args.db, args.operator, args.create_db)


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


def latest_only(records: list, superseded: dict[str, str]) -> list:
    """Each test's latest judgement (a record no later one of the same data supersedes)."""
    return [r for r in records if r.uid not in superseded]


def cmd_sync(args: argparse.Namespace) -> int:
    from rich.console import Console

    from rig.qc.queue import Outbox

    console = Console(stderr=True, soft_wrap=True)
    outbox = Outbox.open(Path(args.out), args.db, lambda text: console.print(text, highlight=False))
    # (it recorded the runs a killed process left and sent the queue)
    try:
        left = len(outbox.queue.pending())
    finally:
        outbox.close()
    print(f"{left} record{'s' * (left != 1)} queued in {outbox.queue.pending_dir}" if left else
          f"nothing queued: every record of {args.out} is in {outbox.records.name}")
    return 3 if left else 0


def _queue_warning(args: argparse.Namespace, url: str) -> str | None:
    """A warning when the station folder (``--out``, or an SQLite database's own folder)
    holds records not yet in the database."""
    from rig.qc.queue import pending_count
    from rig.qc.records import parse_url

    parsed = parse_url(url)
    folders = [Path(args.out)] if args.out else []
    if parsed.get_backend_name() == "sqlite":
        folders.append(Path(str(parsed.database)).parent)
    for folder in dict.fromkeys(f.resolve() for f in folders):
        n = pending_count(folder)
        if n:
            return (f"warning: {n} record{'s' * (n != 1)} of station {folder} queued, not yet in this database "
                    f"(python -m rig qc sync --out {folder} sends them)")
    return None


def cmd_history(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from rig.qc.history import MIN_CAPABILITY_N, capability, control_charts, index, left_out, stat
    from rig.qc.judge import Outcome
    from rig.qc.present import limits_text
    from rig.qc.records import Records, default_url, superseded
    from rig.qc.station import load_station_config

    since = _since(args.since)
    config = load_station_config(Path(args.out)) if args.out else None
    url = args.db or (config.db if config else None) or (default_url(Path(args.out)) if args.out else None)
    if url is None:
        raise BadInput("qc history: give --db URL or --out STATION_DIR")
    # never created here: a mistyped path is refused
    records = Records.open(url, password=config.password if config else None)
    try:
        everything = records.find(serial=args.serial, since=since, station=args.station)
    finally:
        records.close()
    warning = _queue_warning(args, url)
    if warning:
        print(warning, file=sys.stderr)
    later = superseded(everything)
    found = everything if args.all else latest_only(everything, later)
    if args.json:
        print(json.dumps([r.to_json(later.get(r.uid)) for r in found], indent=2))
    else:
        console = Console(soft_wrap=True)
        if not console.is_terminal:
            console = Console(soft_wrap=True, width=200)   # a pipe or a file: whole rows, not 80 columns
        which = "every record" if args.all else "each test's latest judgement; --all: every record"
        table = Table(title=f"QC records in {records.name} ({len(found)}: {which})")
        for col in ("serial", "measured (UTC)", "verdict", "status", "spec", "failed", "operator", "station", "rig",
                    "record"):
            table.add_column(col)
        for r in found:
            failed = ", ".join(c.title or c.name for c in r.characteristics if c.outcome == Outcome.FAIL)
            verdict = (r.verdict or "—") + (" SIMULATED" if r.simulated else "")
            spec = f"{r.spec_name} {r.spec_version}" + (" (re-judged)" if r.rejudges else "")
            if r.uid in later:
                spec += f" (superseded by {later[r.uid][:8]})"
            table.add_row(r.serial, (r.started or "—")[:19], verdict, r.status + (f": {r.reason}" if r.reason else ""),
                          spec, failed, r.operator, r.station or "—", r.rig, r.uid[:8])
        console.print(table)
        counted = "simulated included" if args.include_simulated else "simulated left out (--include-simulated)"
        caps = Table(title=f"Capability: the latest judgement of each complete run, {counted}; I-MR limits "
                           f"from {'the first ' + str(args.baseline) + ' units' if args.baseline else 'every unit'},"
                           " points beyond them left out; σ within = MR̄/1.128")
        for col in ("characteristic", "n", "mean", "σ within", "control limits", "Cp", "Cpk", "spec limits",
                    "pass", "fail", "inconclusive"):
            caps.add_column(col, justify="left" if col in ("characteristic", "control limits", "spec limits")
                            else "right")
        caps_found = capability(everything, args.include_simulated, args.baseline)
        omitted = left_out(everything, args.include_simulated)
        if omitted:
            caps.caption = omitted
        for c in caps_found:
            limits = "—" if c.lcl is None else f"{stat(c.lcl, c)} … {stat(c.ucl, c)}"
            if c.n < c.n_units:
                limits += f" ({c.n_units - c.n} left out)"
            caps.add_row(c.title, str(c.n), stat(c.mean, c), stat(c.sigma_within, c), limits, index(c.cp, c),
                         index(c.cpk, c), limits_text(c.nominal, c.low, c.high, c.unit), str(c.passed),
                         str(c.failed), str(c.inconclusive))
        if caps_found:
            console.print(caps)
        else:   # a table of headers only said nothing; this says why
            console.print(f"Capability: no unit to count ({omitted or 'no complete run with a value'})",
                          highlight=False)
        if any(not c.meaningful for c in caps_found):
            console.print(f"(Cp), (Cpk): not meaningful, fewer than {MIN_CAPABILITY_N} units (AIAG SPC manual)",
                          highlight=False)
    if args.chart:
        charts = control_charts(everything, Path(args.chart), args.include_simulated, args.baseline)
        for path in charts:
            print(f"chart {path}", file=sys.stderr if args.json else sys.stdout)   # stdout stays JSON
        if not charts:   # asked for charts and none written: said, and not a success
            print(f"no chart written to {args.chart}: no unit to chart "
                  f"({left_out(everything, args.include_simulated) or 'no complete run with a value'})",
                  file=sys.stderr)
            return EXIT_NOTHING_CHARTED
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The ``qc`` command and its subcommands, under ``python -m rig``."""
    qc = sub.add_parser("qc", help="quality control: pass/fail runs on production dampers",
                        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    qsub = qc.add_subparsers(dest="qc_command", required=True)

    run = qsub.add_parser("run", help="test one unit: plan, identification, verdict, record, report")
    run.add_argument("--spec", default=DEFAULT_SPEC,
                     help=f"a shipped spec ({DEFAULT_SPEC}: measurands at the axle, the default; default: the "
                          "model-based one of before; transient; measurands-model) or QC.toml")
    run.add_argument("--serial", required=True, help="the unit's serial number (format set by the spec)")
    run.add_argument("--shaker", required=True, help="tcp://HOST:PORT or rtu:///dev/DEVICE")
    run.add_argument("--daq", required=True, help="device path, socket://HOST:PORT or any pyserial URL")
    run.add_argument("--out", required=True, help="the station's folder: a session folder per unit goes in it")
    run.add_argument("--db", help="records database URL without a password: sqlite:///FILE or "
                                  "postgresql://USER@HOST:PORT/DB (default: OUT/station.toml's, else "
                                  "OUT/qc-records.sqlite)")
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
    judge.add_argument("--spec", help=f"a shipped spec or QC.toml (default: the spec of the data's first record, "
                                      f"else {DEFAULT_SPEC})")
    judge.add_argument("--db", help="records database URL (default: qc-records.sqlite beside the session folder)")
    judge.add_argument("--operator", help="for data without an earlier record (default: the login name)")
    judge.add_argument("--create-db", action="store_true",
                       help="create the records database where none exists (otherwise a missing one is refused)")
    judge.set_defaults(func=cmd_judge)

    history = qsub.add_parser("history", help="records, capability per characteristic, control charts")
    history.add_argument("--db", help="records database URL (or an SQLite file); default: the station's (--out)")
    history.add_argument("--out", metavar="STATION_DIR",
                         help="a station's folder: its station.toml's database, and a warning if records are queued")
    history.add_argument("--serial", help="one unit only")
    history.add_argument("--station", help="one station's records only (capability and charts too)")
    history.add_argument("--since", help="measured on or after this ISO date or time")
    history.add_argument("--json", action="store_true", help="print the records as a JSON list")
    history.add_argument("--all", action="store_true",
                         help="every record, re-judged ones too (default: each test's latest judgement)")
    history.add_argument("--include-simulated", action="store_true",
                         help="count records measured on a simulator in the statistics (left out by default)")
    history.add_argument("--baseline", type=_positive_int, metavar="N",
                         help="control limits from the first N units (default: every unit)")
    history.add_argument("--chart", metavar="DIR", help="write an individuals control chart (PNG) per characteristic")
    history.set_defaults(func=cmd_history)

    sync = qsub.add_parser("sync", help="send a station's queued records to the database")
    sync.add_argument("--out", required=True, metavar="STATION_DIR", help="the station's folder (qc run's --out)")
    sync.add_argument("--db", help="records database URL (default: the station's station.toml, else "
                                   "STATION_DIR/qc-records.sqlite)")
    sync.set_defaults(func=cmd_sync)
