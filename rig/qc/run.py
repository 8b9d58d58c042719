"""``qc run`` and ``qc judge``: a QC run is a rig session (rig.session.run: the same checks before
anything moves, the same safe stop whatever ends it) followed by identification and
judging; a re-judgement is the second half alone, on stored data.

Exit status: 0 PASS, 1 FAIL, 4 INCONCLUSIVE (retest with more periods), 2 bad input
(nothing moved, nothing written), 3 aborted after the safe stop (status ABORTED, no
verdict), 130 interrupted after the safe stop (ABORTED too), 70 an internal error after
the safe stop (status ERROR, no verdict; traceback shown).

The verdict is written once, at the end: first into the station's journal (rig.qc.queue),
then in one transaction into the database; a database that does not answer leaves it
queued, and the run still ends with its verdict and exit status.  A run killed on the way
leaves no verdict behind, and the station's next start records it as ABORTED.  The
database is opened before the rig moves, so a bad URL or a wrong password costs no rig time.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import math
import shlex
import shutil
import socket
import tempfile
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich.console import Console

from identify.exit_codes import EXIT_INTERRUPTED, EXIT_OK
from identify.files import atomic_write_bytes
from rig.drivers.daq import probe_daq
from rig.drivers.shaker import MotionInterlock
from rig.errors import BadInput
from rig.events import Kind, Subscriber
from rig.planning.prediction import NOT_MEASURED, predict_s
from rig.qc import DEFAULT_SPEC
from rig.qc.calibration import CertificateError, derived_u_cal, is_certificate_file, load_certificates
from rig.qc.characteristics import check_model
from rig.qc.commissioning import configuration, require_commissioned
from rig.qc.evaluate import FIT_ITERATIONS, STUDY_FIT_ITERATIONS, Evaluation, evaluate
from rig.qc.judge import Judgement, Outcome
from rig.qc.present import shown
from rig.qc.queue import Outbox
from rig.qc.records import CharacteristicRecord, QcRecord, Records, RecordStatus, default_url
from rig.qc.report import render_report
from rig.qc.spec import SPECS_DIR, Spec, load_spec
from rig.qc.station import identify_operator, load_station_config, read_pin
from rig.qc.studies import StudyInputError, gate
from rig.qc.trace import SessionTrace, measuring_equipment, now_utc, software_version, trace_session
from rig.session.acquisition import ExperimentRecord
from rig.session.run import (
    Prepared,
    RunOptions,
    RunResult,
    SessionContext,
    SessionRunner,
    prepare,
    run_lifecycle,
    terminal_progress,
)
from rig.session.storage import Session

STATION_CALIBRATION = "calibration.toml"   # a station folder's certificates, when --calibration names none
EXIT_BY_VERDICT = {Outcome.PASS: 0, Outcome.FAIL: 1, Outcome.INCONCLUSIVE: 4}


@dataclass
class QcOptions:
    spec: str
    serial: str
    shaker: str | None              # None: the station's (station.toml)
    daq: str | None
    out: Path                       # the station's folder: one session folder per unit, and the default database
    db: str | None = None
    operator: str | None = None
    rig_id: str | None = None
    periods: int | None = None      # the remedy for INCONCLUSIVE: more periods than the spec's
    reset_alarm: bool = False
    rig_config: str | None = None
    calibration: str | None = None  # default: the station's OUT/calibration.toml where there is one
    register_map: str | None = None
    pin: str | None = None          # a PIN station's operator PIN (None: asked on the terminal)
    study: str | None = None        # a run of a measurement-system study or master check: not gated by the check


@dataclass
class QcSubscribers:
    """Who hears of one unit's test, and how: the command line's terminal
    (:func:`terminal`) or the console's window (rig.gui.session_worker).  Everything
    else (the checks, the session, the judgement, the record, the report, the exit
    status) is :func:`test_unit`'s, the same for both."""

    say: Callable[[str], None]                                  # a sentence for people (markup allowed)
    attach: Callable[[SessionContext], Sequence[Subscriber]]    # the session's progress, once its time is predicted
    subscribers: Sequence[Subscriber] = ()                      # every session event from the first
    on_runner: Callable[[SessionRunner | None], object] | None = None
    interlock: MotionInterlock | None = None                    # an E-STOP's latch, into the session's connect()
    before_session: Callable[[Prepared], object] | None = None  # checked, records open, nothing sent yet
    predicted: Callable[[Prediction], None] | None = None       # the time left, predicted again after an experiment
    after_session: Callable[[RunResult], object] | None = None  # the session over, its links closed; judging next
    concluded: Callable[[QcRecord, float, Path, str], None] | None = None   # a verdict: record, k, report, database
    ask_pin: Callable[[], str] | None = None                    # a PIN station's: how its operator enters the PIN


