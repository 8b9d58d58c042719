"""The plant truth's physics, module by module: real-gas nitrogen against the reference
table, the adiabatic and isothermal limits, the orifice's laminar and turbulent ends,
dissolution that releases faster than it absorbs, cavitation, the transducers' lags,
production units, and the drop test (docs/plant.md)."""

from __future__ import annotations

import numpy as np
import pytest

from identify.plans import STANDARD_SET
from simulator.physics import Actuator, ActuatorTrack
from simulator.plant import load_constants, load_plant, unit_constants
from simulator.plant.constants import R_GAS, sources
from simulator.plant.damper import PlantDamper, equilibrium_pressure
from simulator.plant.drop import simulate_drop
from simulator.plant.integrator import integrate, integrate_stroke, states_at
from simulator.plant.oil import dissolved_equilibrium, kinematic_viscosity
from simulator.plant.orifice import pressure_drop
from simulator.plant.sequence import Segment
from simulator.plant.streaming import StreamingPlantTruth
from simulator.sensors import DATASHEET_CHANNELS

# Z of nitrogen from the reference EOS of Span et al. 2000 (J. Phys. Chem. Ref. Data 29(6)) via CoolProp.
Z_TABLE = {280: (0.9965, 0.9912, 0.9881, 0.9909), 300: (0.9984, 0.9966, 0.9966, 1.0052),
           320: (0.9998, 1.0006, 1.0030, 1.0158), 350: (1.0013, 1.0049, 1.0097, 1.0269)}
Z_BAR = (10, 30, 50, 100)


@pytest.fixture(scope="module")
def plant() -> PlantDamper:
    return load_plant()


def test_every_constant_names_its_basis_and_source():
    for name, entry in sources().items():
        assert entry["basis"].strip() and entry["source"].strip(), name
        assert entry["source"].lstrip().startswith("["), f"{name}: a source starts with its tag"


@pytest.mark.parametrize("T", sorted(Z_TABLE))
def test_the_virial_gas_reproduces_the_reference_compressibility(plant, T):
    z = [float(plant.gas.compressibility(p * 1e5, float(T))) for p in Z_BAR]
    assert z == pytest.approx(Z_TABLE[T], abs=2e-3)
    assert plant.gas.compressibility(1e3, 300.0) == pytest.approx(1.0, abs=1e-5)  # the ideal-gas limit


def test_a_fast_compression_is_adiabatic_with_the_real_gas_exponent():
    """No heat transfer, no gas dissolving or filling the dead volume: the compression's exponent lies above the
    ideal 1.40 (real cv and T(∂p/∂T)_v; κs = 1.49 at 50 bar) and below 1.5."""
    k = load_constants().changed(heat_natural_coefficient=0.0, heat_forced_coefficient=0.0, oil_ostwald_20C=1e-9,
                                 oil_ostwald_slope=0.0, transducer_dead_volume=1e-9)
    plant = PlantDamper(k)
    t = np.linspace(0.0, 0.5, 501)
    q = 0.26 * (1 - np.cos(np.pi * t / 0.5)) / 2
    v = 0.26 * np.pi / 0.5 * np.sin(np.pi * t / 0.5) / 2
    Y = integrate(plant, t, q, v, plant.rest_state(0.0))
    p, volume = plant.gas_pressure(q, Y)
    exponent = np.log(p[-1] / p[0]) / np.log(volume[0] / volume[-1])
    assert 1.40 < exponent < 1.5
    assert Y[0, -1] - Y[0, 0] > 100  # the gas heats by over 100 K


