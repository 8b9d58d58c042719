"""From dataset experiments to estimator problems: folded, converted to SI, weighted."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identify.dataset import DatasetError, Experiment
from identify.differentiation import BDF2_D1
from identify.errors import InputError
from identify.folding import FoldedRecord, fold
from identify.model import CompiledModel


@dataclass
class PeriodicData:
    """One periodic experiment on the grid, ready for the estimator (SI units)."""

    label: str
    frequency_hz: float
    inputs: np.ndarray  # (n_inputs, n)
    measured: np.ndarray  # (n_outputs, n) for the fitted outputs
    noise_variance: np.ndarray  # (n_outputs,) measurement noise variance of one sample, SI (nan: unknown)
    input_noise_variance: np.ndarray  # (n_inputs,) likewise for the inputs
    folded: FoldedRecord  # its fold operator gives the noise covariance on the grid
    fixed: dict[int, float] = field(default_factory=dict)  # per-experiment parameter values (e.g. friction)

    @property
    def grid_variance(self) -> np.ndarray:
        """(n_outputs,) mean noise variance of one grid value, SI."""
        return self.noise_variance * self.folded.grid_factor

    def noise_estimable(self) -> bool:
        return bool(np.all(np.isfinite(self.noise_variance)) and np.all(np.isfinite(self.input_noise_variance)))

    def theta(self, theta: np.ndarray) -> np.ndarray:
        """The shared parameter vector with this experiment's own fixed values."""
        return with_fixed(theta, self.fixed)


def with_fixed(theta: np.ndarray, fixed: dict[int, float]) -> np.ndarray:
    """The shared parameter vector with a record's own fixed values in place (a copy where
    there are any): one set of parameters for every record, some held per record."""
    if not fixed:
        return theta
    out = theta.copy()
    out[list(fixed)] = list(fixed.values())
    return out


def model_columns(model: CompiledModel, outputs: list[str]) -> list[str]:
    """Dataset columns a fit needs: the model's input columns and the fitted outputs."""
    d = model.declaration
    return [ch.column for ch in d.inputs.values()] + [d.outputs[o].column for o in outputs]


def resolve_outputs(model: CompiledModel, requested: list[str] | None) -> list[str]:
    outputs = list(requested) if requested else list(model.declaration.default_outputs)
    for o in outputs:
        model.output_index(o)
    if set(outputs) & {ch.column for ch in model.declaration.inputs.values()}:
        raise InputError(f"an output of the fit is also the model's input: {outputs}")
    return outputs


def prepare_periodic(model: CompiledModel, experiments: list[Experiment], n: int,
                     outputs: list[str]) -> list[PeriodicData]:
    """Fold each periodic experiment's input and output columns onto the n-point grid."""
    d = model.declaration
    prepared = []
    for exp in experiments:
        if exp.kind != "periodic":
            raise DatasetError(f"experiment {exp.label!r} is a {exp.kind} record; the fit takes periodic records")
        assert exp.data is not None
        cols = {}
        for ch in list(d.inputs.values()) + [d.outputs[o] for o in outputs]:
            if ch.column not in exp.data.columns:
                raise DatasetError(f"{exp.file}: column {ch.column!r}: missing (model {model.name!r} needs it)")
            cols[ch.column] = exp.column(ch.column)
        folded = fold(exp.label, exp.time_s, cols, exp.frequency_hz, n, exp.sample_rate_hz)
        inputs = model.expand_inputs(np.vstack([ch.to_si(folded.values[ch.column]) for ch in d.inputs.values()]),
                                     exp.frequency_hz)
        measured = np.array([d.outputs[o].to_si(folded.values[d.outputs[o].column]) for o in outputs]).reshape(-1, n)
        yvar = np.array([(folded.noise_std[d.outputs[o].column] * d.outputs[o].scale) ** 2 for o in outputs])
        uvar = np.array([(folded.noise_std[ch.column] * ch.scale) ** 2 for ch in d.inputs.values()])
        prepared.append(PeriodicData(exp.label, exp.frequency_hz, inputs, measured, yvar, uvar, folded))
    return prepared


SIGNAL_MARGIN = 1.25  # grid points per period: at least 2·margin·(highest harmonic with signal)
SIGNAL_THRESHOLD = 5.0  # a harmonic has signal where its amplitude exceeds this many noise standard deviations
# Below this fraction of a column's largest harmonic (−80 dB) a noiseless column (a
# commanded force) holds only rounding and folding error: 9 digits of time_s put
# harmonics at 1e-6 of the largest up to the Nyquist line.
RELATIVE_FLOOR = 1e-4
# Records with a whole number of samples per period up to this many times the points
# needed are fitted on their own samples: folding two or three samples into a bin
# averages them, a low-pass filter that biased a broadband Bouc-Wen fit by 10 σ.
OWN_SAMPLES_FACTOR = 4