@dataclass(frozen=True)
class Prediction:
    """After a captured experiment: what is not decided yet and the rig time the rest of
    the plan takes, predicted from the parameters identified so far."""

    after: tuple[str, ...]          # the experiments captured
    undecided: tuple[str, ...]      # the characteristics still INCONCLUSIVE
    rig_left_s: float

    def sentence(self) -> str:
        return (f"after {', '.join(self.after)}: {', '.join(self.undecided)} not yet decided; the rest of the plan, "
                f"predicted from the parameters identified so far: {self.rig_left_s:.0f} s")


@dataclass(frozen=True)
class QcOutcome:
    """How one unit's test ended: its exit status (:data:`EXIT_BY_VERDICT`, or the
    session's), the record stored (judged or not) and where its report is."""

    exit_code: int
    record: QcRecord
    report: Path
    k: float
    database: str


def terminal(console: Console) -> QcSubscribers:
    """``rig qc run``'s subscribers: the session's lines and the summary in the terminal."""
    # the re-prediction is said by the session's terminal progress (a prediction event, with the time left)
    return QcSubscribers(say=lambda text: console.print(text, highlight=False), attach=terminal_progress(console),
                         concluded=lambda record, k, report, database: _print_summary(record, k, report, database),
                         ask_pin=read_pin)


def qc_run(opt: QcOptions, console: Console) -> int:
    """``rig qc run``: :func:`test_unit` with the terminal as its subscriber."""
    return test_unit(opt, terminal(console)).exit_code


