"""Statistical process control over the records: individuals and moving-range (I-MR)
charts and capability per characteristic, as the AIAG SPC manual and the NIST/SEMATECH
e-Handbook (6.3.2.2, 6.1.6) do them.

Which units count: the latest judgement of each measurement (a re-judgement replaces the
earlier verdict on the same data, while both stay on record), of complete runs with a
value; aborted runs have none, and simulated ones are left out unless asked for — a test
on the simulator says nothing about the production process.

The limits come from a baseline (phase I): the first ``baseline`` units in test order (all
by default).  A point beyond the individuals limits, or whose moving range lies beyond the
moving-range limit, is flagged and left out of the estimate, and the limits are estimated
again until none is (a failed unit must not widen the limits that should have caught it).
Moving ranges are taken between neighbours in test order that both count.  σ within =
MR̄/d2 (d2 = 1.128), the individuals limits mean ± 3σ within, the moving-range limit
D4·MR̄ (D4 = 3.267).  Cp = (USL − LSL)/6σ and Cpk = min(USL − mean, mean − LSL)/3σ over
the baseline's counted points, with their number n; below n = 25 they are printed but
marked as not meaningful (AIAG: a capability needs at least 25 units).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 — after the backend is chosen
import numpy as np  # noqa: E402

from identify.notation import at_place, decimal_place, unit_text  # noqa: E402
from rig.qc.present import limits_text  # noqa: E402
from rig.qc.records import QcRecord  # noqa: E402

D2 = 1.128          # E[range of 2] / σ
D4 = 3.267          # moving-range chart's upper limit factor (D3 = 0)
MIN_CAPABILITY_N = 25
MAX_PASSES = 50     # flag-and-estimate-again; each pass drops at least one point


@dataclass(frozen=True)
class Capability:
    name: str
    title: str
    unit: str
    n: int                       # the baseline's points that count (flagged ones left out)
    n_units: int                 # every unit with a value on the chart
    mean: float | None
    std: float | None            # overall sample standard deviation of the counted points
    sigma_within: float | None   # MR̄/d2
    cp: float | None
    cpk: float | None
    low: float | None
    high: float | None
    nominal: float
    passed: int
    failed: int
    inconclusive: int
    lcl: float | None = None
    ucl: float | None = None
    mr_ucl: float | None = None
    flagged: tuple[int, ...] = field(default=())   # indices into the chart's points beyond a limit

    @property
    def meaningful(self) -> bool:
        return self.n >= MIN_CAPABILITY_N


def latest_judgements(records: list[QcRecord], include_simulated: bool = False) -> list[QcRecord]:
    """Complete runs, the last record of each measurement, in the order first measured;
    simulated ones only when asked."""
    latest: dict[str, QcRecord] = {}
    for r in records:
        if r.status == "COMPLETE" and (include_simulated or not r.simulated):
            latest.pop(r.data_sha256, None)   # re-inserted: ordered by the latest judgement's position
            latest[r.data_sha256] = r
    return list(latest.values())


def series(records: list[QcRecord], name: str) -> tuple[list[QcRecord], np.ndarray]:
    rows = [(r, c.value) for r in records for c in r.characteristics if c.name == name and c.value is not None]
    return [r for r, _ in rows], np.array([v for _, v in rows], dtype=float)


def imr_limits(x: np.ndarray, baseline: int | None = None) -> tuple[np.ndarray, float | None, float | None]:
    """The baseline's counted points (mask over ``x``), its mean and MR̄, after flagging and
    leaving out points beyond the limits until none is left (None: fewer than 2 counted)."""
    m = len(x) if baseline is None else min(baseline, len(x))
    keep = np.zeros(len(x), dtype=bool)
    keep[:m] = True
    for _ in range(MAX_PASSES):
        pairs = keep[:-1] & keep[1:]
        mr = np.abs(np.diff(x))[pairs]
        if keep.sum() < 2 or not len(mr):
            return keep, (float(x[keep].mean()) if keep.any() else None), None
        mean, mr_bar = float(x[keep].mean()), float(mr.mean())
        sigma = mr_bar / D2
        drop = keep & ((x > mean + 3 * sigma) | (x < mean - 3 * sigma))
        # of a moving range beyond its limit, the point further from the mean is flagged
        for j in np.flatnonzero(pairs & (np.abs(np.diff(x)) > D4 * mr_bar)):
            drop[j if abs(x[j] - mean) >= abs(x[j + 1] - mean) else j + 1] = True
        if not drop.any() or drop.sum() >= keep.sum() - 1:
            return keep, mean, mr_bar
        keep &= ~drop
    return keep, float(x[keep].mean()), mr_bar


def capability(records: list[QcRecord], include_simulated: bool = False,
               baseline: int | None = None) -> list[Capability]:
    judged = latest_judgements(records, include_simulated)
    names: dict[str, tuple[str, str]] = {}
    for r in judged:
        for c in r.characteristics:
            names.setdefault(c.name, (c.unit, c.title or c.name))
    out = []
    for name, (unit, title) in names.items():
        chars = [c for r in judged for c in r.characteristics if c.name == name]
        _, x = series(judged, name)
        last = chars[-1]                       # the limits in force: those of the latest judgement
        count = {o: sum(c.outcome == o for c in chars) for o in ("PASS", "FAIL", "INCONCLUSIVE")}
        keep, mean, mr_bar = imr_limits(x, baseline) if len(x) else (np.zeros(0, bool), None, None)
        kept = x[keep]
        within = mr_bar / D2 if mr_bar else None
        std = float(np.std(kept, ddof=1)) if len(kept) >= 2 else None
        cp = cpk = ucl = lcl = mr_ucl = None
        flagged: tuple[int, ...] = ()
        if within and mean is not None:
            ucl, lcl, mr_ucl = mean + 3 * within, mean - 3 * within, D4 * (mr_bar or 0.0)
            sides = [s for s in ((last.high - mean) if last.high is not None else None,
                                 (mean - last.low) if last.low is not None else None) if s is not None]
            cpk = min(sides) / (3 * within) if sides else None
            if last.low is not None and last.high is not None:
                cp = (last.high - last.low) / (6 * within)
            flagged = tuple(int(i) for i in np.flatnonzero((x > ucl) | (x < lcl)))
        out.append(Capability(name, title, unit, int(keep.sum()), len(x), mean, std, within, cp, cpk, last.low,
                              last.high, last.nominal, count["PASS"], count["FAIL"], count["INCONCLUSIVE"],
                              lcl, ucl, mr_ucl, flagged))
    return out


def stat(x: float | None, cap: Capability) -> str:
    """A statistic in the characteristic's unit, to the place of two significant digits of σ within."""
    if x is None or math.isnan(x):
        return "—"
    scale = cap.sigma_within or cap.std
    text = at_place(x, decimal_place(scale)) if scale else f"{x:.4g}"
    return f"{text} {unit_text(cap.unit)}"


