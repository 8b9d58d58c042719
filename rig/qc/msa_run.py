"""``qc msa type1|type3`` and ``qc check``: the master unit or a set of units tested on the
rig the way ``qc run`` tests a unit (:func:`rig.qc.run.test_unit`: the same checks, session,
identification and record per run, each run's record marked with its study), then the
study's figures (rig.qc.msa, rig.qc.studies), a study record, a report and charts.

Exit status: 0 the study met its goals (the check passed), 1 it did not (the check
FAILED: the line names the characteristics that drifted), 2 bad input or a refusal
(nothing moved), 3 a run ended without a verdict (the study is not made).
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import shlex
import subprocess
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 — after the backend is chosen

from rig.errors import BadInput, RigFault  # noqa: E402
from rig.qc import msa  # noqa: E402
from rig.qc.calibration import equipment  # noqa: E402
from rig.qc.records import QcRecord  # noqa: E402
from rig.qc.run import QcOptions, QcSubscribers, station_calibration, test_unit  # noqa: E402
from rig.qc.spec import Spec, load_spec  # noqa: E402
from rig.qc.studies import (  # noqa: E402
    STUDIES_DIR,
    StudyInputError,
    StudyRecord,
    gate,
    load_reference,
    master_check,
    master_check_policy,
    new_uid,
    store,
    tolerance,
)

EXIT_GOALS_MET, EXIT_GOALS_MISSED, EXIT_RUN_WITHOUT_VERDICT = 0, 1, 3

Say = Callable[[str], None]


class RunWithoutVerdict(RigFault):
    """A study's run ended without values: the study cannot be made from it."""


def _quiet() -> QcSubscribers:
    return QcSubscribers(say=lambda text: None, attach=lambda ctx: ())


def measure(opt: QcOptions, serial: str, kind: str, say: Say) -> QcRecord:
    """One run of a study: ``qc run``'s test of ``serial``, its record marked with the study."""
    outcome = test_unit(replace(opt, serial=serial, study=kind), _quiet())
    record = outcome.record
    if any(c.value is None for c in record.characteristics) or not record.characteristics:
        raise RunWithoutVerdict(f"the run of {serial} ended without values ({record.status}"
                                f"{': ' + record.reason if record.reason else ''}); record {record.uid}")
    return record


def rows(record: QcRecord, unit: str, repeat: int) -> list[msa.Row]:
    return [msa.Row(unit, repeat, c.name, float(c.value)) for c in record.characteristics if c.value is not None]


def _tolerances(spec: Spec) -> dict[str, float]:
    return {c.name: tolerance(c) for c in spec.characteristics}


def _base(kind: str, spec: Spec, opt: QcOptions, units: tuple[str, ...], passed: bool, result: dict,
          records: list[QcRecord], summary: str) -> StudyRecord:
    return StudyRecord(new_uid(), kind, _dt.datetime.now(_dt.UTC).isoformat(timespec="microseconds"), opt.rig_id,
                       spec.name, spec.version, spec.sha256, opt.calibration, units, passed, result,
                       tuple(r.uid for r in records), any(r.simulated for r in records),
                       tuple(equipment(opt.calibration)), summary)


def keep(opt: QcOptions, study: StudyRecord, say: Say) -> Path:
    """The station's own copy first, then the records database (where it answers: the
    station's copy stands for it otherwise, and ``qc history --out`` lists both)."""
    from rig.qc.records import Records, RecordsError, default_url
    from rig.qc.station import load_station_config

    path = store(opt.out, study)
    config = load_station_config(Path(opt.out))
    url = opt.db or config.db or default_url(Path(opt.out))
    try:
        records = Records.open(url, create=True, password=config.password)
        try:
            records.add_study(study.uid, study.kind, study.at, study.station, (study.spec_name, study.spec_version,
                              study.spec_sha256), study.passed, study.simulated, list(study.units), study.summary,
                              study.to_json())
        finally:
            records.close()
    except RecordsError as exc:
        say(f"study not in the records database ({exc}); the station's copy: {path}")
    return path