def test_unit(opt: QcOptions, to: QcSubscribers) -> QcOutcome:
    """One unit's test, the one way ``rig qc run`` and the console run it: the spec's
    checks, the records opened, the session (:func:`rig.session.run.run_lifecycle`),
    the judgement, the record, the report.  A failure before the session folder exists
    is raised with nothing recorded; after it, it is recorded (ABORTED, ERROR) and then
    raised; a session that ended without its data (aborted, interrupted) is recorded
    ABORTED and returned with the session's exit status."""
    spec = load_spec(opt.spec)
    spec.check_serial(opt.serial)
    check_model(spec)
    station = load_station_config(opt.out)
    opt = replace(opt, shaker=opt.shaker or station.shaker, daq=opt.daq or station.daq,
                  calibration=opt.calibration or station.calibration)
    if not opt.shaker or not opt.daq:
        raise BadInput("--shaker and --daq are needed (or shaker and daq in the station's station.toml)")
    calibration = station_calibration(opt)
    opt = replace(opt, calibration=calibration)
    if station.is_station:   # a production station: commissioned for exactly this configuration
        require_commissioned(opt.out, configuration(opt.out, station, opt.db, opt.shaker, opt.daq, opt.calibration,
                                                    spec.sha256))
    equipment = admit(opt, calibration)
    derived = derived_u_cal(Path(opt.out), spec, calibration)
    if derived is not None:   # GUM type B from the certificates (qc uncertainty), in place of the spec's figures
        u_cal, derived_on = derived
        spec = replace(spec, characteristics=tuple(replace(c, u_cal=u_cal.get(c.name, c.u_cal))
                                                   for c in spec.characteristics))
    pin = opt.pin
    if station.identify == "pin" and station.is_station and pin is None and opt.operator is None:
        if to.ask_pin is None:   # never a prompt on a terminal nobody watches while a window waits
            raise BadInput(f"{station.path}: the station identifies its operator by PIN, which this front end "
                           "does not ask for; run python -m rig qc run in a terminal")
        pin = to.ask_pin()
    who = identify_operator(station, opt.operator, pin)
    operator, rig_id = who.operator, opt.rig_id or socket.gethostname()
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    run_options = RunOptions(plan=spec.source, shaker=opt.shaker, daq=opt.daq,
                             out=Path(opt.out) / f"{opt.serial}-{stamp}", periods=opt.periods,
                             reset_alarm=opt.reset_alarm, rig_config=opt.rig_config, calibration=opt.calibration,
                             register_map=opt.register_map, unit_serial=opt.serial)
    prep = prepare(run_options)
    config = replace(prep.config, steady_state=spec.steady_state)
    prep = replace(prep, config=config).ordered()   # the order the spec's criterion favours
    # Opened before the rig moves (a bad URL or password costs no rig time; runs a killed
    # process left are recorded, queued records sent); a new SQLite file is made only with
    # the first record: a run that never starts leaves none.
    records = Outbox.open(opt.out, opt.db, to.say)
    try:
        to.say(f"QC {spec.name} {spec.version} on unit {opt.serial}: records in {records.name}")
        if to.before_session is not None:
            to.before_session(prep)
        started = now_utc()
        identity: dict[str, Any] = dict(serial=opt.serial, operator=operator, rig=rig_id, started=started,
                                        station=records.station or rig_id, identified_by=who.by)
        records.begin(run_options.out, spec, identity)   # in the station's journal until it ends
        running: list[SessionRunner] = []   # the session's runner: its links' timing and its bus
        decide = decider(spec, prep, to.predicted, lambda: running[0] if running else None)

        def hand_over(runner: SessionRunner | None) -> None:
            if runner is not None:
                runner.decide = decide
                runner.acquisition.judge_partial = partial_judge(spec, run_options.out)
                running[:] = [runner]
            if to.on_runner is not None:
                to.on_runner(runner)

        try:
            result = run_lifecycle(prep, Console(file=io.StringIO()), subscribers=to.subscribers, attach=to.attach,
                                   on_runner=hand_over, interlock=to.interlock)
        except BaseException as exc:
            # A session that started (its folder exists) is on record as ABORTED; one that
            # never started (no link, refused) has nothing to record.
            if (run_options.out / "session.json").is_file():
                reason = "interrupted by the operator" if isinstance(exc, KeyboardInterrupt) else str(exc)
                _store(records, _unjudged(spec, run_options.out, RecordStatus.ABORTED, reason, finished=now_utc(),
                                          **identity), spec)
            raise
        finished = now_utc()
        session = result.session.path
        if to.after_session is not None:
            to.after_session(result)
        if result.error is not None:
            _store(records, _unjudged(spec, session, RecordStatus.ERROR, f"internal error: {result.error!r}",
                                      result.to_json(), finished=finished, **identity), spec)
            raise result.error
        if result.exit_code != EXIT_OK:
            record = _store(records, _unjudged(spec, session, RecordStatus.ABORTED, f"session {result.status}",
                                               result.to_json(), finished=finished, **identity), spec)
            to.say(f"[red]QC run ABORTED: session {result.status}; no verdict[/red]")
            return QcOutcome(result.exit_code, record, session / "qc-report.html", spec.k, records.name)
        try:
            evaluation = evaluate(spec, session, STUDY_FIT_ITERATIONS if opt.study else FIT_ITERATIONS)
        except BaseException as exc:
            status = RecordStatus.ABORTED if isinstance(exc, KeyboardInterrupt) else RecordStatus.ERROR
            record = _store(records, _unjudged(spec, session, status, f"judging ended: {exc!r}", finished=finished,
                                               **identity), spec)
            if isinstance(exc, KeyboardInterrupt):
                return QcOutcome(EXIT_INTERRUPTED, record, session / "qc-report.html", spec.k, records.name)
            raise
        retest = shlex.join(["python", "-m", "rig", "qc", "run", "--spec", opt.spec, "--serial", opt.serial,
                             "--shaker", str(opt.shaker), "--daq", str(opt.daq), "--out", str(opt.out),
                             "--periods", str(spec.retest_periods())])
        evaluation.notes.append(stopping_note(result, prep))
        record = judged_record(spec, trace_session(session), evaluation, retest, rejudges=None, finished=finished,
                               **identity)
        if equipment or opt.study:
            record = replace(record, details={
                **record.details, **({"equipment": equipment} if equipment else {}),
                **({"study": opt.study} if opt.study else {}),
                **({"u_cal": {"from": "calibration certificates", "derived on": derived_on}} if derived else {})})
        report = session / "qc-report.html"
        code = _conclude(records, record, spec, evaluation, report, session / "qc-record.json", to.concluded)
        return QcOutcome(code, record, report, spec.k, records.name)
    finally:
        records.close()


