"""The simulator honours every parameter of its truth, or refuses the truth in one line.

Random truths around the nominal damper go through the offline generator and a fit of
the parameters that carry the physics; a parameter the simulator dropped or bent
(as it once did the stroke offset θ12) would show as an estimate many σ off."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from identify.dataset import read_dataset
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import STANDARD_SET, select
from identify.preparation import model_columns, resolve_outputs
from identify.transient import drop_test as model_drop_test
from simulator.daq import FRAME_DTYPE, TcpPort
from simulator.engine import VirtualRig
from simulator.generate import generate
from simulator.physics import Damper, TruthError, drop_test
from simulator.sensors import DATASHEET_CHANNELS

# Arbitrary fixed seeds (numpy's generators seeded 0, 1, 2, … draw near-equal values at
# some positions of their streams, which would make the truths less varied than they look).
SEEDS = (1635480374, 734572160, 996452236, 158449208, 256974511, 822537139, 379344257, 1449404774,
         715195577, 180937901, 2059356255, 1559949469)
# Middle and low experiments at 2 and 0.5 Hz: for every truth within ±20 % they stay
# inside the actuator's velocity limit, the 65 bar pressure channel (the high group
# compresses the gas to within a few percent of zero volume when θ6 is 20 % steeper)
# and the stroke channel, and the 0.5 Hz pair makes the heat transfer θ16 identifiable.
EXPERIMENTS = ["h", "l", "j"]
# What each model's physics hinges on; the 1-dof gas is polytropic (exponent θ7), so
# θ15 and θ16 do not occur in it.
ESTIMATE = {"2dof": ["theta4", "theta6", "theta16"], "1dof": ["theta4", "theta6", "theta7"]}


def random_truth(model: str, seed: int) -> dict[str, float]:
    """Every parameter drawn around nominal, as far as that makes physical sense."""
    rng = np.random.default_rng(seed)
    theta = {}
    for p in Parameters(load_model(model)):
        if p.name in ("theta13", "theta14"):
            value = 0.0                                                # in no model
        elif p.name == "theta12":
            value = rng.choice([-1.0, 1.0]) * rng.uniform(0.5e-3, 2e-3)  # nominal 0: a transducer zero off by mm
        elif p.name == "theta2":
            # Gravity is not a damper property: ±20 % of g does not exist on earth.  Local g
            # spans 9.78…9.83 m/s²; the sign is the mounting (models.md: sign = orientation).
            value = rng.choice([-1.0, 1.0]) * rng.uniform(9.78, 9.83)
        elif p.name == "theta17":
            # ±20 % of −293.15 K would be a lab at −32 … +86 °C; a test hall is 5 … 40 °C.
            value = -(273.15 + rng.uniform(5.0, 40.0))
        else:
            value = p.nominal * rng.uniform(0.8, 1.2)
        theta[p.name] = float(value)
    return theta


@pytest.mark.slow
@pytest.mark.parametrize("model, seed", [("2dof", s) for s in SEEDS] + [("1dof", s) for s in SEEDS[:6]])
def test_a_random_truth_is_recovered_within_3_sigma(model, seed, tmp_path):
    truth = random_truth(model, seed)
    out = generate(tmp_path / "data", select(STANDARD_SET, EXPERIMENTS), Damper(truth, model), periods=3,
                   rate_hz=2000.0, seed=seed % 10_000)
    manifest = json.loads((out / "dataset.json").read_text())
    assert not any("over_range_samples" in e for e in manifest["experiments"])   # clipped data prove nothing
    assert json.loads((out / "truth.json").read_text())["parameters"] == truth

    compiled = load_model(model)
    columns = model_columns(compiled, resolve_outputs(compiled, None))
    start = Parameters(compiled, truth)
    estimate = ESTIMATE[model]
    for k in estimate:                  # the truth is up to 20 % away from where the fit starts
        start[k].value = start[k].nominal
    result = fit_experiments(compiled, read_dataset(out, columns).experiments, start, estimate)
    assert result.converged, result.message
    z = {k: (result.value(k) - truth[k]) / result.std[k] for k in estimate}
    assert all(abs(v) < 3 for v in z.values()), (z, truth)


@pytest.mark.parametrize("model", ["2dof", "1dof"])
def test_the_drop_test_matches_the_declared_model_with_a_stroke_offset(model):
    truth = random_truth(model, SEEDS[0])
    t = np.linspace(0.0, 5.0, 501)
    sim = drop_test(Damper(truth, model), 350.0, 0.0, t)
    compiled = load_model(model)
    predicted = model_drop_test(compiled, Parameters(compiled, truth).vector(), 350.0, 0.0, t)
    stroke = predicted.outputs[compiled.output_names.index("stroke_mm")]
    assert sim.stroke[0] == pytest.approx(truth["theta12"], abs=1e-12)   # released at q = 0
    assert np.max(np.abs(sim.stroke - stroke)) < 2e-5                     # m: integration tolerances
    pressure = predicted.outputs[compiled.output_names.index("pressure_bar")]
    assert np.max(np.abs(sim.pressure - pressure) / pressure) < 1e-3


def test_the_controller_holds_and_the_daq_reads_the_measured_stroke_the_gas_sees_q():
    truth = random_truth("2dof", SEEDS[1])
    offset, static_m = truth["theta12"], 0.133
    damper = Damper(truth)
    rig = VirtualRig(damper, TcpPort(), seed=1, modbus_port=0, speed=50)   # speed sizes the DAQ FIFO
    c = rig.controller
    c.write_coils(0, [True])
    c.write_holding(2, [round(static_m * 1e5)])
    c.write_holding(0, [1])                                                 # STATIC
    rig.step_to(8.0)
    rig.daq.rate_hz = 2000
    rig.daq._handle("START")
    rig.step_to(rig.t + 0.5)
    counts = np.frombuffer(bytes(rig.daq._out[3:]), dtype=FRAME_DTYPE)["counts"].astype(float)
    rig.daq.port.close()
    stroke_mm, _, pressure_bar, temperature_c = (ch.offset + ch.gain * counts[:, i].mean()
                                                 for i, ch in enumerate(DATASHEET_CHANNELS))
    assert c.position_m == pytest.approx(static_m, abs=1e-6)
    assert stroke_mm * 1e-3 == pytest.approx(static_m, abs=2e-6)            # noise 10 µm / √1000
    p_at_q = damper.pressure(static_m - offset, temperature_c + 273.15)
    p_at_measured = damper.pressure(static_m, temperature_c + 273.15)
    assert pressure_bar * 1e5 == pytest.approx(p_at_q, abs=50.0)            # Pa: 5 σ of the mean of 1000 samples
    assert abs(p_at_q - p_at_measured) > 3000.0                             # θ12 is visible in the pressure


@pytest.mark.parametrize("theta, message", [
    ({"theta13": 0.1}, "theta13 = 0.1: no damper model uses it"),
    ({"theta14": -2.0}, "theta14 = -2: no damper model uses it"),
    ({"theta99": 1.0}, "unknown parameter(s) theta99"),
    ({"theta17": 10.0}, "theta17 = 10: minus the ambient temperature must be negative"),
    ({"theta16": 0.0}, "theta16 = 0: the wall heat transfer must be positive"),
    ({"theta1": -20.0}, "theta1 = -20: the moving mass must be positive"),
    ({"theta4": float("nan")}, "theta4 = nan: not a finite number"),
])
def test_a_truth_the_simulator_cannot_represent_is_refused(theta, message):
    nominal = Parameters(load_model("2dof")).as_dict()
    with pytest.raises(TruthError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Damper(nominal | theta)


def test_the_1dof_truth_needs_no_thermal_parameters_but_all_others():
    nominal = Parameters(load_model("1dof")).as_dict()
    Damper(nominal | {"theta15": 0.0, "theta16": 0.0}, "1dof")             # not in the polytropic model
    with pytest.raises(TruthError, match="no value for theta12"):
        Damper({k: v for k, v in nominal.items() if k != "theta12"}, "1dof")


BAD_TRUTHS = {
    "malformed": ('{"model": "2dof", "parameters": {"theta4": 0.005,', "not valid JSON"),
    "unknown": ('{"model": "2dof", "parameters": {"stroke_offset": 0.001, "theta18": 1}}',
                "unknown parameter 'theta18'"),
    "refused": ('{"model": "2dof", "parameters": {"theta13": 0.5}}', "theta13 = 0.5: no damper model uses it"),
}


# Both commands read the truth through load_truth; serve is run for one kind only, as
# every start of the interpreter costs seconds here (scipy).
@pytest.mark.parametrize("command, kind", [("generate", "malformed"), ("generate", "unknown"),
                                           ("generate", "refused"), ("serve", "refused")])
def test_the_cli_refuses_a_bad_truth_file_in_one_line_with_status_2(command, kind, tmp_path):
    content, message = BAD_TRUTHS[kind]
    truth = tmp_path / "TRUTH.json"
    truth.write_text(content)
    where = (["--out", str(tmp_path / "out")] if command == "generate"
             else ["--modbus", "127.0.0.1:0", "--daq", "tcp://127.0.0.1:0"])
    proc = subprocess.run([sys.executable, "-m", "simulator", command, "--params", str(truth), *where],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"error: {truth}: "), proc.stderr
    assert message in proc.stderr and proc.stdout == ""
    assert not (tmp_path / "out").exists()
