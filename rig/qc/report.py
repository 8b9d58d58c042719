"""The unit's QC report: one self-contained HTML page (figures as PNG data URIs), for the
operator at the station and for the quality engineer later.

Top to bottom: the verdict, large; the likely causes or the remedy; the characteristics
as rig.qc.present shows them (value ± k·σ, σ and which one, the limits as the spec states
them, the acceptance limits), with one note per characteristic on its σ; each on its
tolerance band; the work loops measured against the identified model; where it was
measured and the rest of the record's traceability.  A record measured on a simulator
carries a SIMULATED watermark on every page.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 — after the backend is chosen
import numpy as np  # noqa: E402

from identify.folding import fold  # noqa: E402
from identify.notation import unit_text  # noqa: E402
from rig.qc.evaluate import Evaluation  # noqa: E402
from rig.qc.present import shown, sigma_note, verdict_colours  # noqa: E402
from rig.qc.records import QcRecord  # noqa: E402
from rig.qc.spec import Spec  # noqa: E402

TOLERANCE_ZONE, CONFORMANCE_ZONE = "#f3d9a4", "#b7e1c1"


def _png(fig: plt.Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def band_figure(record: QcRecord, spec: Spec) -> str:
    """Each characteristic on its band: the tolerance zone, the zone where a value passes
    with its guard band (limits moved in by k·σ), the nominal, and value ± k·σ."""
    rows = record.characteristics
    fig, axes = plt.subplots(len(rows), 1, figsize=(9.0, 1.25 * len(rows) + 0.4), squeeze=False)
    k = spec.k
    for ax, c in zip(axes[:, 0], rows, strict=True):
        low = c.low if c.low is not None else c.nominal - 2 * abs(c.high - c.nominal)  # type: ignore[operator]
        high = c.high if c.high is not None else c.nominal + 2 * abs(c.nominal - c.low)  # type: ignore[operator]
        span = high - low
        values = [low, high] + ([c.value - k * c.std, c.value + k * c.std] if c.value is not None and c.std else [])
        left, right = min(values) - 0.15 * span, max(values) + 0.15 * span
        ax.axvspan(low, high, color=TOLERANCE_ZONE, label="tolerance")
        if c.std is not None and high - low > 2 * k * c.std:
            ax.axvspan(low + k * c.std, high - k * c.std, color=CONFORMANCE_ZONE,
                       label=f"acceptance zone (limits ∓ {k:g}σ)")
        ax.axvline(c.nominal, color="#444444", lw=1, ls="--", label="nominal")
        if c.value is not None and c.std is not None:
            ax.errorbar([c.value], [0.0], xerr=[[k * c.std], [k * c.std]], fmt="o", ms=7, capsize=6, lw=2,
                        color=verdict_colours(c.outcome).text)
        ax.set_xlim(left, right)
        ax.set_ylim(-1, 1)
        ax.set_yticks([])
        ax.set_title(f"{c.title or c.name}: {c.outcome}", loc="left", fontsize=10,
                     color=verdict_colours(c.outcome).text)
        ax.set_xlabel(f"{c.title or c.name} [{unit_text(c.unit)}]", fontsize=9, labelpad=1)
        ax.tick_params(axis="x", labelsize=9)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", fontsize=8, ncol=3, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return _png(fig)


def loops_figure(evaluation: Evaluation) -> str | None:
    """Force against stroke per experiment: measured (folded over the captured periods)
    and the model's stroke response to the measured force."""
    exps = evaluation.experiments
    if not exps:
        return None
    fig, axes = plt.subplots(1, len(exps), figsize=(3.6 * len(exps), 3.8), squeeze=False)
    fits = {e.label: e for e in evaluation.fit.experiments} if evaluation.fit else {}
    n = evaluation.fit.n_grid if evaluation.fit else 800
    for ax, e in zip(axes[0], exps, strict=True):
        fit = fits.get(e.label)
        model: np.ndarray | None
        if fit is not None and fit.capture == "transient":
            # A record from RUN on is not folded: its loops as they grew, sample by sample.
            force_kn, stroke = e.column("force_N") / 1e3, e.column("stroke_mm")
            model = fit.predicted["stroke_mm"]
        else:
            folded = fold(e.label, e.time_s, {"stroke_mm": e.column("stroke_mm"), "force_N": e.column("force_N")},
                          e.frequency_hz, n, e.sample_rate_hz)
            force_kn = np.append(folded.values["force_N"], folded.values["force_N"][0]) / 1e3
            stroke = np.append(folded.values["stroke_mm"], folded.values["stroke_mm"][0])
            model = None if fit is None else np.append(fit.predicted["stroke_mm"], fit.predicted["stroke_mm"][0])
        ax.plot(stroke, force_kn, color="#8fb3e8", lw=4.0 if fit is None or fit.capture != "transient" else 1.5,
                label="measured")
        if model is not None:      # the model's stroke under the measured force: drawn over the measurement
            ax.plot(model, force_kn, color="#b34700", lw=1.1, ls="--", label="identified model")
        ax.set_title(f"{e.label}: {e.meta.get('static_position_mm', '?')} ± {e.meta.get('amplitude_mm', '?')} mm, "
                     f"{e.frequency_hz:g} Hz", fontsize=10)
        ax.set_xlabel("stroke [mm]", fontsize=10)
        ax.set_ylabel("axle force [kN]", fontsize=10)
        ax.tick_params(labelsize=9)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=9, loc="upper left")
    fig.tight_layout()
    return _png(fig)


