"""``python -m rig qc run|judge|history``: pass/fail runs on production dampers.

``run``      the spec's plan on the rig, identification, the verdict with its
             uncertainty, a record in the database and a report in the session folder
``judge``    judge stored data again (a new spec or model): a new record referring to
             the first
``history``  the records, capability (n, mean, std, Cp, Cpk, pass/fail counts) per
             characteristic, individuals control charts
``sync``     a station's queued records to the database (and runs a killed process
             left on the rig recorded as ABORTED)
``release``  a second person's approval of a unit's latest judgement
``station``  ``check``: commission a station (database, addresses, calibration, spec);
             ``pin``: the hash of an operator's PIN for station.toml
``db``       ``init``: the administrator makes (or upgrades) the schema and grants
             station roles INSERT and SELECT only

Exit status: 0 PASS, 1 FAIL, 4 INCONCLUSIVE (retest with more periods), 2 bad input,
3 aborted after the safe stop (no verdict), 130 interrupted after the safe stop,
70 an internal error; a record the database did not take is queued in the station's
folder, and the exit status is the verdict's all the same.  ``history``: 0; 1 when
``--chart DIR`` wrote no chart (every record left out, the line says which and why:
simulated, aborted) or ``--verify`` found a record changed, deleted or inserted; 3 when
``--out``'s database is down (its queued records listed); 2 for bad input.
``station check``: 0 every item passed, 1 one failed.  ``release``, ``db init``: 0, or 2
for bad input and refusals.  ``sync``: 0 when nothing is left queued, 3 when
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
from typing import TYPE_CHECKING

from rig.errors import BadInput
from rig.qc import DEFAULT_SPEC

if TYPE_CHECKING:
    from rig.qc.run import QcOptions

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


def _study_options(args: argparse.Namespace, serial: str) -> QcOptions:
    from rig.qc.run import QcOptions

    return QcOptions(spec=args.spec, serial=serial, shaker=args.shaker, daq=args.daq, out=Path(args.out), db=args.db,
                     operator=args.operator, rig_id=args.rig_id, rig_config=args.rig_config,
                     calibration=args.calibration, register_map=args.register_map)


def _say(text: str) -> None:
    print(text, flush=True)


def cmd_check(args: argparse.Namespace) -> int:
    from rig.qc.msa_run import run_check

    return run_check(_study_options(args, args.master), args.master, args.reference, _say)


def cmd_type1(args: argparse.Namespace) -> int:
    from rig.qc.msa_run import run_type1

    return run_type1(_study_options(args, args.master), args.master, args.reference, args.runs, _say)


def cmd_type3(args: argparse.Namespace) -> int:
    from rig.qc.msa_run import mount_by_command, run_type3

    units = [u.strip() for u in args.units.split(",") if u.strip()]
    return run_type3(_study_options(args, units[0] if units else ""), units, args.repeats, _say,
                     mount_by_command(args.mount_command, _say), args.order_seed)


def cmd_uncertainty(args: argparse.Namespace) -> int:
    from rig.qc.calibration import (
        identification_recompute,
        is_certificate_file,
        load_certificates,
        store_budget,
        uncertainty_budget,
    )
    from rig.qc.spec import load_spec

    spec = load_spec(args.spec)
    if not is_certificate_file(args.calibration):
        raise BadInput(f"--calibration {args.calibration}: no [[transducer]] certificates to derive u_cal from")
    budget = uncertainty_budget(identification_recompute(spec, Path(args.session)),
                                load_certificates(args.calibration))
    for c in spec.characteristics:
        b = budget[c.name]
        parts = ", ".join(f"{x.channel} {x.component} {x.u_characteristic:.2g}" for x in
                          sorted(b.contributions, key=lambda x: -x.u_characteristic)[:3])
        print(f"{c.shown}: u_cal {b.u_cal:.2g} {c.unit} from the certificates (the spec types {c.u_cal:g}); "
              f"largest: {parts}")
    if args.out:
        print(f"stored for qc run: {store_budget(Path(args.out), spec, args.calibration, Path(args.session), budget)}")
    return 0


def cmd_judge(args: argparse.Namespace) -> int:
    from rig.qc.run import qc_judge

    return qc_judge(Path(args.session), args.spec, args.db, args.operator, args.create_db, args.reason,
                    Path(args.out) if args.out else None)


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
        elsewhere = sorted({e.queued_for for e in outbox.queue.entries()
                            if e.queued_for is not None and e.queued_for != outbox.records.name})
        if elsewhere and (args.send_to_current or _ask(
                f"records are queued for {', '.join(elsewhere)}; send them to {outbox.records.name} instead? [y/N] ")):
            outbox.send(anywhere=True)
        left = len(outbox.queue.pending())
    finally:
        outbox.close()
    print(f"{left} record{'s' * (left != 1)} queued in {outbox.queue.pending_dir}" if left else
          f"nothing queued: every record of {args.out} is in {outbox.records.name}")
    return 3 if left else 0


def _ask(question: str) -> bool:
    """A yes/no question on the terminal; no terminal: no."""
    if not sys.stdin.isatty():
        print(f"{question.rstrip(' [y/N]')}: not asked (no terminal); --send-to-current sends them",
              file=sys.stderr)
        return False
    return input(question).strip().lower() in ("y", "yes")


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
    from rig.qc.records import Records, Unreachable, default_url, superseded
    from rig.qc.station import load_station_config

    since = _since(args.since)
    config = load_station_config(Path(args.out)) if args.out else None
    url = args.db or (config.db if config else None) or (default_url(Path(args.out)) if args.out else None)
    if url is None:
        raise BadInput("qc history: give --db URL or --out STATION_DIR")
    # never created here: a mistyped path is refused
    try:
        records = Records.open(url, password=config.password if config else None)
    except Unreachable as exc:
        if not args.out:
            raise
        return _history_unreachable(Path(args.out), exc)
    try:
        if args.verify:
            return _verify(records, args)
        everything = records.find(serial=args.serial, since=since, station=args.station)
        released = {r.record_uid: r for r in records.releases(args.serial)}
        records_studies = records.studies()
    finally:
        records.close()
    warning = _queue_warning(args, url)
    if warning:
        print(warning, file=sys.stderr)
    later = superseded(everything)
    found = everything if args.all else latest_only(everything, later)
    if args.json:
        print(json.dumps([{**r.to_json(later.get(r.uid)), "released": _released(released.get(r.uid))}
                          for r in found], indent=2))
    else:
        console = Console(soft_wrap=True)
        if not console.is_terminal:
            console = Console(soft_wrap=True, width=200)   # a pipe or a file: whole rows, not 80 columns
        which = "every record" if args.all else "each test's latest judgement; --all: every record"
        table = Table(title=f"QC records in {records.name} ({len(found)}: {which})")
        for col in ("serial", "measured (UTC)", "verdict", "status", "spec", "failed", "operator", "station", "rig",
                    "record") + (("released by",) if released else ()):
            table.add_column(col)
        for r in found:
            failed = ", ".join(c.title or c.name for c in r.characteristics if c.outcome == Outcome.FAIL)
            verdict = (r.verdict or "—") + (" SIMULATED" if r.simulated else "")
            spec = f"{r.spec_name} {r.spec_version}" + (" (re-judged)" if r.rejudges else "")
            if r.uid in later:
                spec += f" (superseded by {later[r.uid][:8]})"
            release = released.get(r.uid)
            table.add_row(r.serial, (r.started or "—")[:19], verdict, r.status + (f": {r.reason}" if r.reason else ""),
                          spec, failed, r.operator, r.station or "—", r.rig, r.uid[:8],
                          *((f"{release.approver} {release.released[:16]}" if release else "—",) if released else ()))
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
    if not args.json:
        _print_studies(records_studies, Path(args.out) if args.out else None)
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


def _released(release) -> dict | None:
    return None if release is None else {"by": release.approver, "identified_by": release.identified_by,
                                         "at": release.released, "note": release.note, "uid": release.uid}


EXIT_UNREACHABLE = 3        # history: the database did not answer (the station's queue is listed)
EXIT_TAMPERED = 1          # history --verify: a record changed, deleted or inserted


def _history_unreachable(out: Path, exc: Exception) -> int:
    """The station's database is down: said, and what the station holds queued listed."""
    from rig.qc.queue import RecordQueue

    queued = RecordQueue(out).entries()
    print(f"{exc}: the database cannot be read now; {len(queued)} record{'s' * (len(queued) != 1)} of station "
          f"{out} queued{':' if queued else ''}", file=sys.stderr)
    for q in queued:
        print(f"  {q.judged}  {q.serial}  {q.verdict or q.status}  record {q.uid}  for {q.queued_for or '—'}")
    return EXIT_UNREACHABLE