def station_calibration(opt: QcOptions) -> str | None:
    """``--calibration``, else the station folder's ``calibration.toml`` where there is one."""
    if opt.calibration:
        return opt.calibration
    own = Path(opt.out) / STATION_CALIBRATION
    return str(own) if own.is_file() else None


def admit(opt: QcOptions, calibration: str | None) -> list[dict[str, str]]:
    """Before anything moves or is recorded: the certificates in force and for the DAQ
    that answers, and (for a production unit) today's master check passed; refused in
    one line (exit 2) otherwise.  The certificates' data, for the record."""
    if calibration is None or not is_certificate_file(calibration):
        return []
    certificates = load_certificates(calibration)
    why = certificates.refusal(_dt.date.today(), None)
    if why is None and opt.daq is not None:   # test_unit has refused a run without a DAQ before this
        why = certificates.refusal(_dt.date.today(), probe_daq(opt.daq))
    if why is not None:
        raise CertificateError(f"qc run refused: {why}")
    if opt.study is None:
        state = gate(Path(opt.out), calibration)
        if not state.allowed:
            raise StudyInputError(f"qc run refused: {state.sentence}")
    return certificates.equipment()


def decider(spec: Spec, prep: Prepared, predicted: Callable[[Prediction], None] | None,
            runner: Callable[[], SessionRunner | None] = lambda: None) -> Callable[[RunResult], str | None]:
    """After each captured experiment but the last: fit and judge what there is, and end
    the session as soon as every characteristic is decided under the guard band (PASS,
    or FAIL at k·σ); otherwise predict the rest of the plan again from the parameters
    identified so far (a faulty unit heats and settles otherwise than the nominal one
    the first estimate assumed), at the links' measured timing, and publish it
    (``prediction``: every progress display takes it over)."""
    def decide(result: RunResult) -> str | None:
        evaluation = evaluate(spec, result.session.path, diagnose=not spec.model_free)
        labels = ", ".join(e.label for e in result.captured)
        open_ = [j.name for j in evaluation.judgement.characteristics if j.outcome is Outcome.INCONCLUSIVE]
        if not open_:
            return f"every characteristic decided after {labels} ({evaluation.judgement.verdict.value})"
        done = {e.label for e in result.captured}
        rest = tuple(e for e in prep.plan.experiments if result.session.label(e.letter) not in done)
        if evaluation.fit is not None and evaluation.fit.converged and rest:
            last = prep.plan.experiments[len(prep.plan.experiments) - len(rest) - 1]
            session = runner()
            left = predict_s(replace(prep.plan, experiments=rest), prep.config,
                             session.timing() if session is not None else NOT_MEASURED,
                             last.static_position_mm * 1e-3, evaluation.fit.params)
            basis = f"the parameters identified from {labels}"
            if session is not None:   # on the bus: session.log, the terminal's and the bar's time left
                session.bus.publish(Kind.PREDICTION, rig_time_left_s=round(left, 1), basis=basis,
                                    message=f"{', '.join(open_)} not yet decided after {labels}: the rest of the "
                                            f"plan ({len(rest)} experiment{'s' if len(rest) != 1 else ''}) "
                                            f"predicted again from {basis}: {left:.0f} s of rig time")
            if predicted is not None:
                predicted(Prediction(tuple(e.label for e in result.captured), tuple(open_), left))
        return None

    return decide


def partial_judge(spec: Spec, session_dir: Path) -> Callable[[ExperimentRecord], str | None]:
    """Within a transient capture: the record so far fitted and judged beside the
    session's experiments already written (in a scratch folder: the session holds only
    what was captured whole); a reason when every characteristic is decided under the
    guard band, which ends the capture (the verdict is then made again on all of it)."""
    def judge(record: ExperimentRecord) -> str | None:
        with tempfile.TemporaryDirectory() as tmp:
            scratch = Path(tmp)
            manifest = json.loads((session_dir / "dataset.json").read_text())
            manifest["experiments"] = [e for e in manifest["experiments"] if e["label"] != record.label]
            for entry in manifest["experiments"]:
                shutil.copyfile(session_dir / entry["file"], scratch / entry["file"])
            Session(scratch, {}, manifest).write_experiment(record)
            evaluation = evaluate(spec, scratch, diagnose=not spec.model_free)
        if any(j.outcome is Outcome.INCONCLUSIVE for j in evaluation.judgement.characteristics):
            return None
        return f"every characteristic decided ({evaluation.judgement.verdict.value})"

    return judge


