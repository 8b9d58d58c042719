"""From dataset experiments to estimator problems: folded, converted to SI, weighted."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identify.dataset import DatasetError, Experiment
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
        if not self.fixed:
            return theta
        out = theta.copy()
        out[list(self.fixed)] = list(self.fixed.values())
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
        folded = fold(exp.label, exp.time_s, cols, exp.frequency_hz, n)
        inputs = np.vstack([ch.to_si(folded.values[ch.column]) for ch in d.inputs.values()])
        measured = np.array([d.outputs[o].to_si(folded.values[d.outputs[o].column]) for o in outputs]).reshape(-1, n)
        yvar = np.array([(folded.noise_std[d.outputs[o].column] * d.outputs[o].scale) ** 2 for o in outputs])
        uvar = np.array([(folded.noise_std[ch.column] * ch.scale) ** 2 for ch in d.inputs.values()])
        prepared.append(PeriodicData(exp.label, exp.frequency_hz, inputs, measured, yvar, uvar, folded))
    return prepared