def test_at_rest_the_gas_reaches_the_isothermal_equilibrium(plant):
    """After a move and a long rest the gas is back at the wall's temperature (the wall
    itself, ~1 h to ambient, barely warmer) and the dissolved gas at equilibrium: the
    pressure is the isothermal real-gas one."""
    t = np.concatenate([np.linspace(0, 2, 201), np.linspace(2.5, 400, 796)])
    q = np.where(t < 2, 0.1 * (1 - np.cos(np.pi * t / 2)) / 2, 0.1)
    v = np.where(t < 2, 0.1 * np.pi / 2 * np.sin(np.pi * t / 2) / 2, 0.0)
    Y = integrate(plant, t, q, v, plant.rest_state(0.0))
    p_end = float(plant.gas_pressure(q[-1:], Y[:, -1:])[0][0])
    assert Y[1, -1] == pytest.approx(plant.ambient_k, abs=0.3)
    assert Y[0, -1] == pytest.approx(Y[1, -1], abs=0.02)
    assert p_end == pytest.approx(equilibrium_pressure(plant, 0.1, Y[1, -1]), rel=1e-3)
    assert Y[2, -1] == pytest.approx(float(dissolved_equilibrium(plant.k, p_end, Y[1, -1])), rel=0.05)
    assert plant.gas_pressure(q[-1:], Y[:, -1:])[0][0] > plant.gas_pressure(np.array([0.0]),
                                                                           plant.rest_state(0.0)[:, None])[0][0]


def test_gas_comes_out_of_the_oil_faster_than_it_goes_in(plant):
    """A pressure step up then down by the same stroke: the dissolved amount's gap to
    equilibrium closes faster on the way down (release) than up (absorption)."""
    def gap_after(q0: float, q1: float) -> float:
        plant_rest = plant.rest_state(q0)
        t = np.concatenate([np.linspace(0, 1, 101), np.linspace(1.1, 6, 50)])
        q = np.where(t < 1, q0 + (q1 - q0) * (1 - np.cos(np.pi * t)) / 2, q1)
        v = np.where(t < 1, (q1 - q0) * np.pi / 2 * np.sin(np.pi * t), 0.0)
        Y = integrate(plant, t, q, v, plant_rest)
        p = plant.gas_pressure(q, Y)[0]
        eq = dissolved_equilibrium(plant.k, p, Y[1])
        return float(abs(eq[-1] - Y[2, -1]) / abs(eq[-1] - plant_rest[2]))
    assert gap_after(0.2, 0.05) < 0.6 * gap_after(0.05, 0.2)


def test_the_orifice_is_laminar_at_low_and_turbulent_at_high_reynolds_numbers(plant):
    k, nu = plant.k, float(kinematic_viscosity(plant.k, 293.15))
    low = pressure_drop(k, np.array([1e-8, 2e-8]), nu)
    high = pressure_drop(k, np.array([1e-2, 2e-2]), nu)
    assert low[1] / low[0] == pytest.approx(2.0, rel=0.02)       # Δp ∝ Q
    assert high[1] / high[0] == pytest.approx(4.0, rel=0.02)     # Δp ∝ Q²
    area = np.pi * k.orifice_diameter**2 / 4
    cd = 1e-2 / (area * np.sqrt(2 * high[0] / k.oil_density))
    assert cd == pytest.approx(k.orifice_cd_turbulent, rel=0.01)
    assert 20 < nu * 1e6 < 25   # MIL-PRF-5606 at 20 °C, Walther through the datasheet


def test_the_rebound_chamber_cavitates_and_the_void_closes_on_compression():
    """A low charge and a fast extension: the chamber's pressure holds at the cavitation
    pressure, a void opens, and the next compression closes it before oil resists."""
    plant = PlantDamper(load_constants().changed(charge_pressure=1.5e5))
    t = np.linspace(0.0, 0.6, 601)
    q = 0.05 + 0.04 * np.cos(2 * np.pi * t / 0.6)      # out at 0.42 m/s, then back in
    v = -0.04 * 2 * np.pi / 0.6 * np.sin(2 * np.pi * t / 0.6)
    Y = integrate(plant, t, q, v, plant.rest_state(0.09))
    f = plant.forces(q, v, Y)
    assert np.max(Y[5]) > 1e-6
    assert np.min(f.chamber_pressure) == pytest.approx(plant.k.oil_cavitation_pressure)
    assert Y[5, -1] == 0.0