def stopping_note(result: RunResult, prep: Prepared) -> str:
    """The record's line on how much of the plan was run, and why it ended there."""
    used = [e.label for e in result.captured]
    return (f"experiments used: {', '.join(used)} ({len(used)} of {len(prep.plan.experiments)}); "
            f"stopped: {result.decided or 'end of the plan'}")


def qc_judge(session_dir: Path, spec_source: str | None, db: str | None, operator: str | None,
             create_db: bool = False, reason: str | None = None, out: Path | None = None,
             pin: str | None = None) -> int:
    """Judge stored data again (a new spec, a new model): a new record that refers to the
    first, in an existing database (``create_db``: a new one where none is).  The station
    is ``out``'s, else the session folder's own (a session lies in its station's folder):
    its station.toml names the database and its password and identifies who re-judges;
    ``reason``: why, on record.  No spec given: the one the data's first record was judged
    with where it is a shipped one, else :data:`rig.qc.DEFAULT_SPEC`."""
    if spec_source is not None:
        check_model(load_spec(spec_source))
    session = Path(session_dir).resolve()
    if not (session / "dataset.json").is_file():
        raise BadInput(f"{session_dir}: not a session or dataset folder (no dataset.json)")
    folder = Path(out) if out is not None else session.parent
    station = load_station_config(folder)
    who = identify_operator(station, operator, pin)
    records = Records.open(db or station.db or default_url(folder), create=create_db, password=station.password,
                           writer=True)
    try:
        trace = trace_session(session)
        first = records.first_for_data(trace.data_sha256)
        if spec_source is None:
            shipped = first is not None and (SPECS_DIR / f"{first.spec_name}.toml").is_file()
            spec_source = first.spec_name if shipped and first is not None else DEFAULT_SPEC
        spec = load_spec(spec_source)
        check_model(spec)
        manifest = json.loads((session / "dataset.json").read_text())
        serial = first.serial if first else str(manifest.get("unit", {}).get("serial", "unknown"))
        rig = first.rig if first else str(manifest.get("source", {}).get("generator", "unknown"))
        evaluation = evaluate(spec, session)
        if first is not None:   # said in the record itself, not only in its link to the first
            evaluation.notes.insert(0, rejudgement_note(first))
        retest = rejudge_remedy(spec)
        # The measurement is the first record's: its times, not the session files' (which
        # said 14:19:09 where the first record said 14:19:08 for the same measurement).
        # Who judged is who judges now (the first record keeps its own operator); the
        # station is the first record's (its chain), or the one judging data never recorded.
        record = judged_record(spec, trace, evaluation, retest, rejudges=first.uid if first else None,
                               simulated=bool(first and first.simulated), serial=serial,
                               operator=who.operator, identified_by=who.by, rig=rig,
                               started=first.started if first else trace.started,
                               finished=first.finished if first else trace.finished,
                               station=first.station if first else station.name,
                               rejudge_reason=reason if first else None)
        tag = f"{record.judged.replace(':', '').replace('-', '')[:15]}-{record.uid[:8]}"
        return _conclude(records, record, spec, evaluation, session / f"qc-report-{tag}.html",
                         session / f"qc-record-{tag}.json", _print_summary)
    finally:
        records.close()


def rejudgement_note(first: QcRecord) -> str:
    """What a re-judgement's record and report say of the record it judges again."""
    return (f"re-judgement of record {first.uid} (spec {first.spec_name} {first.spec_version}, verdict "
            f"{first.verdict or first.status}, judged {first.judged}): the same measurement judged again; that "
            "record and its report are kept unchanged")


