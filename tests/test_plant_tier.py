"""The plant tier behind the simulator's public interface: ``simulator generate|serve
--physics plant`` (the model stays the default), production units and faults in both
tiers, and the controller and DAQ unaware of which tier runs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from identify.plans import STANDARD_SET, select
from simulator.cli import main
from simulator.controller import State
from simulator.daq import FRAME_DTYPE, TcpPort
from simulator.engine import VirtualRig
from simulator.faults import FaultLog, parse_fault
from simulator.plant import PlantDamper, load_plant
from simulator.sensors import DATASHEET_CHANNELS
from simulator.truth import load_truth


def test_generate_writes_a_plant_dataset_and_its_constants(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["generate", "--physics", "plant", "--experiments", "j", "--periods", "1", "--out", str(out),
                 "--date", "261126"]) == 0
    assert "plant physics" in capsys.readouterr().out
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["source"]["physics"] == "plant"
    truth = json.loads((out / "truth.json").read_text())
    assert truth["physics"] == "plant" and truth["constants"]["orifice_diameter"] > 0
    data = np.genfromtxt(out / "261126j.csv", delimiter=",", names=True)
    assert len(data) == 1000 and data["time_s"][0] == 60.0
    assert 120 < data["stroke_mm"].min() and data["stroke_mm"].max() < 146
    assert 8 < data["pressure_bar"].mean() < 12          # the gas at 133 mm, warmed by the run
    assert np.ptp(data["force_N"]) > 500


@pytest.mark.parametrize("argv, says", [
    (["--params", "examples/start-2dof.json"], "--params"),
    (["--model", "1dof"], "--model 1dof"),
])
def test_generate_refuses_what_the_plant_cannot_take(tmp_path, capsys, argv, says):
    assert main(["generate", "--physics", "plant", "--out", str(tmp_path / "x"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {says}") and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("physics", ["model", "plant"])
def test_generate_names_the_plan_a_misspelt_one_meant(tmp_path, capsys, physics):
    assert main(["generate", "--physics", physics, "--plan", "standrad", "--out", str(tmp_path / "x")]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == ("error: --plan standrad: no such plan and no such file (did you mean 'standard'?); the plans: "
                    "standard (built in), or the path of a plan TOML file")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("physics", ["model", "plant"])
def test_generate_refuses_a_plan_past_the_end_stops_in_one_line(tmp_path, capsys, physics):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[experiment]]\nlabel = "m"\nstatic_mm = 17\namplitude_mm = 22\nfrequency_Hz = 1\n')
    assert main(["generate", "--physics", physics, "--plan", str(plan), "--out", str(tmp_path / "x")]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (f"error: --plan {plan}: experiment m commands the stroke to -5.0 mm, past the damper's full "
                    "extension at 0.0 mm; nothing generated")
    assert not (tmp_path / "x").exists()


def test_the_end_stops_resist_past_the_stroke_in_both_tiers():
    """Full extension and bottom-out: the plant's stops and the model tier's, the same
    stiff contact, nothing between them; a mass thrown outward from full extension in
    the model tier's drop is caught by the top-out stop."""
    from simulator.physics import drop_test, stop_force
    from simulator.plant.drop import simulate_drop

    plant = load_plant()
    q = np.array([-1e-3, 0.0, 0.15, 0.30, 0.301])
    for force in (plant.stop_force(q), stop_force(q)):
        assert force[0] < -1e6 and force[4] > 1e6 and not force[1:4].any()
    y = plant.rest_state(0.0)[:, None]
    assert plant.forces(q[:1], np.zeros(1), y).damper_force[0] < -1e6
    t = np.linspace(0.0, 0.5, 501)
    thrown = drop_test(load_truth(), 350.0, -0.5, t)   # extending at 0.5 m/s at q = 0
    assert -5e-4 < np.min(thrown.q) < 0 and np.max(thrown.q) > 0.02   # δ = v·√(M/k) = 0.2 mm
    assert -5e-4 < np.min(simulate_drop(velocity_m_s=-0.5, duration_s=0.5).stroke_m) < 0


@pytest.mark.parametrize("argv, velocity", [([], 0.5), (["--drop-velocity", "0"], 0.0)])
def test_the_drop_touches_down_at_the_papers_speed_unless_told(tmp_path, argv, velocity):
    """The paper's drop reaches about 0.5 m/s: by default the mass touches down at that
    speed (released at rest on the extended damper it would peak at a quarter of a m/s)."""
    out = tmp_path / "ds"
    assert main(["generate", "--physics", "plant", "--experiments", "j", "--periods", "1", "--drop", *argv,
                 "--out", str(out), "--date", "261126"]) == 0
    (drop,) = [e for e in json.loads((out / "dataset.json").read_text())["experiments"] if e.get("kind") == "drop"]
    assert drop["drop_velocity_m_s"] == velocity
    stroke = np.genfromtxt(out / "261126drop.csv", delimiter=",", names=True)["stroke_mm"]
    peak_speed = np.max(stroke[20:2000] - stroke[:1980]) / 20 * 2000 / 1e3   # over 10 ms at 2 kHz, mm → m/s
    assert peak_speed == pytest.approx(0.5 if velocity else 0.24, abs=0.03)