def _prepare(opt: QcOptions) -> tuple[QcOptions, Spec]:
    spec = load_spec(opt.spec)
    opt = replace(opt, calibration=station_calibration(opt))
    return opt, spec


# ----- the daily master check --------------------------------------------------------------------
def run_check(opt: QcOptions, master: str, reference_file: str, say: Say) -> int:
    opt, spec = _prepare(opt)
    reference = load_reference(reference_file, spec)
    _same_master(reference.master, master, reference_file)
    policy = master_check_policy(opt.calibration)
    if policy is None:
        raise StudyInputError(f"qc check: the calibration {opt.calibration or '(datasheet)'} sets no [master_check] "
                              "(fraction of the tolerance): give the station's certificate file")
    spec.check_serial(master)
    # A judged run without values (the identification did not converge: a drifted
    # transducer can make the channels disagree with any model) fails the check; a
    # session that ended without data (no record of characteristics) says nothing of drift.
    record = test_unit(replace(opt, serial=master, study="check"), _quiet()).record
    if not record.characteristics:
        raise RunWithoutVerdict(f"the master check's run ended without data ({record.status}"
                                f"{': ' + record.reason if record.reason else ''}); record {record.uid}")
    drifts = master_check(spec, reference, {c.name: c.value for c in record.characteristics}, policy)
    failed = [d for d in drifts if not d.passed]
    unmeasured = [d.title for d in failed if d.deviation is None]
    why = next((n for n in record.notes if n.startswith("identification")), "no value")
    summary = ("every characteristic within its limit" if not failed else
               "; ".join(filter(None, [
                   "drifted: " + ", ".join(f"{d.title} {d.deviation:+.4g} {d.unit} (limit ±{d.limit:.3g})"
                                           for d in failed if d.deviation is not None)
                   if len(unmeasured) < len(failed) else "",
                   f"not measured ({why}): {', '.join(unmeasured)}" if unmeasured else ""])))
    result = {d.characteristic: {"title": d.title, "unit": d.unit, "value": d.value, "reference": d.reference,
                                 "limit": d.limit, "passed": d.passed} for d in drifts}
    study = _base("check", spec, opt, (master,), not failed, result, [record], summary)
    path = keep(opt, study, say)
    say(f"master check of {master}: {'PASS' if not failed else 'FAIL'}: {summary} "
        f"(limits ±{policy.fraction:g}·T of the reference; {path})")
    for d in drifts:
        say(f"  {'ok   ' if d.passed else 'DRIFT'} {d.title}: {d.value:.6g} against {d.reference:.6g} {d.unit}, "
            f"limit ±{d.limit:.3g}" if d.value is not None else f"  DRIFT {d.title}: not measured")
    say(gate(Path(opt.out), opt.calibration).sentence)
    return EXIT_GOALS_MET if not failed else EXIT_GOALS_MISSED


def _same_master(expected: str, master: str, where: str) -> None:
    if expected != master:
        raise StudyInputError(f"--master {master}: the reference {where} is for master {expected}")


# ----- type 1 ------------------------------------------------------------------------------------
def run_type1(opt: QcOptions, master: str, reference_file: str, runs: int, say: Say) -> int:
    opt, spec = _prepare(opt)
    if runs < msa.MIN_TYPE1_RUNS:
        raise StudyInputError(f"--runs {runs}: a type 1 study needs at least {msa.MIN_TYPE1_RUNS} runs (VDA 5, "
                              "Bosch booklet 10)")
    reference = load_reference(reference_file, spec)
    _same_master(reference.master, master, reference_file)
    spec.check_serial(master)
    table: list[msa.Row] = []
    records = []
    for i in range(1, runs + 1):
        record = measure(opt, master, "type1", say)
        records.append(record)
        table += rows(record, master, i)
        say(f"type 1 run {i}/{runs}: " + ", ".join(f"{c.name} {c.value:.6g}" for c in record.characteristics))
    results = msa.type1(table, reference.values, _tolerances(spec))
    passed = all(r.capable for r in results)
    missed = [r.characteristic for r in results if not r.capable]
    summary = "every characteristic Cg, Cgk ≥ 1.33" if passed else "below 1.33: " + ", ".join(missed)
    study = _base("type1", spec, opt, (master,), passed, {"rows": [r.__dict__ for r in table],
                                                            "figures": [r.__dict__ for r in results]},
                  records, summary)
    charts = {r.characteristic: run_chart(spec, r, [x.value for x in table if x.characteristic == r.characteristic])
              for r in results}
    return _conclude_study(opt, study, type1_html(spec, study, results, charts), charts,
                           [type1_line(spec, r) for r in results], say)


