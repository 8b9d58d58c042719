"""Report figures as PNG: measured vs predicted per experiment, residual bands (paper Fig. 8/11)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from identify.result import FitResult


def axis_label(column: str) -> str:
    """``stroke_mm`` → ``stroke [mm]``: dataset columns carry their unit after the last underscore."""
    name, _, unit = column.rpartition("_")
    return f"{name.replace('_', ' ')} [{'°C' if unit == 'C' else unit}]" if name else column


def write_figures(result: FitResult, folder: Path) -> list[Path]:
    """Write ``fit_<output>.png`` (measured vs predicted over the phase of each experiment)
    and ``residuals.png`` (mean ± 2σ of the primary output per experiment)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    exps = result.experiments
    cols = min(4, len(exps))
    rows = int(np.ceil(len(exps) / cols))
    for out in result.outputs:
        fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), squeeze=False)
        for ax, e in zip(axes.ravel(), exps, strict=False):  # the grid may have spare cells
            tau = np.arange(len(e.measured[out])) / len(e.measured[out])
            ax.plot(tau, e.measured[out], ".", ms=1.5, label="measured")
            ax.plot(tau, e.predicted[out], "-", lw=1, label="model")
            ax.set_title(f"{e.label} ({e.frequency_hz:g} Hz)", fontsize=8)
            ax.set_xlabel("phase of the period [-]", fontsize=7)
            ax.set_ylabel(axis_label(out), fontsize=7)
            ax.tick_params(labelsize=7)
        for ax in axes.ravel()[len(exps):]:
            ax.axis("off")
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{result.model}: {out} over one period", fontsize=9)
        fig.tight_layout()
        path = folder / f"fit_{out}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    primary = result.outputs[0]
    stats = np.array([e.stats(primary) for e in exps])
    fig, ax = plt.subplots(figsize=(max(4, 0.5 * len(exps) + 2), 3))
    x = np.arange(len(exps))
    ax.errorbar(x, stats[:, 0], yerr=2 * stats[:, 1], fmt="o", capsize=3)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x, [e.label for e in exps], rotation=60, fontsize=7)
    ax.set_ylabel(f"residual {axis_label(primary)}, mean ± 2σ")
    fig.tight_layout()
    path = folder / "residuals.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def friction_figure(result, path: Path) -> Path:
    """Friction amplitude at each reversal against gas pressure, with the set's line (paper Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    p = np.array([r.pressure_bar for e in result.experiments for r in e.reversals])
    a = np.array([r.amplitude_n for e in result.experiments for r in e.reversals])
    ax.plot(p, a, "o", ms=4, label="reversals")
    x = np.linspace(0, p.max() * 1.05, 50)
    ax.plot(x, result.theta8 + result.theta9 * x * 1e5, "-", label=f"θ8 + θ9·p  (θ8 = {result.theta8:.3g} N, "
                                                                     f"θ9 = {result.theta9:.3g} m²)")
    ax.set_xlabel("gas pressure [bar]")
    ax.set_ylabel("friction amplitude [N]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