def _conclude(records: Records | Outbox, record: QcRecord, spec: Spec, evaluation: Evaluation, report: Path,
              record_file: Path, concluded: Callable[[QcRecord, float, Path, str], None] | None) -> int:
    """The report rendered first (a failure there costs no record), then the record
    stored, then the files: a killed process leaves a verdict in the database or nowhere."""
    html = render_report(record, spec, evaluation)
    record = replace(record, report_sha256=hashlib.sha256(html.encode()).hexdigest())
    records.add(record)
    atomic_write_bytes(report, html.encode())
    atomic_write_bytes(record_file, (json.dumps(_document(record), indent=2) + "\n").encode())
    if concluded is not None:
        concluded(record, spec.k, report, records.name)
    assert record.verdict is not None  # a judged record
    return EXIT_BY_VERDICT[record.verdict]


def _document(record: QcRecord) -> dict:
    doc = record.to_json()
    doc.update(software=record.software, files=record.files, calibration_sha256=record.calibration_sha256,
               register_map_sha256=record.register_map_sha256, diagnosis=list(record.diagnosis),
               remedy=record.remedy, notes=list(record.notes))
    return doc


def _store(records: Records | Outbox, record: QcRecord, spec: Spec) -> QcRecord:
    """A run without a verdict: on record all the same, with a report that says why."""
    html = render_report(record, spec, None)
    record = replace(record, report_sha256=hashlib.sha256(html.encode()).hexdigest())
    records.add(record)
    atomic_write_bytes(Path(record.session) / "qc-report.html", html.encode())
    atomic_write_bytes(Path(record.session) / "qc-record.json",
                       (json.dumps(_document(record), indent=2) + "\n").encode())
    return record


def rejudge_remedy(spec: Spec) -> str:
    """The remedy of an INCONCLUSIVE re-judgement (no rig at hand to name in a command)."""
    return f"retest the unit with more periods (qc run … --periods {spec.retest_periods()})"


def _base(spec: Spec, trace: SessionTrace, uid: str | None = None, *, simulated: bool = False,
          **identity: Any) -> dict:
    """What every record says: who, when, with what, on what.  ``simulated``: the record
    this one re-judges was (a flag that no later record can drop)."""
    peers = trace.peers[0] if trace.peers else {}
    details: dict[str, Any] = {"connections": list(trace.peers)} if len(trace.peers) > 1 else {}
    if trace.generated:
        details["generated"] = "the data were generated by the simulator, not measured"
    if spec.release_required:
        details["release"] = "required"     # the spec's: a second person's qc release before the unit ships
    return dict(uid=uid or str(uuid.uuid4()), judged=now_utc(), software=software_version(), spec_name=spec.name,
                spec_version=spec.version, spec_sha256=spec.sha256, calibration_sha256=trace.calibration_sha256,
                register_map_sha256=trace.register_map_sha256, session=trace.path, data_sha256=trace.data_sha256,
                files=trace.files, simulated=simulated or trace.simulated, controller=peers.get("controller"),
                daq=peers.get("daq"), k=spec.k, details=details, equipment=measuring_equipment(trace),
                flagged=trace.flagged, **identity)


def _unjudged(spec: Spec, session: Path, status: RecordStatus, reason: str, outcome: dict[str, Any] | None = None,
              **identity: Any) -> QcRecord:
    """A run without a verdict (ABORTED, ERROR): status, reason, no characteristics;
    ``outcome``: how the session ended, as data (``RunResult.to_json``), kept in the details."""
    base = _base(spec, trace_session(session), **identity)
    if outcome is not None:
        base["details"] = {**base["details"], "session_outcome": outcome}
    return QcRecord(**base, verdict=None, status=status, characteristics=(), reason=reason, notes=(reason,))


def judged_record(spec: Spec, trace: SessionTrace, evaluation: Evaluation, retest: str, rejudges: str | None,
                  uid: str | None = None, *, simulated: bool = False, **identity: Any) -> QcRecord:
    """The record of a verdict (``uid``: a new random one unless the caller keys it)."""
    j = evaluation.judgement
    titles = {c.name: c.title for c in spec.characteristics}
    characteristics = tuple(
        CharacteristicRecord(c.name, c.measured.unit, c.measured.value, c.measured.std, c.measured.std_fit,
                             c.measured.u_cal, c.low, c.high, c.nominal, c.outcome, titles.get(c.name) or None,
                             "predicted" if c.measured.predicted else c.measured.basis)
        for c in j.characteristics)
    base = _base(spec, trace, uid, simulated=simulated, **identity)
    base["details"] = {**base["details"], **measurement_details(spec, evaluation)}
    return QcRecord(**base, verdict=j.verdict,
                    status=RecordStatus.COMPLETE, characteristics=characteristics, diagnosis=tuple(j.diagnosis),
                    remedy=remedy(j, retest) if j.verdict is Outcome.INCONCLUSIVE else None,
                    notes=tuple(evaluation.notes), rejudges=rejudges)