def type1_line(spec: Spec, r: msa.Type1) -> str:
    c = next(x for x in spec.characteristics if x.name == r.characteristic)
    return (f"  {c.shown}: n {r.n}, Cg {r.cg:.2f}, Cgk {r.cgk:.2f} ({'≥' if r.capable else 'below'} 1.33); "
            f"bias {r.bias:+.4g} {c.unit} (t {r.t:.2f}, p {r.p:.3f}: "
            f"{'significant' if r.bias_significant else 'not significant'} at 5 %), s {r.s:.4g} {c.unit}, "
            f"T {r.tolerance:.4g} {c.unit}")


def run_chart(spec: Spec, r: msa.Type1, values: list[float]) -> bytes:
    """The run chart of a type 1 study: each run's value, the reference, ±0.1·T about it
    (the part of the tolerance Cgk allows the bias and 3s), the mean."""
    c = next(x for x in spec.characteristics if x.name == r.characteristic)
    fig, ax = plt.subplots(figsize=(8, 3.6), dpi=100)
    runs = range(1, len(values) + 1)
    ax.plot(runs, values, "o-", color="#1565c0", ms=4, lw=1, label="measured")
    ax.axhline(r.reference, color="#2e7d32", lw=1.5, label=f"reference {r.reference:.5g} {c.unit}")
    for sign in (-1, 1):
        ax.axhline(r.reference + sign * 0.1 * r.tolerance, color="#c62828", ls="--", lw=1,
                   label="reference ± 0.1·T" if sign > 0 else None)
    ax.axhline(r.mean, color="#6a1b9a", ls=":", lw=1.2, label=f"mean {r.mean:.5g} {c.unit}")
    ax.set_xlabel("run")
    ax.set_ylabel(f"{c.shown} [{c.unit}]")
    ax.set_title(f"{c.shown}: Cg {r.cg:.2f}, Cgk {r.cgk:.2f}, bias {r.bias:+.3g} {c.unit} (n {r.n})", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


# ----- type 3 ------------------------------------------------------------------------------------
def run_type3(opt: QcOptions, units: list[str], repeats: int, say: Say, mount: Callable[[str], None],
              seed: int | None = None) -> int:
    opt, spec = _prepare(opt)
    if len(units) < msa.MIN_TYPE3_UNITS or repeats < msa.MIN_TYPE3_REPEATS or len(set(units)) != len(units):
        raise StudyInputError(f"--units: {len(set(units))} different units × {repeats} repeats; a type 3 study needs "
                              f"at least {msa.MIN_TYPE3_UNITS} × {msa.MIN_TYPE3_REPEATS} (AIAG MSA)")
    for u in units:
        spec.check_serial(u)
    order = msa.randomised_order(units, repeats, seed)
    table: list[msa.Row] = []
    records = []
    for i, (unit, repeat) in enumerate(order, 1):
        mount(unit)
        record = measure(opt, unit, "type3", say)
        records.append(record)
        table += rows(record, unit, repeat)
        say(f"type 3 run {i}/{len(order)} ({unit}, repeat {repeat}): "
            + ", ".join(f"{c.name} {c.value:.6g}" for c in record.characteristics))
    results = msa.type3(table, _tolerances(spec))
    passed = all(r.acceptable for r in results)
    missed = [r.characteristic for r in results if not r.acceptable]
    summary = "every characteristic %GRR ≤ 10 % of T and ndc ≥ 5" if passed else "missed: " + ", ".join(missed)
    study = _base("type3", spec, opt, tuple(units), passed,
                  {"rows": [r.__dict__ for r in table], "order": order,
                   "figures": [{**r.__dict__, "anova": [a.__dict__ for a in r.anova]} for r in results]},
                  records, summary)
    return _conclude_study(opt, study, type3_html(spec, study, results), {}, [type3_line(spec, r) for r in results],
                           say)


def type3_line(spec: Spec, r: msa.Type3) -> str:
    c = next(x for x in spec.characteristics if x.name == r.characteristic)
    return (f"  {c.shown}: %GRR {r.grr_tolerance_percent:.1f} % of T, {r.grr_tv_percent:.1f} % of TV, "
            f"ndc {r.ndc:.1f}; EV {r.ev:.4g} {c.unit}, PV {r.pv:.4g} {c.unit} "
            f"({'acceptable' if r.acceptable else 'NOT acceptable'})")


def mount_by_command(command: str | None, say: Say) -> Callable[[str], None]:
    """Before each run of a type 3 study: ``COMMAND SERIAL`` (a unit changer, or a script
    that serves a simulated unit), else the operator's Enter once the unit is on the rig."""
    def mount(serial: str) -> None:
        if command:
            r = subprocess.run([*shlex.split(command), serial], capture_output=True, text=True)
            if r.returncode != 0:
                raise BadInput(f"--mount-command {command!r} {serial}: exit {r.returncode}: "
                               f"{(r.stderr or r.stdout).strip().splitlines()[-1:] or ''}")
        else:
            input(f"mount unit {serial} on the rig, then press Enter ")
    return mount


# ----- the report --------------------------------------------------------------------------------
def _img(png: bytes, alt: str) -> str:
    return f"<img alt='{html.escape(alt)}' src='data:image/png;base64,{base64.b64encode(png).decode()}'>"


def _page(title: str, study: StudyRecord, body: str) -> str:
    e = html.escape
    sim = ("<div class=simbanner>SIMULATED: measured on a simulator, not on hardware. Not a study of a production "
           "station.</div>") if study.simulated else ""
    eq = "".join(f"<tr><td>{e(q['channel'])}</td><td>{e(q['serial'])}</td><td>{e(q['certificate'])}</td>"
                 f"<td>{e(q['calibrated'])}</td><td>{e(q['due'])}</td></tr>" for q in study.equipment)
    equipment_html = (("<h2>Calibration certificates used</h2><table><tr><th>channel</th><th>serial</th>"
                       "<th>certificate</th><th>calibrated</th><th>due</th></tr>" + eq + "</table>") if eq else
                      "<p>No calibration certificates: the DAQ's datasheet calibration was used.</p>")
    colour = "#2e7d32" if study.passed else "#c62828"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{e(title)}{' (SIMULATED)' if study.simulated else ''}</title>
<style>
body {{ font-family: "DejaVu Sans", Arial, sans-serif; margin: 24px auto; max-width: 1000px; color: #222; }}
h1 {{ font-size: 22px; margin: 0 0 10px 0; }} h2 {{ font-size: 17px; margin: 22px 0 6px 0; }}
.verdict {{ font-size: 30px; font-weight: bold; color: #fff; background: {colour}; padding: 6px 18px;
           border-radius: 6px; display: inline-block; }}
table {{ border-collapse: collapse; width: 100%; font-size: 13px; margin-bottom: 8px; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 4px 8px; text-align: left; vertical-align: top; }}
td.num {{ text-align: right; white-space: nowrap; font-variant-numeric: tabular-nums; }}
table.fig th {{ text-align: right; }} table.fig th:first-child, table.fig th.text {{ text-align: left; }}
.miss {{ color: #c62828; font-weight: bold; }}
img {{ max-width: 100%; }}
.simbanner {{ background: #c62828; color: #fff; font-weight: bold; padding: 6px 12px; margin-bottom: 10px; }}
* {{ -webkit-print-color-adjust: exact; print-color-adjust: exact; }}
.small {{ font-size: 11px; color: #555; word-break: break-all; }}
</style></head><body>
{sim}
<h1>{e(title)}</h1>
<div class="verdict">{'GOALS MET' if study.passed else 'GOALS MISSED'}</div>
<p>{e(study.summary)}</p>
<p>Spec <b>{e(study.spec_name)} {e(study.spec_version)}</b>; finished {e(study.at)} UTC; station
{e(study.station or '—')}; {len(study.records)} runs.</p>
{body}
{equipment_html}
<h2>Traceability</h2>
<p class=small>study {e(study.uid)}; spec sha256 {e(study.spec_sha256)}; the runs' QC records:
{e(', '.join(study.records))}</p>
</body></html>
"""


def _num(x: float, fmt: str) -> str:
    return f"<td class=num>{format(x, fmt)}</td>"


def type1_html(spec: Spec, study: StudyRecord, results: list[msa.Type1], charts: dict[str, bytes]) -> str:
    rows_html = ""
    for r in results:
        c = next(x for x in spec.characteristics if x.name == r.characteristic)
        cg = "num" if r.cg >= msa.CAPABILITY_GOAL else "num miss"
        cgk = "num" if r.cgk >= msa.CAPABILITY_GOAL else "num miss"
        rows_html += (f"<tr><td>{html.escape(c.shown)}</td><td>{html.escape(c.unit)}</td>{_num(r.reference, '.5g')}"
                      f"{_num(r.tolerance, '.4g')}{_num(r.mean, '.5g')}{_num(r.s, '.3g')}<td class='{cg}'>"
                      f"{r.cg:.2f}</td><td class='{cgk}'>{r.cgk:.2f}</td>"
                      f"{_num(r.bias, '+.3g')}<td class=num>{r.t:.2f} / {r.p:.3f}</td>"
                      f"<td>{'significant' if r.bias_significant else 'not significant'}</td></tr>")
    body = (f"<p>Master {html.escape(study.units[0])} measured {results[0].n if results else 0} times. "
            "Cg = 0.2·T/(6s), Cgk = (0.1·T − |bias|)/(3s), goal ≥ 1.33 (VDA 5; Bosch booklet 10); the bias "
            "against the reference value with its one-sample t-test (AIAG MSA: significant at p &lt; 0.05).</p>"
            "<table class=fig><tr><th>characteristic</th><th class=text>unit</th><th>reference</th><th>T</th>"
            "<th>mean</th><th>s</th><th>Cg</th><th>Cgk</th><th>bias</th><th>t / p</th><th class=text>bias test</th>"
            "</tr>" + rows_html + "</table>"
            "<h2>Run charts</h2>" + "".join(_img(png, f"run chart {name}") for name, png in charts.items()))
    return _page(f"Type 1 study — master {study.units[0]}", study, body)


def type3_html(spec: Spec, study: StudyRecord, results: list[msa.Type3]) -> str:
    rows_html, anova_html = "", ""
    for r in results:
        c = next(x for x in spec.characteristics if x.name == r.characteristic)
        grr_miss = " miss" if r.grr_tolerance_percent > msa.GRR_GOAL_PERCENT else ""
        ndc_miss = " miss" if r.ndc < msa.NDC_GOAL else ""
        rows_html += (f"<tr><td>{html.escape(c.shown)}</td><td>{html.escape(c.unit)}</td>{_num(r.ev, '.3g')}"
                      f"{_num(r.pv, '.3g')}{_num(r.tv, '.3g')}{_num(r.tolerance, '.4g')}"
                      f"<td class='num{grr_miss}'>{r.grr_tolerance_percent:.1f} %</td>"
                      f"<td class=num>{r.grr_tv_percent:.1f} %</td><td class='num{ndc_miss}'>{r.ndc:.1f}</td></tr>")
        anova_html += (f"<h3>{html.escape(c.shown)} [{html.escape(c.unit)}]</h3>"
                       "<table class=fig style='width: 70%'><tr><th>source</th><th>df</th><th>SS</th><th>MS</th>"
                       "<th>F</th><th>p</th></tr>"
                       + "".join(f"<tr><td>{a.source}</td><td class=num>{a.df}</td>{_num(a.ss, '.4g')}"
                                 f"{_num(a.ms, '.4g')}<td class=num>{'' if a.f is None else f'{a.f:.2f}'}</td>"
                                 f"<td class=num>{'' if a.p is None else f'{a.p:.3g}'}</td></tr>" for a in r.anova)
                       + "</table>")
    n = results[0] if results else None
    body = (f"<p>{n.units if n else 0} units × {n.repeats if n else 0} repeats in a randomised order, no operator "
            "influence (AIAG MSA, ANOVA method; statsmodels). EV = √MS<sub>error</sub> (repeatability, = GRR), "
            "PV = √((MS<sub>unit</sub> − MS<sub>error</sub>)/r), TV = √(GRR² + PV²); %GRR of T = 100·6·GRR/T, "
            "ndc = 1.41·PV/GRR. Goals: %GRR ≤ 10 % of T, ndc ≥ 5.</p>"
            "<table class=fig><tr><th>characteristic</th><th class=text>unit</th><th>EV (GRR)</th><th>PV</th>"
            "<th>TV</th><th>T</th>"
            "<th>%GRR of T</th><th>%GRR of TV</th><th>ndc</th></tr>" + rows_html + "</table>"
            "<h2>ANOVA tables</h2>" + anova_html
            + "<p>Order of the runs: " + html.escape(", ".join(f"{u}#{k}" for u, k in study.result["order"])) + "</p>")
    return _page(f"Type 3 study — {len(study.units)} units", study, body)


STUDY_NAMES = {"type1": "type 1", "type3": "type 3"}


def _conclude_study(opt: QcOptions, study: StudyRecord, page: str, charts: dict[str, bytes], lines: list[str],
                    say: Say) -> int:
    """A type 1 or type 3 study kept as a record, its report written, its figures said."""
    path = keep(opt, study, say)
    report = _write_report(Path(opt.out), study, page, charts)
    for line in lines:
        say(line)
    say(f"{STUDY_NAMES[study.kind]} study {'met its goals' if study.passed else 'missed its goals'}: "
        f"{study.summary}; record {path}; report {report}")
    return EXIT_GOALS_MET if study.passed else EXIT_GOALS_MISSED


def _write_report(folder: Path, study: StudyRecord, page: str, charts: dict[str, bytes]) -> Path:
    d = folder / STUDIES_DIR
    stem = f"{study.at[:19].replace(':', '')}-{study.kind}-{study.uid[:8]}"
    for name, png in charts.items():
        (d / f"{stem}-{name}.png").write_bytes(png)
    path = d / f"{stem}.html"
    path.write_text(page)
    return path


def report_for(study: StudyRecord, spec: Spec) -> str:
    """A stored study's report rendered again (the console, tests)."""
    if study.kind == "type1":
        type1s = [msa.Type1(**{**f, "bias_ci": tuple(f["bias_ci"])}) for f in study.result["figures"]]
        rows_ = study.result["rows"]
        return type1_html(spec, study, type1s, {
            r.characteristic: run_chart(spec, r, [x["value"] for x in rows_ if x["characteristic"] == r.characteristic])
            for r in type1s})
    if study.kind == "type3":
        type3s = [msa.Type3(**{**f, "anova": tuple(msa.AnovaRow(**a) for a in f["anova"])})
                  for f in study.result["figures"]]
        return type3_html(spec, study, type3s)
    raise BadInput(f"study {study.uid}: a {study.kind} has no report")