def test_the_thermometer_lags_the_gas_and_leans_to_the_wall(plant):
    t = np.linspace(0.0, 4.0, 1001)
    q = 0.133 + 0.03 * np.sin(2 * np.pi * t)
    v = 0.03 * 2 * np.pi * np.cos(2 * np.pi * t)
    Y = integrate(plant, t, q, v, plant.rest_state(0.133))
    last = t > 3
    assert np.ptp(Y[4, last]) < 0.3 * np.ptp(Y[0, last])


def test_the_transducer_reads_the_dead_volume_behind_its_line(plant):
    """At 2 Hz the transducer's pressure lags the gas's by a few milliseconds."""
    t = np.linspace(0.0, 2.0, 1001)
    q = 0.133 + 0.01 * np.sin(4 * np.pi * t)
    v = 0.01 * 4 * np.pi * np.cos(4 * np.pi * t)
    Y = integrate(plant, t, q, v, plant.rest_state(0.133))
    f = plant.forces(q, v, Y)
    last = t > 1
    lag = np.angle(np.sum(f.p_dead[last] * np.exp(-4j * np.pi * t[last])) / np.sum(
        f.p_gas[last] * np.exp(-4j * np.pi * t[last])))
    assert -0.2 < lag < -0.005


def test_units_change_the_constants_their_fault_changes():
    nominal = load_constants()
    assert unit_constants(None) == nominal
    leak = unit_constants("gas-leak", 5)
    assert leak.gas_loss < 0.9 and PlantDamper(leak).n_total < PlantDamper(nominal).n_total
    assert unit_constants("worn-orifice", 5).orifice_diameter > 1.04 * nominal.orifice_diameter
    seal = unit_constants("worn-seal", 5)
    assert seal.seal_preload_force > 1.5 * nominal.seal_preload_force
    good = unit_constants("good", 5)
    assert good.orifice_diameter == pytest.approx(nominal.orifice_diameter, rel=0.02)
    assert unit_constants("good", 5) == good   # seeded


def test_the_drop_test_reaches_about_half_a_metre_per_second_and_settles_at_the_static_load():
    r = simulate_drop(duration_s=2.5)
    assert np.max(r.velocity_m_s) == pytest.approx(0.5, abs=0.05)
    assert np.max(r.force_N) > 350 * 9.81
    assert 0.03 < np.max(r.stroke_m) < 0.25
    # The static load: the damper carries the mass once it has stopped moving.
    assert np.mean(r.force_N[-200:]) == pytest.approx(350 * 9.81, rel=0.05)
    worn = simulate_drop("worn-orifice", 5, duration_s=1.0)
    assert np.max(worn.stroke_m) > np.max(r.stroke_m[r.t <= 1.0])


def test_the_gas_constant_is_codata():
    assert R_GAS == pytest.approx(8.314462618)


def test_docs_plant_lists_every_constant_with_its_value():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "plant.md").read_text()
    for name, entry in sources().items():
        assert f"`{name}`" in doc, name
        value = entry["value"]
        shown = ", ".join(f"{x:g}" for x in value) if isinstance(value, list) else f"{value:g}"
        assert f"`{name}` | {shown} |" in doc, f"{name}: docs/plant.md shows another value than constants.toml"


# ----- one integration for every use -------------------------------------------------
ENGINE_DT_S = 1e-4   # the served engine's step (simulator.engine.PHYSICS_RATE_HZ)
DAQ_EVERY = 5        # its DAQ samples every fifth step (2 kHz)
CYCLES = {"a": 1, "b": 1}   # cycles after the fade-in; the slow experiments fewer


def _fade_in_setpoint(spec, t):
    static = spec.static_position_mm * 1e-3
    return static + spec.amplitude_mm * 1e-3 * np.clip(t / spec.period_s, 0.0, 1.0) * np.sin(
        2 * np.pi * spec.frequency_hz * t)


@pytest.mark.parametrize("spec", [pytest.param(s, marks=pytest.mark.slow) if s.letter == "a" else s
                                  for s in STANDARD_SET], ids=lambda s: s.letter)