def test_a_negative_drop_velocity_is_refused_in_one_line(tmp_path, capsys):
    assert main(["generate", "--drop", "--drop-velocity", "-1", "--out", str(tmp_path / "x")]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == "error: --drop-velocity -1: a touchdown speed, 0 or more m/s"
    assert not (tmp_path / "x").exists()


def test_plant_constants_only_with_the_plant(tmp_path, capsys):
    assert main(["generate", "--plant-constants", "x.toml", "--out", str(tmp_path / "x")]) == 2
    assert "--physics plant" in capsys.readouterr().err


def test_a_bad_constants_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[seal.viscous]\nvalue = 1.0\n")
    assert main(["generate", "--physics", "plant", "--plant-constants", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and err.count("\n") == 1


def run_rig(damper, letter: str, seconds: float, faults: tuple[str, ...] = ()) -> tuple[np.ndarray, VirtualRig]:
    """Engineering samples of ``seconds`` after 8 s of RUN, in-process on the simulated clock."""
    spec = select(STANDARD_SET, [letter])[0]
    rig = VirtualRig(damper, TcpPort(), seed=3, modbus_port=0, speed=50, faults=[parse_fault(f) for f in faults],
                     log=FaultLog(sink=lambda line: None))
    c = rig.controller
    c.write_coils(0, [True])
    c.write_holding(1, [0, int(spec.static_position_mm * 100), int(spec.amplitude_mm * 100),
                        int(round(spec.frequency_hz * 1000)), 20])
    c.write_holding(0, [2])
    rig.step_to(8.0)
    rig.daq.rate_hz = 1000
    rig.daq._handle("START")
    rig.step_to(rig.t + seconds)
    frames = np.frombuffer(bytes(rig.daq._out[3:]), dtype=FRAME_DTYPE)
    rig.daq.port.close()
    counts = frames["counts"].astype(float)
    return np.array([ch.offset + ch.gain * counts[:, i] for i, ch in enumerate(DATASHEET_CHANNELS)]).T, rig


def test_the_served_plant_streams_the_four_channels():
    eng, rig = run_rig(load_plant(), "n", 2.0)
    assert len(eng) == pytest.approx(2000, abs=3)
    stroke, force, pressure, temp = eng.T
    assert stroke.min() > 3 and stroke.max() < 25
    assert 5.9 < pressure.min() and pressure.max() < 7.5
    assert 19 < temp.mean() < 22
    assert rig.controller.state == State.RUNNING


@pytest.mark.parametrize("tier", ["model", "plant"])
def test_an_estop_fault_stops_either_tier_the_same_way(tier):
    damper = load_plant() if tier == "plant" else load_truth()
    _, rig = run_rig(damper, "n", 1.0, faults=("estop@8.5",))
    assert rig.controller.state == State.ALARM and not rig.controller.hydraulics_on
    assert any("emergency stop" in m for _, m in rig.log.entries)


@pytest.mark.parametrize("tier", ["model", "plant"])
def test_a_worn_orifice_unit_damps_less_in_either_tier(tier):
    """Experiment j's force loop: its area (the energy dissipated per cycle) falls for a
    worn orifice, in both tiers, with the same unit seeds."""
    def dissipated(unit: str) -> float:
        damper = load_plant(unit, 7) if tier == "plant" else load_truth(None, "2dof", unit, 7)
        eng, _ = run_rig(damper, "j", 1.0)
        q, f = eng[:, 0] * 1e-3, eng[:, 1]
        return float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(q)) / 2)
    assert dissipated("worn-orifice") < 0.97 * dissipated("good")


def test_the_drop_rig_releases_the_mass_in_the_plant_tier():
    rig = VirtualRig(load_plant(), TcpPort(), seed=1, modbus_port=0, speed=50, rig_type="drop",
                     log=FaultLog(sink=lambda line: None))
    assert isinstance(rig.damper, PlantDamper)
    c = rig.controller
    rig.daq.rate_hz = 1000
    rig.daq._handle("START")
    c.write_coils(0, [True])
    rig.step_to(1.0)
    c.write_holding(0, [2])
    rig.step_to(3.0)
    frames = np.frombuffer(bytes(rig.daq._out[3:]), dtype=FRAME_DTYPE)
    rig.daq.port.close()
    stroke = frames["counts"][:, 0].astype(float) * DATASHEET_CHANNELS[0].gain + DATASHEET_CHANNELS[0].offset
    assert stroke[:900].max() < 0.1 and stroke.max() > 20


@pytest.mark.slow
def test_a_session_runs_against_the_served_plant(tmp_path):
    """``simulator serve --physics plant`` behind its real interfaces: a scripted session
    captures experiment n and the fit sees model error the model world does not have."""
    import rig
    from rig.testing import VirtualRig as ServedRig

    with ServedRig(speed=10, seed=2, extra_args=["--physics", "plant"]) as sim:
        with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
            session = r.run_plan("standard", experiments=["n"], out=tmp_path / "s", progress=False)
    assert session.status == "complete"
    result = session.identify(model="2dof", estimate=["theta4", "theta6"])
    variance = result.channel_variances["pressure_bar"]
    assert variance ** 0.5 > 3 * DATASHEET_CHANNELS[2].noise_std   # the plant is not the model


def test_serve_refuses_a_theta_file_for_the_plant_before_any_endpoint_opens(capsys):
    assert main(["serve", "--physics", "plant", "--params", "examples/start-2dof.json",
                 "--modbus", "tcp://127.0.0.1:0", "--daq", "socket://127.0.0.1:0"]) == 2
    assert capsys.readouterr().err.startswith("error: --params")