def index(x: float | None, cap: Capability) -> str:
    """Cp or Cpk: two decimals, and not meaningful below n = 25."""
    if x is None or math.isnan(x):
        return "—"
    return f"{x:.2f}" if cap.meaningful else f"({x:.2f})"


def left_out(records: list[QcRecord], include_simulated: bool = False) -> str | None:
    """Why records are not counted, in one clause (None: every one counts): the charts and
    the capability table say it rather than showing nothing."""
    latest = latest_judgements(records, include_simulated=True)
    simulated = sum(r.simulated for r in latest) if not include_simulated else 0
    unjudged = sum(r.status != "COMPLETE" for r in records)
    parts = []
    if simulated:
        parts.append(f"{simulated} simulated (measured on the simulator; --include-simulated counts them)")
    if unjudged:
        parts.append(f"{unjudged} not complete (aborted or in error: no values)")
    return ", ".join(parts) + " left out" if parts else None


def control_charts(records: list[QcRecord], directory: Path, include_simulated: bool = False,
                   baseline: int | None = None) -> list[Path]:
    """One individuals chart (PNG) per characteristic: values in test order, centre line,
    control limits from the baseline, the specification limits, flagged points in red."""
    judged = latest_judgements(records, include_simulated)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for cap in capability(records, include_simulated, baseline):
        rows, x = series(judged, cap.name)
        if not len(x):
            continue
        u = unit_text(cap.unit)
        fig, ax = plt.subplots(figsize=(9.0, 4.4))
        i = np.arange(1, len(x) + 1)
        ax.plot(i, x, "-", color="#9bb0d0", lw=1)
        outside = np.zeros(len(x), dtype=bool)
        outside[list(cap.flagged)] = True
        labels = []
        if cap.ucl is not None and cap.lcl is not None:
            for y, label in ((cap.ucl, "UCL"), (cap.lcl, "LCL")):
                ax.axhline(y, color="#1f4e9c", ls=":", lw=1.2)
                labels.append((y, f"{label} {stat(y, cap)}", "#1f4e9c"))
        if cap.mean is not None:
            ax.axhline(cap.mean, color="#1f4e9c", lw=1.2)
            labels.append((cap.mean, f"mean {stat(cap.mean, cap)}", "#1f4e9c"))
        for y, label, colour in labels:
            ax.annotate(label, (1.0, y), xycoords=("axes fraction", "data"), xytext=(4, 0),
                        textcoords="offset points", va="center", fontsize=8, color=colour)
        for limit, label, inward in ((cap.low, "LSL", 1), (cap.high, "USL", -1)):
            if limit is not None:   # labelled inside on the left: control limits may lie close by on the right;
                # on the side of the line towards the tolerance band, so that the plot's edge never cuts it
                ax.axhline(limit, color="#c62828", ls="--", lw=1.2)
                ax.annotate(f"{label} {limit:g} {u}", (0.0, limit), xycoords=("axes fraction", "data"),
                            xytext=(4, 3 * inward), textcoords="offset points",
                            va="bottom" if inward > 0 else "top", fontsize=8, color="#c62828")
        drawn = [float(v) for v in (*x, cap.low, cap.high, cap.lcl, cap.ucl) if v is not None]
        pad = 0.08 * (max(drawn) - min(drawn) or abs(max(drawn)) or 1.0)
        ax.set_ylim(min(drawn) - pad, max(drawn) + pad)   # every line and its label inside the plot
        simulated = np.array([r.simulated for r in rows], dtype=bool)
        measured = ~outside & ~simulated
        ax.plot(i[measured], x[measured], "o", color="#1f4e9c", ms=5)
        if (simulated & ~outside).any():   # hollow: the simulator's, not a unit's measurement
            ax.plot(i[simulated & ~outside], x[simulated & ~outside], "o", mfc="white", mec="#1f4e9c", ms=6,
                    label="SIMULATED: measured on the simulator, not on a unit")
        if outside.any():
            ax.plot(i[outside], x[outside], "o", color="#c62828", ms=7,
                    label="beyond the control limits (left out of their estimate)")
        if outside.any() or simulated.any():
            ax.legend(fontsize=8, loc="best")
        if simulated.any():   # across the plot, as on the report: a simulated chart is never a process chart
            ax.text(0.5, 0.5, "SIMULATED", transform=ax.transAxes, fontsize=56, color="#c62828", alpha=0.13,
                    ha="center", va="center", rotation=20, fontweight="bold", zorder=0)
        ax.set_xlabel("unit, in test order")
        ax.set_ylabel(f"{cap.title} [{u}]")
        note = "" if cap.meaningful else f"; n < {MIN_CAPABILITY_N}: not meaningful"
        sim = "" if not simulated.any() else (
            "SIMULATED: " if simulated.all() else f"SIMULATED ({int(simulated.sum())} of {len(x)} units): ")
        ax.set_title(f"{sim}Individuals chart: {cap.title}, spec "
                     f"{limits_text(cap.nominal, cap.low, cap.high, cap.unit)}"
                     f"\nn = {cap.n}, Cp {index(cap.cp, cap)}, Cpk {index(cap.cpk, cap)}{note}", fontsize=10,
                     color="#c62828" if sim else "black")
        ax.grid(alpha=0.3)
        if len(x) <= 25:
            ax.set_xticks(i, [r.serial for r in rows], rotation=60, ha="right", fontsize=7)
        fig.tight_layout()
        path = directory / f"{re.sub(r'[^A-Za-z0-9._-]', '_', cap.name)}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written