def _verify(records, args: argparse.Namespace) -> int:
    """``history --verify``: every station's hash chain, and the station's own copies (``--out``)."""
    from rig.qc.integrity import sentence, verify
    from rig.qc.records import station_copies

    found = records.find(station=args.station)
    copies = station_copies(Path(args.out), records.name) if args.out else []
    result = verify(found, copies)
    for problem in result.problems:
        print(sentence(problem))
    stations = len({r.station for r in found})
    print(f"{records.name}: {result.checked} record{'s' * (result.checked != 1)} of {stations} "
          f"station{'s' * (stations != 1)} checked against their hash chains"
          + (f", {len(copies)} against the station's own copies" if args.out else "")
          + (f"; {result.unchained} written before the chain (schema version < 4) cannot be checked"
             if result.unchained else "")
          + (": intact" if result.ok else f": {len(result.problems)} problem{'s' * (len(result.problems) != 1)}"))
    return 0 if result.ok else EXIT_TAMPERED


def cmd_db_init(args: argparse.Namespace) -> int:
    from rig.qc.records import init_schema

    if bool(args.db) == bool(args.admin_service):
        raise BadInput("qc db init: give --admin-service NAME or --db ADMIN_URL (one of them)")
    url = args.db or f"postgresql:///?service={args.admin_service}"
    name, version, rights = init_schema(url, tuple(args.grant or ()))
    print(f"{name}: QC records schema version {version}"
          + (f", owned by {rights.role}" if rights else ""))
    for role in args.grant or ():
        print(f"  {role}: SELECT on every table, INSERT on qc_record, qc_characteristic, qc_release and qc_study; "
              "nothing else")
    if rights is not None and not args.grant:
        print("  no station role granted (--grant ROLE): stations cannot write yet")
    return 0


