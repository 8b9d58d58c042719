"""Monte-Carlo check of the reported standard deviations (used by the slow test and by
``benchmarks/bench_sigma.py``).

One case is a generator, a set of experiments, a sample rate and a record length; each
seed is one noise realisation of it, written in the dataset format and fitted from a
start 15–40 % off (examples/start-2dof.json) as ``identify fit`` would.  Over the seeds,
the spread of the estimates divided by the mean reported σ should be 1, and ±2σ should
cover the truth about 95 % of the time.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from identify.dataset import read_dataset
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import STANDARD_SET, ExperimentSpec, select
from identify.preparation import model_columns, resolve_outputs
from tests import independent_generator

ESTIMATE = ("theta4", "theta6", "theta16")
TRUTH = np.array([independent_generator.NOMINAL[k] for k in ESTIMATE])
START = json.loads((Path(__file__).resolve().parents[1] / "examples" / "start-2dof.json").read_text())["parameters"]
GENERATORS = ("independent", "simulator")


@dataclass(frozen=True)
class Case:
    generator: str  # "independent" (tests/independent_generator.py) or "simulator" (simulator.generate)
    rate_hz: float
    periods: int
    letters: tuple[str, ...] | None = None  # experiments of the standard set; None: all 14

    @property
    def specs(self) -> list[ExperimentSpec]:
        return select(STANDARD_SET, list(self.letters) if self.letters else None)

    def describe(self) -> str:
        which = ",".join(self.letters) if self.letters else "standard set"
        return f"{self.generator}, {which}, {self.rate_hz:g} samples/s, {self.periods} periods"


@dataclass
class Summary:
    seeds: int
    spread_over_sigma: np.ndarray  # (3,) std of the estimates / mean reported σ
    coverage: np.ndarray  # (3,) fraction of ±2σ intervals that hold the truth
    bias_over_se: np.ndarray  # (3,) (mean − truth) / standard error of the mean
    converged: int


def warm(case: Case) -> None:
    """Compute the independent generator's noise-free signals once (before worker
    processes fork, so that they inherit them)."""
    if case.generator == "independent":
        for spec in case.specs:
            independent_generator.clean_signals(spec, float(case.rate_hz), float(case.periods))


def _generate(case: Case, seed: int, out: Path) -> None:
    if case.generator == "independent":
        independent_generator.generate_dataset(out, case.specs, rate_hz=case.rate_hz, periods=case.periods,
                                               seed=seed)
    elif case.generator == "simulator":
        from simulator.generate import generate
        from simulator.truth import load_truth

        generate(out, case.specs, load_truth(), periods=case.periods, rate_hz=case.rate_hz, seed=seed)
    else:
        raise ValueError(f"unknown generator {case.generator!r} ({', '.join(GENERATORS)})")


def fit_seed(case: Case, seed: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """Estimates, reported σ and convergence of θ4, θ6, θ16 for one noise realisation."""
    model = load_model("2dof")
    columns = model_columns(model, resolve_outputs(model, None))
    with tempfile.TemporaryDirectory(prefix="sigma-") as tmp:
        _generate(case, seed, Path(tmp))
        experiments = read_dataset(tmp, columns).experiments
    result = fit_experiments(model, experiments, Parameters(model, START), list(ESTIMATE))
    return (np.array([result.value(k) for k in ESTIMATE]), np.array([result.std[k] for k in ESTIMATE]),
            result.converged)


def summarise(values: np.ndarray, stds: np.ndarray, converged: int) -> Summary:
    """(seeds, 3) estimates and reported σ -> the calibration figures."""
    n = len(values)
    spread = np.std(values, axis=0, ddof=1)
    return Summary(n, spread / np.mean(stds, axis=0), np.mean(np.abs(values - TRUTH) <= 2 * stds, axis=0),
                   (np.mean(values, axis=0) - TRUTH) / (spread / np.sqrt(n)), converged)