def test_offline_and_served_records_agree_within_the_transducers_noise(plant, spec):
    """One stroke (the actuator's answer to a faded-in sine at the engine's 10 kHz), the
    served plant advanced in blocks of irregular length as the engine cuts them, the
    offline plant on its own grid as simulator generate runs it: the DAQ's samples agree
    within a standard deviation of each channel's noise."""
    static = spec.static_position_mm * 1e-3
    n = int(round((1 + CYCLES.get(spec.letter, 2)) * spec.period_s / ENGINE_DT_S))
    t = ENGINE_DT_S * np.arange(1, n + 1)
    setpoint = _fade_in_setpoint(spec, t)
    served = StreamingPlantTruth(plant, Actuator(), ENGINE_DT_S, static)
    rng = np.random.default_rng(ord(spec.letter))
    rows, start = [], 0
    while start < n:
        k = min(int(rng.integers(3, 1000)), n - start)
        stroke, v, a, Y = served.advance(setpoint[start:start + k])
        served.commit(k, Y)
        rows.append(plant.channels(stroke, v, a, Y))
        start += k
    served_si = np.hstack(rows)[:, DAQ_EVERY - 1::DAQ_EVERY]
    stroke, v, a, _ = ActuatorTrack(Actuator(), ENGINE_DT_S, static).track(setpoint)
    tt, qq, vv = np.concatenate(([0.0], t)), np.concatenate(([static], stroke)), np.concatenate(([0.0], v))
    grid, states = integrate_stroke(plant, lambda g: (np.interp(g, tt, qq), np.interp(g, tt, vv)), 0.0, t[-1],
                                    plant.rest_state(static))
    samples = slice(DAQ_EVERY - 1, None, DAQ_EVERY)
    Y = states_at(plant, grid, np.interp(grid, tt, qq), np.interp(grid, tt, vv), states, t[samples])
    offline_si = plant.channels(stroke[samples], v[samples], a[samples], Y)
    for i, ch in enumerate(DATASHEET_CHANNELS):
        gap = np.max(np.abs(ch.to_engineering(served_si[i]) - ch.to_engineering(offline_si[i])))
        assert gap < ch.noise_std, f"{ch.name}: offline and served differ by {gap:.3g} {ch.unit}"


@pytest.mark.parametrize("spec", [pytest.param(s, marks=pytest.mark.slow) if s.letter in "ab" else s
                                  for s in STANDARD_SET], ids=lambda s: s.letter)
def test_the_plants_grid_keeps_loop_work_and_peak_pressure_within_a_percent_of_lsoda(plant, spec):
    """The experiment faded in from rest at its static position, then one cycle: the
    gas's ∮p dV over that cycle and the transducer's peak pressure, on the states' grid
    and from scipy's LSODA at rtol 1e-8, both read at the grid's nodes."""
    from scipy.integrate import solve_ivp

    static, period = spec.static_position_mm * 1e-3, spec.period_s
    seg = Segment(spec, Actuator(), static, 1.0, period, 1e9)
    y0 = plant.rest_state(static)
    grid, states = integrate_stroke(plant, seg.stroke, 0.0, 2 * period, y0)

    def rhs(time, y):
        q, v, _ = seg.stroke(np.array([time]))
        return plant.rates(q, v, y[:, None])[:, 0]

    sol = solve_ivp(rhs, (0.0, grid[-1]), y0, method="LSODA", rtol=1e-8, atol=1e-10 * np.abs(y0) + 1e-14,
                    dense_output=True)
    assert sol.success, sol.message
    last = grid >= grid[-1] - period - 1e-9
    q, v, _ = seg.stroke(grid[last])

    def loop(Y):
        f = plant.forces(q, v, Y)
        return -np.trapezoid(f.p_gas, f.gas_volume), np.max(f.p_dead)

    work, peak = loop(states[:, last])
    work_ref, peak_ref = loop(sol.sol(grid[last]))
    assert work_ref > 0
    assert work == pytest.approx(work_ref, rel=0.01)
    assert peak == pytest.approx(peak_ref, rel=0.01)