def _fold_own(exp: Experiment, columns: list[str]) -> tuple[FoldedRecord, int, bool]:
    """One record folded onto its own samples per period where they are whole (else the
    power of two above): the folded record, its size, and whether they were whole."""
    per_period = exp.sample_rate_hz / exp.frequency_hz
    samples = int(round(per_period))
    whole = abs(per_period - samples) < 1e-6 * per_period
    size = samples if whole else 1 << int(np.ceil(np.log2(per_period)))
    return fold(exp.label, exp.time_s, {c: exp.column(c) for c in columns}, exp.frequency_hz, size,
                exp.sample_rate_hz), size, whole


def fewest_samples(experiments: list[Experiment]) -> tuple[float, str]:
    """The fewest samples per period of any record, and that record's label."""
    return min(((exp.sample_rate_hz / exp.frequency_hz, exp.label) for exp in experiments), key=lambda p: p[0])


def choose_points(model: CompiledModel, experiments: list[Experiment], outputs: list[str]) -> tuple[int, str]:
    """Grid points per period for the spectral scheme, from the data, and a sentence
    saying why: the smallest power of two with SIGNAL_MARGIN to spare above twice the
    highest harmonic that stands out of its column's noise, or the records' own samples
    per period where they are whole and not many more (every record the same).  Never
    more points than a record has samples per period: such a grid only interpolates
    between the samples (a level whose content reached near the Nyquist line got twice
    the points of its sibling levels)."""
    d = model.declaration
    columns = [ch.column for ch in d.inputs.values()] + [d.outputs[o].column for o in outputs]
    best, why, sizes = 0, "", set()
    fewest, fewest_label = fewest_samples(experiments)
    finest = int(np.floor(fewest + 1e-6 * fewest))  # a grid point per sample at most, never between them
    for exp in experiments:
        folded, size, whole = _fold_own(exp, columns)
        sizes.add(size if whole else 0)
        for c in columns:
            spectrum = np.abs(np.fft.rfft(folded.values[c] - folded.values[c].mean()))
            noise = folded.noise_std[c] ** 2 * folded.grid_factor
            floor = max(SIGNAL_THRESHOLD * np.sqrt(size * noise) if np.isfinite(noise) else 0.0,
                        RELATIVE_FLOOR * spectrum.max())
            above = np.flatnonzero(spectrum > floor)
            if above.size and above[-1] > best:
                best, why = int(above[-1]), f"{c} of {exp.label}"
    needed = max(64, 1 << int(np.ceil(np.log2(2 * SIGNAL_MARGIN * max(best, 1)))))
    own = sizes.pop() if len(sizes) == 1 else 0
    if own and needed <= own <= OWN_SAMPLES_FACTOR * needed:
        return own, (f"n = {own}, the records' samples per period (the highest harmonic with signal is {best}, "
                     f"in {why}: {needed} points would resolve it)")
    if needed > finest:
        whose = ("the records' samples per period" if own else
                 f"the fewest samples per period of the records ({fewest:.1f}, in {fewest_label})")
        return finest, (f"n = {finest}, {whose}: 2 x {SIGNAL_MARGIN:g} x the highest "
                        f"harmonic with signal ({best}, in {why}) would ask for {needed}, more points than were "
                        f"sampled")
    return needed, (f"n = {needed}, the power of two above 2 x {SIGNAL_MARGIN:g} x the highest harmonic with signal "
                    f"({best}, in {why})")


def excitation(model: CompiledModel, experiments: list[Experiment]) -> tuple[int, int, str]:
    """The most excited lines of any record's inputs (:func:`excited_lines`), its highest
    excited harmonic and its label: what says whether a record is broadband."""
    columns = [ch.column for ch in model.declaration.inputs.values()]
    most = (0, 0, "")
    for exp in experiments:
        folded, _, _ = _fold_own(exp, columns)
        lines = excited_lines(np.array([folded.values[c] for c in columns]))
        if lines.size and (lines.size, int(lines[-1])) > most[:2]:
            most = (int(lines.size), int(lines[-1]), exp.label)
    return most


def bdf2_error(harmonic: int, n: int) -> float:
    """Relative error of the bdf2 first derivative at a harmonic of the period on n points."""
    z = np.exp(-2j * np.pi * harmonic / n * np.arange(BDF2_D1.size))
    return float(abs((BDF2_D1 @ z) * n / (2j * np.pi * harmonic) - 1))


EXCITED_FRACTION = 0.1  # a line of the input within 20 dB of its strongest is excited
MULTISINE_LINES = 4  # a record exciting at least this many lines is broadband (a multisine), not a sine
# Relative error of bdf2's derivative at the highest excited line above which bdf2 does
# not resolve the record (a 1-mode fit on 800 points put a 7.3 Hz resonance at 9.4 Hz).
BDF2_ERROR = 0.01


def excited_lines(inputs: np.ndarray) -> np.ndarray:
    """Harmonics (indices of one period's rfft, DC excluded) where some input
    ((n_inputs,) n) is within EXCITED_FRACTION of its strongest line."""
    amplitude = np.abs(np.fft.rfft(np.atleast_2d(inputs), axis=-1))[:, 1:]
    return 1 + np.flatnonzero(np.any(amplitude >= EXCITED_FRACTION * amplitude.max(axis=1, keepdims=True), axis=0))