IDENTIFIED = {"login": "identified by the station: OS login", "pin": "identified by the station: PIN",
              "typed": "typed, not identified by a station"}


RELEASE = {"required": "required by the spec: a second person approves this record (python -m rig qc release "
                        "SERIAL); the database holds the release, not this report",
           None: "not required by the spec"}


def ambient_text(ambient: dict | None) -> str:
    """The ambient conditions as the report states them; the rig's controller and DAQ
    report none (docs/rig-interfaces.md: the gas temperature is the damper's, not the room's)."""
    if not ambient:
        return "not reported by the rig"
    return ", ".join(f"{k} {v}" for k, v in sorted(ambient.items()))


def _css_string(text: str) -> str:
    """A CSS string literal: quotes and backslashes escaped, '<' too (it sits inside <style>)."""
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("<", "\\3C ").replace("\n", " ")
    return f'"{escaped}"'


def budget_tables(record: QcRecord) -> str:
    """Each measurand's GUM uncertainty budget, row by row (from the record's details),
    with the combined standard uncertainty u and the expanded U = k·u."""
    obtained = record.details.get("characteristics", {})
    e = html.escape
    out = []
    for c in record.characteristics:
        budget = obtained.get(c.name, {}).get("budget")
        if not budget or c.std is None:
            continue
        u = unit_text(c.unit)
        rows = "".join(f"<tr><td>{e(str(r['source']))}</td><td>{e(str(r['type']))}</td>"
                       f"<td class=num>{float(r['u']):.2g} {e(u)}</td><td><small>{e(str(r['basis']))}</small></td></tr>"
                       for r in budget)
        k = record.k or 2.0
        out.append(f"<h3>{e(c.title or c.name)} ({obtained[c.name].get('cycles', '?')} cycles)</h3>"
                   f"<table><tr><th>source</th><th>type</th><th>u</th><th>how</th></tr>{rows}"
                   f"<tr><th>combined u</th><td></td><td class=num><b>{c.std:.2g} {e(u)}</b></td><td></td></tr>"
                   f"<tr><th>expanded U = k·u, k = {k:g}</th><td></td><td class=num><b>{k * c.std:.2g} {e(u)}</b>"
                   f"</td><td></td></tr></table>")
    return ("<h2>Uncertainty budgets (GUM)</h2>" + "".join(out)) if out else ""


