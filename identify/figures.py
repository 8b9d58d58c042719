"""Report figures as PNG: measured vs predicted per experiment, residual bands (paper Fig. 8/11)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from identify.preparation import MULTISINE_LINES, excited_lines
from identify.result import ExperimentFit, FitResult


def axis_label(column: str) -> str:
    """``stroke_mm`` → ``stroke [mm]``: dataset columns carry their unit after the last underscore."""
    name, _, unit = column.rpartition("_")
    return f"{name.replace('_', ' ')} [{'°C' if unit == 'C' else unit}]" if name else column


def write_figures(result: FitResult, folder: Path, loops: bool = False) -> list[Path]:
    """Write ``fit_<output>.png`` (measured vs predicted over the phase of each experiment),
    ``residuals.png`` (mean ± 2σ of each fitted output per experiment), for
    multisine records ``frf_<output>.png`` (frequency response at the excited lines) and,
    with ``loops`` (a model driven by an input's derivative: a damper whose displacement
    is imposed), ``loop_<output>.png``: each output against the input's rate, the
    force–velocity loop a damper test is judged by."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    exps = result.experiments
    cols = min(4, len(exps))
    rows = int(np.ceil(len(exps) / cols))
    for out in result.outputs:
        fig, axes = plt.subplots(rows, cols, figsize=(max(5.5, 3.6 * cols), 0.5 + 2.6 * rows), squeeze=False)
        windows = []
        for ax, e in zip(axes.ravel(), exps, strict=False):  # the grid may have spare cells
            windows.append(_time_panel(ax, e, out, result.units))
        for ax in axes.ravel()[len(exps):]:
            ax.axis("off")
        # Beneath the panels: inside one it hid the data of a multisine's window.
        fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="lower center", ncol=3, fontsize=7, frameon=False)
        what = "over one period" if not any(windows) else (
            "a window of each record (frf_*.png shows every excited line)" if all(windows) else
            "over one period; multisines in a window of their dominant line")
        fig.suptitle(f"{result.model}: {_label(out, result.units)}\n{what}", fontsize=9)
        fig.tight_layout(rect=(0, 0.25 / (0.5 + 2.6 * rows), 1, 1))
        path = folder / f"fit_{out}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    broadband = [e for e in exps if _broadband(e)]
    for out in result.outputs if broadband else []:
        written.append(_frf_figure(result, out, broadband, folder / f"frf_{out}.png"))
    for out in result.outputs if loops and exps and all(e.inputs for e in exps) else []:
        written.append(_loop_figure(result, out, folder / f"loop_{out}.png"))
    outputs = result.outputs
    fig, axes = plt.subplots(len(outputs), 1, figsize=(max(4, 0.5 * len(exps) + 2), 0.4 + 2.6 * len(outputs)),
                             sharex=True, squeeze=False)
    x = np.arange(len(exps))
    for ax, out in zip(axes[:, 0], outputs, strict=True):
        stats = np.array([e.stats(out) for e in exps])
        ax.errorbar(x, stats[:, 0], yerr=2 * stats[:, 1], fmt="o", capsize=3)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"residual {_label(out, result.units)}\nmean ± 2σ", fontsize=8)
    axes[-1, 0].set_xticks(x, [e.label for e in exps], rotation=60, fontsize=7)
    axes[-1, 0].set_xlabel("experiment", fontsize=8)
    fig.tight_layout()
    path = folder / "residuals.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def _loop_figure(result: FitResult, out: str, path: Path) -> Path:
    """Measured and model output against the first input's rate (its spectral time
    derivative on the grid), all records in one panel, each in its colour."""
    import matplotlib.pyplot as plt

    from identify.differentiation import periodic_derivative

    column = next(iter(result.experiments[0].inputs))
    name, _, unit = column.rpartition("_")
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for i, e in enumerate(result.experiments):
        rate = periodic_derivative(e.inputs[column], e.frequency_hz, 1)
        colour = f"C{i % 10}"
        ax.plot(rate, e.measured[out], ".", ms=2.5, color=colour)
        # In grid order, closed at the period's end: the loop as the damper runs it.
        ax.plot(np.append(rate, rate[0]), np.append(e.predicted[out], e.predicted[out][0]), "-", lw=1,
                color=colour, label=f"{e.label} ({e.frequency_hz:.3g} Hz)")
    ax.set_xlabel(f"{(name or column).replace('_', ' ')} rate [{unit or '-'}/s]", fontsize=9)
    ax.set_ylabel(_label(out, result.units), fontsize=9)
    ax.set_title(f"{result.model}: {_label(out, result.units)} against the imposed rate\n"
                 f"dots measured (folded), lines the fitted model", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


WINDOW_PERIODS = 5  # of a multisine's dominant line: what a time plot of it can show readably


def _time_panel(ax, e: ExperimentFit, out: str, units: dict[str, str]) -> bool:
    """Measured and model output of one experiment over its period, or for a multisine
    (whose whole period is an unreadable band) over WINDOW_PERIODS periods of the
    output's dominant line around its largest swing, with the misfit; whether windowed."""
    y, model = e.measured[out], e.predicted[out]
    n = len(y)
    broadband = _broadband(e)
    if not broadband:
        tau = np.arange(n) / n
        ax.plot(tau, y, ".", ms=1.5, label="measured")
        ax.plot(tau, model, "-", lw=1, label="model")
        ax.set_title(f"{e.label} ({e.frequency_hz:g} Hz)", fontsize=8)
        ax.set_xlabel("phase of the period [-]", fontsize=7)
    else:
        spectrum = np.abs(np.fft.rfft(y - y.mean()))
        dominant = max(1, int(np.argmax(spectrum)))
        width = min(n, int(np.ceil(WINDOW_PERIODS * n / dominant)))
        first = int(np.argmax(np.abs(y - y.mean()))) - width // 2
        idx = np.arange(first, first + width) % n  # periodic: a window may wrap round the period's end
        t = (first + np.arange(width)) / (n * e.frequency_hz)
        ax.plot(t, y[idx], ".", ms=2, label="measured")
        ax.plot(t, model[idx], "-", lw=1, label="model")
        ax.plot(t, y[idx] - model[idx], "-", lw=0.8, color="#c03030", label="measured − model")
        ax.set_title(f"{e.label}: {WINDOW_PERIODS} periods of its dominant line, "
                     f"{dominant * e.frequency_hz:.3g} Hz", fontsize=8)
        ax.set_xlabel("time in the period [s]", fontsize=7)
    ax.set_ylabel(_label(out, units), fontsize=7)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    return broadband


def _broadband(e: ExperimentFit) -> bool:
    return bool(e.inputs) and excited_lines(_first(e.inputs)).size >= MULTISINE_LINES


def _first(inputs: dict[str, np.ndarray]) -> np.ndarray:
    return next(iter(inputs.values()))


def _label(column: str, units: dict[str, str]) -> str:
    """A column's name and unit: the declared unit where known, else from the column name."""
    unit = units.get(column)
    if unit is None:
        return axis_label(column)
    name = column[:-len(unit) - 1] if column.endswith("_" + unit) else column
    return f"{name.replace('_', ' ')} [{unit}]"


def _frf_figure(result: FitResult, out: str, exps: list[ExperimentFit], path: Path) -> Path:
    """Frequency response, output over the (first) input, of measured and model at each
    record's excited lines: amplitude (log scale, with the misfit's) and phase.  One
    period of a many-line multisine in time shows nothing; its lines show where the
    model departs, and over the input they no longer carry its random phases."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MultipleLocator

    cols = min(3, len(exps))
    rows = 2 * int(np.ceil(len(exps) / cols))  # amplitude above phase
    fig, axes = plt.subplots(rows, cols, figsize=(4.8 * cols, 2.8 * rows), squeeze=False)
    column = next(iter(exps[0].inputs))
    out_name, in_name = _label(out, result.units), _label(column, result.units)
    out_unit, in_unit = (result.units.get(c) or axis_label(c).rpartition("[")[2].rstrip("]") for c in (out, column))
    for j in range(len(exps), rows // 2 * cols):  # spare cells of the last row pair
        g, c = divmod(j, cols)
        axes[2 * g, c].axis("off")
        axes[2 * g + 1, c].axis("off")
    for j, e in enumerate(exps):
        g, c = divmod(j, cols)
        u = np.fft.rfft(_first(e.inputs))
        lines = excited_lines(_first(e.inputs))
        f = lines * e.frequency_hz
        measured, predicted = (np.fft.rfft(x)[lines] / u[lines] for x in (e.measured[out], e.predicted[out]))
        amp, ph = axes[2 * g, c], axes[2 * g + 1, c]
        amp.semilogy(f, np.abs(measured), ".", ms=3, label="measured")
        amp.semilogy(f, np.abs(predicted), "-", lw=1, label="model")
        amp.semilogy(f, np.abs(measured - predicted), "x", ms=2.5, color="#c03030", label="measured − model")
        # The model's phase unwrapped along the lines, the measured one as its offset from
        # it: a measured line just across ±180° from the model stays beside it.
        model_phase = np.unwrap(np.angle(predicted))
        ph.plot(f, np.degrees(model_phase + np.angle(measured / predicted)), ".", ms=3, label="measured")
        ph.plot(f, np.degrees(model_phase), "-", lw=1, label="model")
        amp.set_title(f"{e.label}: {lines.size} excited lines, {f[0]:g}–{f[-1]:g} Hz", fontsize=8)
        amp.set_ylabel(f"|{out.split('_')[0]} / {column.split('_')[0]}| [{out_unit}/{in_unit}]", fontsize=8)
        ph.set_ylabel("phase [°]", fontsize=8)
        ph.yaxis.set_major_locator(MultipleLocator(90))
        ph.set_xlabel("frequency [Hz]", fontsize=8)
        for ax in (amp, ph):
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{result.model}: frequency response\n{out_name} / {in_name} at the excited lines", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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


def drop_figure(pred, measured, title: str, path: Path) -> Path:
    """The virtual drop test (:class:`identify.drop.DropPrediction`): force, stroke and
    pressure against time, each with its 2σ band (fit and model discrepancy), the
    measured drop (:class:`identify.drop.MeasuredDrop`) over it when there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("force [kN]", pred.force_N, pred.force_std, 1e-3, measured.force_N if measured else None),
              ("stroke [mm]", pred.stroke_m, pred.stroke_std, 1e3, measured.stroke_m if measured else None),
              ("gas pressure [bar]", pred.pressure_Pa, pred.pressure_std, 1e-5,
               measured.pressure_Pa if measured else None)]
    fig, axes = plt.subplots(3, 1, figsize=(7, 7.5), sharex=True)
    for ax, (label, y, std, scale, meas) in zip(axes, panels, strict=True):
        ax.fill_between(pred.t, (y - 2 * std) * scale, (y + 2 * std) * scale, color="C0", alpha=0.25, lw=0,
                        label="predicted ± 2σ (fit and model discrepancy)")
        ax.plot(pred.t, y * scale, color="C0", lw=1.2, label="predicted")
        if meas is not None:
            ax.plot(measured.t, meas * scale, color="k", lw=0.8, ls="--", label="measured")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time from contact [s]")
    axes[0].legend(fontsize=8, loc="upper right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