def cmd_station_check(args: argparse.Namespace) -> int:
    from rig.qc.commissioning import check_station, write
    from rig.qc.station import load_station_config

    out = Path(args.out)
    config = load_station_config(out)
    result = check_station(out, config, args.db, args.shaker or config.shaker, args.daq or config.daq,
                           args.calibration or config.calibration, args.spec)
    for line in result.lines():
        print(line)
    path = write(out, result)
    print(f"written to {path}", file=sys.stderr)
    return 0 if result.passed else 1


def cmd_station_pin(args: argparse.Namespace) -> int:
    from rig.qc.station import pin_hash, read_pin

    pin = read_pin("new PIN: ")
    if len(pin) < 4 or (sys.stdin.isatty() and read_pin("the PIN again: ") != pin):
        raise BadInput("PIN: at least 4 characters, typed the same twice")
    print(f'pin = "{pin_hash(pin)}"')
    return 0


def cmd_release(args: argparse.Namespace) -> int:
    """``qc release SERIAL``: a second person approves the unit's latest judgement."""
    import uuid

    from rig.qc.records import Records, RecordStatus, Release, default_url, superseded
    from rig.qc.station import identify_operator, load_station_config
    from rig.qc.trace import now_utc

    out = Path(args.out)
    config = load_station_config(out)
    who = identify_operator(config, args.approver)
    records = Records.open(args.db or config.db or default_url(out), password=config.password, writer=True)
    try:
        found = records.find(serial=args.serial)
        latest = latest_only(found, superseded(found))
        if not latest:
            raise BadInput(f"qc release {args.serial}: no record of this unit in {records.name}")
        record = latest[-1]
        if record.status != RecordStatus.COMPLETE:
            raise BadInput(f"qc release {args.serial}: its latest record {record.uid} has no verdict ({record.status})")
        if record.operator == who.operator:
            raise BadInput(f"qc release {args.serial}: {who.operator} judged it (record {record.uid}); a release is "
                           "a second person's")
        release = Release(str(uuid.uuid4()), record.uid, record.serial, who.operator, who.by, now_utc(),
                          config.name, args.note)
        records.add_release(release)
    finally:
        records.close()
    print(f"{args.serial}: record {record.uid} ({record.verdict}, judged by {record.operator}) released by "
          f"{who.operator} ({who.by}) at {release.released}")
    return 0


