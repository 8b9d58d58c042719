"""The plant truth recorded from RUN on (issue 36): ``simulator generate --physics plant
--capture transient`` runs a plan as a rig that does not wait runs it, and a transient
fit of the identification model takes the record."""

from __future__ import annotations

import json

import numpy as np
import pytest

from identify.dataset import read_dataset
from identify.plans import ExperimentSpec
from simulator.generate import generate
from simulator.plant import load_plant

A = ExperimentSpec("a", "qc", 14.0, 20.0, 4.0, periods=8)
B = ExperimentSpec("b", "qc", 133.0, 10.0, 2.0, periods=4)


def test_the_plant_records_from_run_with_the_ramp_and_the_heating_in_it(tmp_path):
    out = generate(tmp_path / "d", [A, B], load_plant(), periods=None, seed=3, capture="transient", ramp_s=1.0,
                   noise_scale=0.0)
    manifest = json.loads((out / "dataset.json").read_text())
    assert [e["capture"] for e in manifest["experiments"]] == ["transient", "transient"]
    assert manifest["source"]["physics"] == "plant"
    a, b = read_dataset(out).experiments
    for exp, spec in ((a, A), (b, B)):
        t, stroke = exp.data["time_s"].to_numpy(), exp.data["stroke_mm"].to_numpy()
        assert t[0] == 0.0 and t[-1] == pytest.approx(spec.periods / spec.frequency_hz, abs=1e-3)
        # RUN at the static position, the amplitude still ramping in the first period
        assert stroke[0] == pytest.approx(spec.static_position_mm, abs=0.05)
        first = np.ptp(stroke[t < 1 / spec.frequency_hz])
        last = np.ptp(stroke[t > t[-1] - 1 / spec.frequency_hz])
        assert first < 0.8 * last and last == pytest.approx(2 * spec.amplitude_mm, rel=0.1)
    # nothing waited out: the gas still warming over a's record
    temp = a.data["gas_temperature_C"].to_numpy()
    assert temp[-200:].mean() - temp[:200].mean() > 0.1


def test_the_second_experiment_starts_from_what_the_first_left(tmp_path):
    """The plant's states carry from one experiment to the next (wall heat, dissolved
    gas): b after a starts otherwise than b after a gentle cycle at a's position."""
    gentle = ExperimentSpec("a", "qc", 14.0, 2.0, 4.0, periods=8)
    temps = []
    for first in (A, gentle):
        out = generate(tmp_path / f"{first.amplitude_mm:g}", [first, B], load_plant(), periods=None,
                       capture="transient", noise_scale=0.0)
        temps.append(read_dataset(out).experiments[1].data["gas_temperature_C"].iloc[0])
    assert abs(temps[0] - temps[1]) > 0.05


def test_a_plant_plan_half_captured_from_run_is_refused(tmp_path):
    mixed = [A, ExperimentSpec("b", "qc", 133.0, 10.0, 2.0, periods=4, capture="transient")]
    with pytest.raises(ValueError, match="all from RUN on or all in steady state"):
        generate(tmp_path / "m", mixed, load_plant(), periods=None)