def measurement_details(spec: Spec, evaluation: Evaluation) -> dict[str, Any]:
    """What a record holds beyond its columns (``details``): the spec's basis, and per
    characteristic how it was obtained (measured or predicted), its definition, and a
    measurand's uncertainty budget row by row (in its unit) with the cycles it covers."""
    out: dict[str, Any] = {}
    for m, c in zip(evaluation.measured, spec.characteristics, strict=True):
        entry: dict[str, Any] = {"obtained": "predicted" if m.predicted else "measured",
                                 "definition": m.definition or c.description}
        if m.budget:
            entry.update(budget=list(m.budget), cycles=m.cycles)
        if m.predicted:
            entry["model_discrepancy_relative"] = c.discrepancy
        out[c.name] = entry
    return {"spec_basis": spec.basis, "characteristics": out} if spec.basis or any(
        c.measurand or c.predicted for c in spec.characteristics) else {}


def remedy(judgement: Judgement, retest: str) -> str:
    """The remedy of an INCONCLUSIVE verdict, true to its cause: more periods narrow only
    the repeatability (type A, as 1/√n), so a retest with more periods is named only
    where twice the periods would take every undecided characteristic's value ± k·u off
    its limit; otherwise the unit is on a limit within what the rig can tell (its
    calibration, the folding), and only a better measurement decides it."""
    k = judgement.k
    open_ = [c for c in judgement.characteristics if c.outcome is Outcome.INCONCLUSIVE and not c.measured.predicted]
    hopeless = []
    for c in open_:
        m = c.measured
        if m.value is None or m.std is None or not m.budget:
            continue        # not measured, or a model's σ (a fit on more periods may narrow it): retest
        u_a = m.std_fit or 0.0
        u_twice = math.sqrt(max(m.std**2 - u_a**2 / 2, 0.0))
        distance = min(abs(m.value - x) for x in (c.low, c.high) if x is not None)
        if k * u_twice >= distance:
            hopeless.append(c.title or c.name)
    if open_ and len(hopeless) == len(open_):
        return (f"{', '.join(hopeless)}: on a limit within the rig's uncertainty (more periods would not narrow "
                "U enough: it is held by the calibration and the folding, see the budget); decide with a "
                "better-calibrated rig or treat the unit as not conforming")
    return retest


def _print_summary(record: QcRecord, k: float, report: Path, database: str) -> None:
    """The terminal summary: one line per characteristic, fields separated by ' | ' (the
    console's QC panel shows the same cells from the record, rig.qc.present.shown)."""
    simulated = "  SIMULATED (not a production record)" if record.simulated else ""
    again = f"  RE-JUDGEMENT of record {record.rejudges}" if record.rejudges else ""
    print(f"{record.serial}: {record.verdict}  (spec {record.spec_name} {record.spec_version}; "
          f"value ± {k:g}σ){simulated}{again}")
    rows = [shown(record, c, k) for c in record.characteristics]
    width = max((len(s.title) for s in rows), default=0)
    for s in rows:
        print(f"  {s.outcome:<12} | {s.title:<{width}} | {s.value} | limits {s.limits} | accept {s.acceptance} | "
              f"σ {s.sigma} {s.basis}".rstrip())
    for line in record.diagnosis:
        print(f"  likely cause: {line}")
    if record.remedy:
        print(f"  remedy: {record.remedy}")
    print(f"report {report}; record {record.uid} in {database}")
    if record.details.get("release") == "required" and record.verdict is not None:
        print(f"release required by the spec: a second person runs python -m rig qc release {record.serial} "
              f"--out {report.parent.parent}")     # the report lies in the session folder, in the station's
