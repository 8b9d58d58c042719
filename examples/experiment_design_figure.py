"""The figure of docs/experiment-design.md: rig design's candidate space (frequency,
amplitude, static position within the rig's limits), each candidate coloured by its
predicted rig time from rest, with the standard plan and the designed plans on it.

    python -m rig design --target theta4,theta6,theta16 --no-worse-than standard --out lab.toml
    python examples/experiment_design_figure.py --plan lab.toml --plan rig/qc/specs/default.toml \\
        --out docs/experiment-design.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from identify.model import load_model  # noqa: E402
from identify.parameters import Parameters  # noqa: E402
from rig.config import load_rig_config  # noqa: E402
from rig.design import candidate_specs, standalone_seconds  # noqa: E402
from rig.planning.plans import load_plan  # noqa: E402

MARKERS = ("*", "D", "^", "v")
COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:purple")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plan", action="append", default=[], help="a designed plan (or a QC spec) to mark")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    config = load_rig_config(None)
    specs = candidate_specs(config)
    seconds = standalone_seconds(specs, config, Parameters(load_model("2dof")))
    f = np.array([e.frequency_hz for e in specs])
    a = np.array([e.amplitude_mm for e in specs])
    s = np.array([e.static_position_mm for e in specs])
    # candidates sharing a frequency and amplitude are spread sideways by static position
    statics = sorted(set(s))
    shift = np.array([1.0 + 0.05 * (statics.index(x) - len(statics) / 2) for x in s])

    fig, (left, right) = plt.subplots(1, 2, figsize=(12.5, 5.6), constrained_layout=True)
    kw = dict(c=seconds, cmap="viridis", s=22, vmin=0, vmax=float(np.percentile(seconds, 95)))
    points = left.scatter(f * shift, a, **kw)
    right.scatter(s, a, **kw)
    ff = np.geomspace(0.03, 5, 100)
    left.plot(ff, config.limits.max_velocity_m_s / (2 * np.pi * ff) * 1e3, "k--", lw=1,
              label=f"velocity limit {config.limits.max_velocity_m_s:g} m/s")
    lo, hi = config.limits.stroke_low_m * 1e3, config.limits.stroke_high_m * 1e3
    ss = np.linspace(lo, hi, 100)
    right.plot(ss, np.minimum(ss - lo, hi - ss), "k--", lw=1, label=f"stroke limits {lo:g}…{hi:g} mm")

    standard = load_plan("standard").experiments
    for ax, x in ((left, [e.frequency_hz for e in standard]), (right, [e.static_position_mm for e in standard])):
        ax.scatter(x, [e.amplitude_mm for e in standard], marker="x", c="black", s=50, label="standard plan (14)")
    for k, path in enumerate(args.plan):
        plan = load_plan(path)
        name = f"{plan.name} ({len(plan.experiments)})"
        for ax, x in ((left, [e.frequency_hz for e in plan.experiments]),
                      (right, [e.static_position_mm for e in plan.experiments])):
            ax.scatter(x, [e.amplitude_mm for e in plan.experiments], marker=MARKERS[k % 4], s=170,
                       facecolors="none", edgecolors=COLOURS[k % 4], linewidths=2, label=name)
    left.set_xscale("log")
    left.set_xlabel("frequency [Hz]")
    right.set_xlabel("static position [mm]")
    for ax in (left, right):
        ax.set_ylabel("amplitude [mm]")
        ax.set_ylim(0, 140)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left" if ax is left else "lower center", fontsize=8, framealpha=0.9)
    left.set_title(f"{len(specs)} candidates within the rig's limits")
    right.set_title("the same, by static position")
    fig.colorbar(points, ax=[left, right], label="predicted rig time from rest, without the capture [s]")
    fig.suptitle("candidates of rig design coloured by predicted rig time; at one static position and amplitude, "
                 "the frequencies overlap on the right", fontsize=9)
    fig.savefig(args.out, dpi=110)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
