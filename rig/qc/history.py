"""Statistical process control over the records: capability per characteristic and
individuals control charts.

Only the latest judgement of each measurement counts (a re-judgement replaces the
earlier verdict on the same data for the statistics, while both stay on record), and
only complete runs with a value.  Cp and Cpk follow the AIAG convention for individual
values: σ within = MR̄/d2 (d2 = 1.128 for moving ranges of two), the process limits of
the chart at mean ± 3·σ within; ``std`` is the overall sample standard deviation.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 — after the backend is chosen
import numpy as np  # noqa: E402

from rig.qc.records import QcRecord  # noqa: E402

D2 = 1.128


@dataclass(frozen=True)
class Capability:
    name: str
    unit: str
    n: int
    mean: float | None
    std: float | None
    sigma_within: float | None
    cp: float | None
    cpk: float | None
    low: float | None
    high: float | None
    passed: int
    failed: int
    inconclusive: int


def latest_judgements(records: list[QcRecord]) -> list[QcRecord]:
    """Complete runs, the last record of each measurement, in the order first measured."""
    latest: dict[str, QcRecord] = {}
    for r in records:
        if r.status == "COMPLETE":
            latest.pop(r.data_sha256, None)   # re-inserted: ordered by the latest judgement's position
            latest[r.data_sha256] = r
    return list(latest.values())


def series(records: list[QcRecord], name: str) -> tuple[list[QcRecord], np.ndarray]:
    rows = [(r, c.value) for r in records for c in r.characteristics if c.name == name and c.value is not None]
    return [r for r, _ in rows], np.array([v for _, v in rows], dtype=float)


def capability(records: list[QcRecord]) -> list[Capability]:
    judged = latest_judgements(records)
    names: dict[str, str] = {}
    for r in judged:
        for c in r.characteristics:
            names.setdefault(c.name, c.unit)
    out = []
    for name, unit in names.items():
        chars = [c for r in judged for c in r.characteristics if c.name == name]
        _, x = series(judged, name)
        last = chars[-1]                       # the limits in force: those of the latest judgement
        mean = float(np.mean(x)) if len(x) else None
        std = float(np.std(x, ddof=1)) if len(x) >= 2 else None
        within = float(np.mean(np.abs(np.diff(x))) / D2) if len(x) >= 2 else None
        cp = cpk = None
        if within and mean is not None:
            sides = [s for s in ((last.high - mean) if last.high is not None else None,
                                 (mean - last.low) if last.low is not None else None) if s is not None]
            cpk = min(sides) / (3 * within) if sides else None
            if last.low is not None and last.high is not None:
                cp = (last.high - last.low) / (6 * within)
        count = {o: sum(c.outcome == o for c in chars) for o in ("PASS", "FAIL", "INCONCLUSIVE")}
        out.append(Capability(name, unit, len(x), mean, std, within, cp, cpk, last.low, last.high,
                              count["PASS"], count["FAIL"], count["INCONCLUSIVE"]))
    return out


def control_charts(records: list[QcRecord], directory: Path) -> list[Path]:
    """One individuals chart (PNG) per characteristic: values in test order, centre line,
    natural process limits mean ± 3·MR̄/d2, and the specification limits."""
    judged = latest_judgements(records)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for cap in capability(records):
        rows, x = series(judged, cap.name)
        if not len(x):
            continue
        fig, ax = plt.subplots(figsize=(9.0, 4.2))
        i = np.arange(1, len(x) + 1)
        ax.plot(i, x, "-", color="#9bb0d0", lw=1)
        outside = np.zeros(len(x), dtype=bool)
        if cap.sigma_within and cap.mean is not None:
            ucl, lcl = cap.mean + 3 * cap.sigma_within, cap.mean - 3 * cap.sigma_within
            outside = (x > ucl) | (x < lcl)
            for y, label in ((ucl, "UCL"), (lcl, "LCL")):
                ax.axhline(y, color="#1f4e9c", ls=":", lw=1.2)
                ax.annotate(f"{label} {y:.4g}", (1.0, y), xycoords=("axes fraction", "data"), xytext=(4, 0),
                            textcoords="offset points", va="center", fontsize=8, color="#1f4e9c")
        if cap.mean is not None:
            ax.axhline(cap.mean, color="#1f4e9c", lw=1.2)
            ax.annotate(f"mean {cap.mean:.4g}", (1.0, cap.mean), xycoords=("axes fraction", "data"), xytext=(4, 0),
                        textcoords="offset points", va="center", fontsize=8, color="#1f4e9c")
        for limit, label in ((cap.low, "LSL"), (cap.high, "USL")):
            if limit is not None:   # labelled inside on the left: control limits may lie close by on the right
                ax.axhline(limit, color="#c62828", ls="--", lw=1.2)
                ax.annotate(f"{label} {limit:.4g}", (0.0, limit), xycoords=("axes fraction", "data"), xytext=(4, 3),
                            textcoords="offset points", va="bottom", fontsize=8, color="#c62828")
        ax.plot(i[~outside], x[~outside], "o", color="#1f4e9c", ms=5)
        if outside.any():
            ax.plot(i[outside], x[outside], "o", color="#c62828", ms=7, label="beyond the control limits")
            ax.legend(fontsize=8, loc="best")
        ax.set_xlabel("unit, in test order")
        ax.set_ylabel(f"{cap.name} [{cap.unit}]")
        cp = "—" if cap.cp is None else f"{cap.cp:.2f}"
        cpk = "—" if cap.cpk is None else f"{cap.cpk:.2f}"
        ax.set_title(f"Individuals chart: {cap.name} (n = {cap.n}, Cp {cp}, Cpk {cpk})", fontsize=11)
        ax.grid(alpha=0.3)
        if len(x) <= 25:
            ax.set_xticks(i, [r.serial for r in rows], rotation=60, ha="right", fontsize=7)
        fig.tight_layout()
        path = directory / f"{re.sub(r'[^A-Za-z0-9._-]', '_', cap.name)}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def fmt(x: float | None, digits: int = 4) -> str:
    return "—" if x is None or math.isnan(x) else f"{x:.{digits}g}"