def _print_studies(in_database: list[dict], station: Path | None) -> None:
    """The measurement-system studies and master checks: the database's and the station's
    own copies (one not yet in the database says so)."""
    from rich.console import Console
    from rich.table import Table

    from rig.qc.studies import stored

    docs = {d["uid"]: (d, True) for d in in_database}
    for study in stored(station) if station is not None else []:
        docs.setdefault(study.uid, (study.to_json(), False))
    if not docs:
        return
    table = Table(title=f"Measurement-system studies and master checks ({len(docs)})")
    for col in ("finished (UTC)", "kind", "result", "units", "spec", "station", "summary", "study"):
        table.add_column(col)
    for d, in_db in sorted(docs.values(), key=lambda x: x[0]["at"]):
        result = ("PASS" if d["passed"] else "FAIL") if d["kind"] == "check" else \
            ("goals met" if d["passed"] else "goals missed")
        table.add_row(d["at"][:19], d["kind"], result + (" SIMULATED" if d["simulated"] else ""),
                      ", ".join(d["units"]), f"{d['spec_name']} {d['spec_version']}", d["station"] or "—",
                      d["summary"], d["uid"][:8] + ("" if in_db else " (station copy only)"))
    console = Console(soft_wrap=True)
    if not console.is_terminal:
        console = Console(soft_wrap=True, width=200)
    console.print(table)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The ``qc`` command and its subcommands, under ``python -m rig``."""
    qc = sub.add_parser("qc", help="quality control: pass/fail runs on production dampers",
                        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    qsub = qc.add_subparsers(dest="qc_command", required=True)

    run = qsub.add_parser("run", help="test one unit: plan, identification, verdict, record, report")
    run.add_argument("--spec", default=DEFAULT_SPEC,
                     help=f"a shipped spec ({DEFAULT_SPEC}, the default: identified characteristics; measurands: "
                          "measured at the axle; measurands-model; transient) or QC.toml")
    run.add_argument("--serial", required=True, help="the unit's serial number (format set by the spec)")
    run.add_argument("--shaker", help="tcp://HOST:PORT or rtu:///dev/DEVICE (default: station.toml's shaker)")
    run.add_argument("--daq", help="device path, socket://HOST:PORT or any pyserial URL (default: station.toml's)")
    run.add_argument("--out", required=True, help="the station's folder: a session folder per unit goes in it")
    run.add_argument("--db", help="records database URL without a password: sqlite:///FILE or "
                                  "postgresql://USER@HOST:PORT/DB (default: OUT/station.toml's, else "
                                  "OUT/qc-records.sqlite)")
    run.add_argument("--operator", help="who runs the test, on a bench folder without station.toml (default: the "
                                        "login name); a station identifies its operator itself")
    run.add_argument("--rig-id", help="this rig's name in the records (default: the host name)")
    run.add_argument("--periods", type=_positive_int, help="periods per experiment (the retest of an INCONCLUSIVE)")
    run.add_argument("--reset-alarm", action="store_true", help="clear an alarm latched before the run")
    run.add_argument("--rig-config", help="limits TOML (the spec's steady-state criteria replace its own)")
    run.add_argument("--calibration", help="DAQ calibration TOML of this rig")
    run.add_argument("--register-map", help="register map TOML")
    run.set_defaults(func=cmd_run)

    def station_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--spec", default="default", help="default or QC.toml")
        p.add_argument("--shaker", required=True, help="tcp://HOST:PORT or rtu:///dev/DEVICE")
        p.add_argument("--daq", required=True, help="device path, socket://HOST:PORT or any pyserial URL")
        p.add_argument("--out", required=True, help="the station's folder (its qc-studies/ holds the studies)")
        p.add_argument("--db", help="records database URL without a password (as qc run)")
        p.add_argument("--operator", help="who runs it (default: the login name)")
        p.add_argument("--rig-id", help="this rig's name in the records (default: the host name)")
        p.add_argument("--rig-config", help="limits TOML")
        p.add_argument("--calibration", help="the station's certificate file (default: OUT/calibration.toml)")
        p.add_argument("--register-map", help="register map TOML")

    check = qsub.add_parser("check", help="the daily master check: the master unit against its reference values")
    check.add_argument("--master", required=True, help="the master unit's serial")
    check.add_argument("--reference", required=True, metavar="REF.toml", help="the master's reference values")
    station_args(check)
    check.set_defaults(func=cmd_check)

    msa = qsub.add_parser("msa", help="measurement-system studies: type 1 (a master, Cg/Cgk), type 3 (units, %%GRR)")
    msub = msa.add_subparsers(dest="msa_command", required=True)
    type1 = msub.add_parser("type1", help="the master unit N times: Cg, Cgk, bias and its t-test, run charts")
    type1.add_argument("--master", required=True, help="the master unit's serial")
    type1.add_argument("--reference", required=True, metavar="REF.toml", help="the master's reference values")
    type1.add_argument("--runs", type=_positive_int, default=25, help="runs (at least 25; default 25)")
    station_args(type1)
    type1.set_defaults(func=cmd_type1)
    type3 = msub.add_parser("type3", help="units × repeats in a randomised order: %%GRR, ndc, ANOVA")
    type3.add_argument("--units", required=True, help="comma-separated serials (at least 10)")
    type3.add_argument("--repeats", type=_positive_int, default=2, help="repeats per unit (at least 2; default 2)")
    type3.add_argument("--mount-command", help="run as COMMAND SERIAL before each run (a unit changer; default: "
                                               "ask the operator to mount the unit and press Enter)")
    type3.add_argument("--order-seed", type=int, help="seed of the randomised order (default: a fresh one)")
    station_args(type3)
    type3.set_defaults(func=cmd_type3)

    unc = qsub.add_parser("uncertainty", help="each characteristic's calibration uncertainty from the certificates "
                                               "(GUM sensitivity coefficients on a measured session)")
    unc.add_argument("session", help="a session folder of the unit (the master's) to derive it on")
    unc.add_argument("--spec", default="default", help="default or QC.toml")
    unc.add_argument("--calibration", required=True, help="the station's certificate file")
    unc.add_argument("--out", metavar="STATION_DIR", help="store it for the station's qc run (in place of the spec's "
                                                          "u_cal)")
    unc.set_defaults(func=cmd_uncertainty)

    judge = qsub.add_parser("judge", help="judge stored data again: a new record referring to the first")
    judge.add_argument("session", help="session folder (or any dataset folder)")
    judge.add_argument("--spec", help=f"a shipped spec or QC.toml (default: the spec of the data's first record, "
                                      f"else {DEFAULT_SPEC})")
    judge.add_argument("--db", help="records database URL (default: the station's station.toml, else "
                                    "qc-records.sqlite beside the session folder)")
    judge.add_argument("--operator", help="who re-judges, on a bench folder without station.toml (default: the "
                                          "login name); a station identifies its operator itself")
    judge.add_argument("--reason", help="why the data are judged again (on record)")
    judge.add_argument("--out", metavar="STATION_DIR",
                       help="the station's folder: its station.toml (default: the session folder's own folder)")
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
    history.add_argument("--verify", action="store_true",
                         help="check every station's hash chain (and --out's own copies): changed, deleted or "
                              "inserted records; exit 1 if any")
    history.set_defaults(func=cmd_history)

    release = qsub.add_parser("release", help="a second person approves a unit's latest judgement")
    release.add_argument("serial")
    release.add_argument("--out", required=True, metavar="STATION_DIR", help="the station's folder")
    release.add_argument("--db", help="records database URL (default: the station's)")
    release.add_argument("--note", help="a note on record with the release")
    release.add_argument("--approver", help="on a bench folder without station.toml only (default: the login)")
    release.set_defaults(func=cmd_release)

    db = qsub.add_parser("db", help="the records database (an administrator's commands)")
    dsub = db.add_subparsers(dest="db_command", required=True)
    init = dsub.add_parser("init", help="make or upgrade the schema, owned by the administrator's role; grant "
                                        "station roles INSERT and SELECT only")
    init.add_argument("--admin-service", metavar="NAME", help="the administrator's pg_service.conf service")
    init.add_argument("--db", metavar="ADMIN_URL", help="the database as the administrator (no password in it)")
    init.add_argument("--grant", action="append", metavar="ROLE", help="a station's role (repeatable)")
    init.set_defaults(func=cmd_db_init)

    station = qsub.add_parser("station", help="a station's commissioning and its operators' PINs")
    ssub = station.add_subparsers(dest="station_command", required=True)
    check = ssub.add_parser("check", help="check database, addresses, calibration and spec; production runs wait "
                                          "for a pass")
    check.add_argument("--out", required=True, metavar="STATION_DIR", help="the station's folder")
    check.add_argument("--db", help="records database URL (default: the station's)")
    check.add_argument("--shaker", help="default: station.toml's shaker")
    check.add_argument("--daq", help="default: station.toml's daq")
    check.add_argument("--calibration", help="default: station.toml's calibration, else the datasheet's")
    check.add_argument("--spec", default="default", help="the spec the station tests with")
    check.set_defaults(func=cmd_station_check)
    pin = ssub.add_parser("pin", help="the hash of an operator's PIN, for station.toml (the PIN is read, not typed "
                                      "on the command line)")
    pin.set_defaults(func=cmd_station_pin)

    sync = qsub.add_parser("sync", help="send a station's queued records to the database")
    sync.add_argument("--out", required=True, metavar="STATION_DIR", help="the station's folder (qc run's --out)")
    sync.add_argument("--db", help="records database URL (default: the station's station.toml, else "
                                   "STATION_DIR/qc-records.sqlite)")
    sync.add_argument("--send-to-current", action="store_true",
                      help="send records queued for another database to this one without asking")
    sync.set_defaults(func=cmd_sync)
