"""Offline generator: a dataset in the interchange format from the simulated rig,
without the protocol loop (steady states of a plan, optionally the drop test), in either
physics tier: the model's periodic steady states, or the plant truth run through the
plan in order (:mod:`simulator.plant.sequence`)."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from identify.dataset import FORMAT, csv_bytes, write_manifest
from identify.files import atomic_write_bytes
from identify.plans import ExperimentSpec
from simulator.physics import Actuator, Damper, SteadyState, drop_test, periodic_steady_state, run_from_rest
from simulator.plant.damper import PlantDamper
from simulator.plant.drop import DROP_VELOCITY_M_S, simulate_drop
from simulator.plant.sequence import run_plan, run_plan_from_run
from simulator.sensors import SensorSet
from simulator.truth import truth_document

SETTLE_S = 60.0  # simulated time from RUN to the first captured sample (ramp + settling)
CAPTURES = ("steady", "transient")
RAMP_S = 2.0  # the controller's default ramp time (ramp_time 20 x 0.1 s), for records captured from RUN
DROP_MASS_KG = 350.0
DROP_DURATION_S = 40.0


def _record(state: SteadyState, sensors: SensorSet, with_temperature: bool) -> tuple[dict[str, np.ndarray], int]:
    si = np.vstack([state.stroke, state.axle_force, state.pressure, state.temperature])
    return _digitise(state.t, si, sensors, with_temperature)


def _digitise(t: np.ndarray, si: np.ndarray, sensors: SensorSet,
              with_temperature: bool) -> tuple[dict[str, np.ndarray], int]:
    counts, over = sensors.counts(si, t)
    eng = sensors.engineering(counts)
    cols = {"time_s": t}
    for i, ch in enumerate(sensors.channels):
        if ch.name == "gas_temperature_C" and not with_temperature:
            continue
        cols[ch.name] = eng[i]
    return cols, int(over.sum())


def generate(out: str | Path, plan: list[ExperimentSpec], damper: Damper | PlantDamper, *, periods: int | None = 3,
             rate_hz: float = 2000.0, seed: int = 0, drop: bool = False, date: str | None = None,
             actuator: Actuator | None = None, noise_scale: float = 1.0, name: str | None = None,
             serial: str = "SIM-0001", capture: str = "steady", ramp_s: float = RAMP_S,
             drop_velocity_m_s: float = DROP_VELOCITY_M_S,
             gain_error: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)) -> Path:
    """Write the dataset folder ``out`` and return its path.

    Labels are ``date + letter`` as in the paper; ``truth.json`` beside the manifest
    holds the simulated parameters (the plant: its constants) for round-trip checks.
    ``periods`` None captures each experiment's own number of periods.  ``gain_error``:
    each transducer's relative gain error (the ``gain`` fault of a served rig).  A
    :class:`PlantDamper` runs the plan in order, the wall's heat and the dissolved gas
    carried from one experiment to the next.  ``capture`` "transient" records each
    experiment from RUN on: the model started at rest at its static position with the
    gas at ambient temperature, the plant after its move there, carrying what the
    experiments before left (:func:`simulator.plant.sequence.run_plan_from_run`), the
    amplitude ramped over ``ramp_s`` (dataset key ``capture``: "transient"); "steady"
    records its periodic steady state.  The plant runs a plan all one way or the other.
    ``drop_velocity_m_s``: the drop's velocity at touchdown (q = 0; default the paper's
    landing, about 0.5 m/s).
    """
    if capture not in CAPTURES:
        raise ValueError(f"unknown capture {capture!r} (steady or transient)")
    transient = [capture == "transient" or spec.capture == "transient" for spec in plan]
    if isinstance(damper, PlantDamper) and any(transient) and not all(transient):
        raise ValueError("the plant runs a plan captured either all from RUN on or all in steady state")
    out = Path(out)
    actuator = actuator or Actuator()
    date = date or _dt.date.today().strftime("%y%m%d")
    entries = []
    times = []
    for spec in plan:
        k_periods = spec.periods if periods is None else periods
        k = int(np.ceil(k_periods * rate_hz / spec.frequency_hz))
        times.append(SETTLE_S + np.arange(k) / rate_hz)
    plant = None
    if isinstance(damper, PlantDamper):
        plant = (run_plan_from_run(damper, plan, actuator, times, ramp_s) if all(transient)
                 else run_plan(damper, plan, actuator, times, SETTLE_S))
    for i, spec in enumerate(plan):
        sensors = SensorSet(seed=seed * 1000 + i, noise_scale=noise_scale, gain_error=gain_error)
        k_periods = spec.periods if periods is None else periods
        t = times[i]
        if plant is not None:
            cols, over = _digitise(plant[i].t, plant[i].si, sensors, True)
        elif transient[i]:
            assert isinstance(damper, Damper)
            cols, over = _record(run_from_rest(damper, actuator, spec, t - t[0], ramp_s), sensors, True)
        else:
            assert isinstance(damper, Damper)
            cols, over = _record(periodic_steady_state(damper, actuator, spec, t), sensors, True)
        label = f"{date}{spec.letter}"
        atomic_write_bytes(out / f"{label}.csv", csv_bytes(cols))
        entry = {"label": label, "file": f"{label}.csv", **spec.metadata(), "sample_rate_Hz": rate_hz,
                 "periods": k_periods}
        if transient[i]:
            entry.update(capture="transient", ramp_s=ramp_s)
        if over:
            entry["over_range_samples"] = over
        entries.append(entry)
    if drop:
        sensors = SensorSet(seed=seed * 1000 + 999, noise_scale=noise_scale, gain_error=gain_error)
        t = np.arange(int(DROP_DURATION_S * rate_hz)) / rate_hz
        if isinstance(damper, PlantDamper):
            rec = simulate_drop(mass_kg=DROP_MASS_KG, velocity_m_s=drop_velocity_m_s, duration_s=float(t[-1]),
                                rate_hz=rate_hz, constants=damper.k, ambient_k=damper.ambient_k)
            si = np.vstack([rec.stroke_m, rec.force_N, rec.pressure_Pa, rec.temperature_K])
            cols, _ = _digitise(rec.t, si, sensors, True)
        else:
            cols, _ = _record(drop_test(damper, DROP_MASS_KG, drop_velocity_m_s, t), sensors, True)
        label = f"{date}drop"
        atomic_write_bytes(out / f"{label}.csv", csv_bytes(cols))
        entries.append({"label": label, "kind": "drop", "file": f"{label}.csv", "drop_mass_kg": DROP_MASS_KG,
                        "drop_velocity_m_s": drop_velocity_m_s, "sample_rate_Hz": rate_hz})
    manifest = {
        "format": FORMAT,
        "name": name or f"simulated {_tier_name(damper)} damper, {len(plan)}-experiment set",
        "unit": {"serial": serial, "type": "simulated nose landing gear damper"},
        "ambient": {"temperature_K": damper.ambient_k, "pressure_Pa": 101325.0},
        "source": {"generator": "simulator generate", "seed": seed, "model": _tier_name(damper),
                   "physics": "plant" if isinstance(damper, PlantDamper) else "model"},
        "experiments": entries,
    }
    write_manifest(out, manifest)
    doc = plant_document(damper) if isinstance(damper, PlantDamper) else truth_document(damper)
    atomic_write_bytes(out / "truth.json", (json.dumps(doc, indent=2) + "\n").encode())
    return out


def _tier_name(damper: Damper | PlantDamper) -> str:
    return "plant-truth" if isinstance(damper, PlantDamper) else damper.model


def plant_document(plant: PlantDamper) -> dict:
    """truth.json of a plant: its constants (no θ: the plant is not a model's instance)."""
    return {"physics": "plant", "ambient_K": plant.ambient_k, "constants": plant.k.as_dict()}