def render_report(record: QcRecord, spec: Spec, evaluation: Evaluation | None) -> str:
    def e(text: str) -> str:
        """Escaped, and without a path of the station's disk: the session folder is named by
        its archive id, the station's folder (a retest command's --out) as STATION_DIR."""
        text = str(text)
        if len(Path(record.session).parts) > 2:     # a real folder in a station's folder, not "/" itself
            text = text.replace(record.session, record.archive_id)
            text = text.replace(str(Path(record.session).parent), "STATION_DIR")
        return html.escape(text)

    verdict = record.verdict or f"no verdict ({record.status})"
    colour = verdict_colours(record.verdict).text
    descriptions = {c.name: c.description for c in spec.characteristics}
    obtained = record.details.get("characteristics", {})
    rows = []
    for c in record.characteristics:
        s = shown(record, c, spec.k)
        how = obtained.get(c.name, {})
        definition = how.get("definition") or descriptions.get(c.name, "")
        label = f"<i>{e(how['obtained'])}</i>: " if "obtained" in how else ""
        rows.append(
            f"<tr><td><b>{e(s.title)}</b><br><small>{label}{e(definition)}<br>"
            f"<code>{e(s.name)}</code></small></td>"
            f"<td class=num>{e(s.value)}</td><td class=num>{e(s.sigma)}<br><small>{e(s.basis)}</small></td>"
            f"<td class=num>{e(s.limits)}</td><td class=num>{e(s.acceptance)}</td>"
            f"<td style='color:{verdict_colours(c.outcome).text};font-weight:bold'>{e(c.outcome)}</td></tr>")
    sigma_notes = "".join(f"<li>{e(sigma_note(c))}</li>" for c in record.characteristics)
    budgets = budget_tables(record)
    findings = ""
    if record.reason:
        findings += f"<div class=box><h2>Why there is no verdict</h2><p>{e(record.reason)}</p></div>"
    if record.diagnosis:
        findings += "<div class=box><h2>Likely cause</h2><ul>" + "".join(
            f"<li>{e(d)}</li>" for d in record.diagnosis) + "</ul></div>"
    if record.remedy:
        findings += f"<div class=box><h2>Remedy</h2><p>{e(record.remedy)}</p></div>"
    figures = ""
    if record.characteristics:
        bands = band_figure(record, spec)
        figures += f"<h2>Characteristics on their tolerance bands</h2><img alt='bands' src='{bands}'>"
    loops = loops_figure(evaluation) if evaluation is not None else None
    if loops:
        figures += f"<h2>Work loops: measured and identified model</h2><img alt='work loops' src='{loops}'>"
    controller = ", ".join(f"{k} {v}" for k, v in (record.controller or {}).items()) or "not identified"
    operator = f"{record.operator} ({IDENTIFIED.get(record.identified_by or '', 'identification not recorded')})"
    trace = [("serial", record.serial), ("station", record.station or "not named"), ("operator", operator),
             ("rig", record.rig),
             ("measured on", "a SIMULATOR, not hardware" if record.simulated else "hardware (no peer named "
                                                                                   "itself a simulator)"),
             ("controller", controller), ("DAQ *IDN?", record.daq or "not identified"),
             ("measured", f"{record.started or '—'} … {record.finished or '—'}"), ("judged", record.judged),
             ("status", record.status), ("software", record.software),
             ("ambient conditions", ambient_text(record.ambient)),
             ("spec", f"{record.spec_name} {record.spec_version}"), ("spec sha256", record.spec_sha256),
             ("calibration sha256", record.calibration_sha256 or "—"),
             ("register map sha256", record.register_map_sha256 or "—"),
             ("archive id", record.archive_id), ("record", record.uid), ("re-judges record", record.rejudges or "—")]
    trace += [(f"sha256 {name}", digest) for name, digest in sorted(record.files.items())]
    notes = "".join(f"<li>{e(n)}</li>" for n in record.notes if n != record.reason)
    equipment = "".join(
        f"<tr><td>{e(q.name)}</td><td>{e(q.serial or '—')}</td><td>{e(q.certificate or '—')}</td>"
        f"<td>{e(q.due or '—')}</td><td class=hash>{e(q.sha256 or '—')}</td></tr>" for q in record.equipment) or (
        "<tr><td colspan=5>none recorded</td></tr>")
    if record.flagged:
        findings += ("<div class='box flagged'><h2>Flagged captures</h2><p>The session captured these experiments "
                     "anyway and flagged them; the verdict uses them as captured.</p><ul>" + "".join(
                         f"<li><b>{e(label)}</b>: {e('; '.join(flags))}</li>"
                         for label, flags in sorted(record.flagged.items())) + "</ul></div>")
    watermark = ("<div class=watermark aria-hidden=true>SIMULATED</div><div class=simbanner>SIMULATED: measured on "
                 "a simulator, not on hardware. Not a production record.</div>") if record.simulated else ""
    # A re-judgement says so where the eye lands first: the title, the header and a box
    # naming the record it judges again (it looked like the original before).
    kind = "QC re-judgement" if record.rejudges else "QC report"
    if record.rejudges:
        findings = (f"<div class=box><h2>Re-judgement</h2><p>This report judges again the measurement of record "
                    f"<code>{e(record.rejudges)}</code> ({e(record.started or '—')} … {e(record.finished or '—')}), "
                    f"with spec {e(record.spec_name)} {e(record.spec_version)}. That record and its report are "
                    f"kept unchanged.</p><p>Re-judged by <b>{e(operator)}</b> at {e(record.judged)}; why: "
                    f"{e(record.rejudge_reason or 'no reason given')}.</p></div>") + findings
    head = f"{kind} — unit {record.serial} — station {record.station or record.rig} — record {record.uid}"
    header = (f"<table class=head><tr><th>station</th><td>{e(record.station or 'not named')}</td>"
              f"<th>operator</th><td>{e(operator)}</td></tr>"
              f"<tr><th>archive id</th><td>{e(record.archive_id)}</td><th>software</th>"
              f"<td>{e(record.software)}</td></tr>"
              f"<tr><th>record</th><td>{e(record.uid)}</td><th>judged</th><td>{e(record.judged)}</td></tr>"
              f"<tr><th>ambient</th><td>{e(ambient_text(record.ambient))}</td><th>equipment</th>"
              f"<td>{len(record.equipment)} item{'s' * (len(record.equipment) != 1)} (below)</td></tr>"
              f"<tr><th>release</th><td colspan=3>{e(RELEASE.get(record.details.get('release'), RELEASE[None]))}"
              "</td></tr></table>")
    basis = (f" Revision {e(record.spec_version)}, sha256 <code>{e(record.spec_sha256[:16])}…</code>; basis: "
             f"{e(str(record.details['spec_basis']))}" if record.details.get("spec_basis") else "")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>{kind} {e(record.serial)}: {e(verdict)}{' (SIMULATED)' if record.simulated else ''}\
{f' of record {e(record.rejudges[:8])}' if record.rejudges else ''}</title>
<style>
body {{ font-family: "DejaVu Sans", Arial, sans-serif; margin: 24px auto; max-width: 1000px; color: #222; }}
.verdict {{ font-size: 56px; font-weight: bold; color: #fff; background: {colour}; padding: 10px 24px;
           border-radius: 8px; display: inline-block; }}
h1 {{ font-size: 22px; margin: 0 0 10px 0; }} h2 {{ font-size: 17px; margin: 22px 0 6px 0; }}
h3 {{ font-size: 14px; margin: 14px 0 4px 0; }}
table {{ border-collapse: collapse; width: 100%; font-size: 13px; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 5px 8px; text-align: left; vertical-align: top; }}
td.num {{ text-align: right; white-space: nowrap; font-variant-numeric: tabular-nums; }}
.box {{ border-left: 5px solid {colour}; background: #f7f7f7; padding: 4px 14px; margin: 14px 0; }}
img {{ max-width: 100%; }}
.watermark {{ position: fixed; top: 40%; left: 0; right: 0; text-align: center; font-size: 150px; font-weight: bold;
  color: rgba(198, 40, 40, 0.13); transform: rotate(-30deg); pointer-events: none; z-index: 10; }}
.simbanner {{ background: #c62828; color: #fff; font-weight: bold; padding: 6px 12px; margin-bottom: 10px; }}
/* Printed, the colours are the message (white PASS on green, the white SIMULATED banner on
   red): without this a browser drops the backgrounds and the words vanish.  The fixed
   watermark repeats on every printed page. */
* {{ -webkit-print-color-adjust: exact; print-color-adjust: exact; }}
h2 {{ break-after: avoid; }} img, tr {{ break-inside: avoid; }}
.trace td, td.hash {{ font-family: "DejaVu Sans Mono", monospace; font-size: 11px;
  word-break: break-all; }}
table.head {{ margin-bottom: 12px; }} table.head th {{ width: 11%; color: #555; }}
.flagged {{ border-left-color: #b26a00; }}
/* Every printed page: a running head naming the unit, station and record, page numbers,
   and for a simulated record SIMULATED in the margin too (the fixed watermark repeats). */
@page {{ size: A4; margin: 16mm 12mm 16mm 12mm;
  @top-left {{ content: {_css_string(head)}; font-size: 8pt; color: #555; }}
  @top-right {{ content: {_css_string('SIMULATED' if record.simulated else '')}; font-size: 9pt;
    font-weight: bold; color: #c62828; }}
  @bottom-left {{ content: {_css_string('archive id ' + record.archive_id)}; font-size: 8pt; color: #555; }}
  @bottom-right {{ content: "page " counter(page) " of " counter(pages); font-size: 8pt; color: #555; }} }}
@media print {{ body {{ margin: 0; max-width: none; }}
  .watermark {{ font-size: 104px; top: 42%; }} }}
</style></head><body>
{watermark}
<h1>{kind} — unit {e(record.serial)}{f' (re-judges record {e(record.rejudges)})' if record.rejudges else ''}</h1>
{header}
<div class="verdict">{e(verdict)}</div>
<p>Spec <b>{e(record.spec_name)} {e(record.spec_version)}</b> ({e(spec.title)}); guard band k = {spec.k:g}:
PASS when value ± kσ lies inside the limits, that is the value inside the acceptance limits (the limits moved
in by kσ); FAIL when value ∓ kσ lies outside (ISO 14253-1).{basis}</p>
{findings}
<h2>Characteristics</h2>
<table><tr><th>characteristic</th><th>value ± {spec.k:g}σ</th><th>σ (which)</th><th>limits (spec)</th>
<th>acceptance limits</th><th>outcome</th></tr>
{''.join(rows) or '<tr><td colspan=6>none: the run ended without a verdict</td></tr>'}</table>
{'<h2>Which σ the verdict used</h2><ul>' + sigma_notes + '</ul>' if sigma_notes else ''}
{budgets}
{figures}
{'<h2>Notes</h2><ul>' + notes + '</ul>' if notes else ''}
<h2>Measuring equipment</h2>
<table><tr><th>item</th><th>serial</th><th>certificate</th><th>calibration due</th><th>sha256</th></tr>
{equipment}</table>
<h2>Traceability</h2>
<table class="trace">{''.join(f'<tr><th>{e(k)}</th><td>{e(str(v))}</td></tr>' for k, v in trace)}</table>
</body></html>
"""
