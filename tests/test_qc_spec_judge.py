"""QC rules without the rig: the guard-band decision, the default spec against the nominal
damper of docs/models.md, and every kind of bad input refused in one line with exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import ExperimentSpec
from rig.planning.imposed import loop_energy_j
from rig.qc.characteristics import drop_peak_force, gas_pressure, loop_energy
from rig.qc.judge import Outcome, decide
from rig.qc.spec import SPECS_DIR, load_spec

DEFAULT = SPECS_DIR / "default.toml"


@pytest.mark.parametrize(("value", "std", "expected"), [
    (6.00, 0.02, (Outcome.PASS, None)),
    (5.75, 0.02, (Outcome.PASS, None)),            # 5.75 - 2·0.02 = 5.71 > 5.70
    (5.73, 0.02, (Outcome.INCONCLUSIVE, "low")),   # the interval straddles the lower limit
    (5.70, 0.0, (Outcome.INCONCLUSIVE, "low")),    # exactly on a limit: never a PASS, even with σ = 0
    (5.67, 0.02, (Outcome.INCONCLUSIVE, "low")),
    (5.65, 0.02, (Outcome.FAIL, "low")),           # 5.65 + 0.04 < 5.70
    (6.35, 0.02, (Outcome.FAIL, "high")),
    (6.28, 0.02, (Outcome.INCONCLUSIVE, "high")),
    (None, None, (Outcome.INCONCLUSIVE, None)),     # not computed: cannot be judged
])
def test_guard_band_decision(value, std, expected):
    assert decide(value, std, 5.70, 6.30, k=2.0) == expected


def test_one_sided_limits_and_the_coverage_factor():
    assert decide(10.0, 1.0, None, 12.5, k=2.0) == (Outcome.PASS, None)
    assert decide(10.0, 1.0, None, 12.5, k=3.0) == (Outcome.INCONCLUSIVE, "high")
    assert decide(10.0, 1.0, 13.0, None, k=2.0) == (Outcome.FAIL, "low")


def test_the_default_spec_describes_the_nominal_damper(tmp_path):
    """Nominal values and limits as the issue states them, each nominal the nominal
    model's own value; the energy's the simulator's nominal damper's."""
    spec = load_spec("default")
    c = {x.name: x for x in spec.characteristics}
    assert (c["gas_precharge_bar"].low, c["gas_precharge_bar"].high) == (5.70, 6.30)
    assert (c["damping_force_0.3_N"].low, c["damping_force_0.3_N"].high) == (405.0, 495.0)
    assert (c["friction_10bar_N"].low, c["friction_10bar_N"].high) == (60.0, 150.0)
    model = load_model(spec.model)
    theta = model.nominal_vector()
    assert gas_pressure(model, theta, 0.0, 293.15) / 1e5 == pytest.approx(6.00, abs=5e-4)
    assert theta[model.parameter_index("theta3")] * 0.3**2 == pytest.approx(450.0)
    assert drop_peak_force(model, theta, 350.0, 0.0) / 1e3 == pytest.approx(c["drop_peak_force_kN"].nominal, abs=1e-3)
    for x in ("dissipated_energy_J", "drop_peak_force_kN"):
        assert c[x].low == pytest.approx(0.85 * c[x].nominal if x.startswith("diss") else 0.9 * c[x].nominal)

    from simulator.generate import generate
    from simulator.truth import load_truth

    # the designed plan does not run the energy's experiment: its conditions are in the spec
    a = c["dissipated_energy_J"].args
    plan = [ExperimentSpec(a["experiment"], "", a["static_mm"], a["amplitude_mm"], a["frequency_Hz"], periods=4)]
    out = generate(tmp_path / "nominal", plan, load_truth(), periods=None, noise_scale=0.0, date="261122")
    from identify.dataset import read_dataset

    (exp,) = read_dataset(out).experiments
    assert loop_energy(exp)[0] == pytest.approx(c["dissipated_energy_J"].nominal, rel=1e-3)
    # and the model's value there is the measured one
    assert loop_energy_j(Parameters(model), plan[0]) == pytest.approx(c["dissipated_energy_J"].nominal, rel=1e-3)
    # every judged characteristic carries its likely cause for a FAIL on the side the faults push it
    for name, side in (("gas_precharge_bar", "low"), ("friction_10bar_N", "high"), ("damping_force_0.3_N", "low")):
        assert spec.cause(name, side)


def qc(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``python -m rig qc …`` in this process: exit status and stderr."""
    from rig.cli import main

    capsys.readouterr()
    code = main(["qc", *args])
    return code, capsys.readouterr().err


def spec_with(tmp_path: Path, old: str, new: str) -> str:
    text = DEFAULT.read_text()
    assert old in text, old
    path = tmp_path / "QC.toml"
    path.write_text(text.replace(old, new, 1))
    return str(path)


BAD_SPECS = {
    "unknown key": ('tolerance_percent = 5\n', 'tolerance_percnt = 5\n', "unknown key 'tolerance_percnt'"),
    "unit of another dimension": ('unit = "bar"', 'unit = "N"', "unit 'N' is not a unit of pressure"),
    "energy of a missing experiment": ('experiment = "v"\nstatic_mm = 133\namplitude_mm = 30\nfrequency_Hz = 2.0',
                                       'experiment = "x"', "the plan has no experiment 'x'"),
    "energy's conditions in part": ('amplitude_mm = 30\nfrequency_Hz = 2.0', 'amplitude_mm = 30',
                                    "give all of static_mm, amplitude_mm, frequency_Hz"),
    "unknown parameter": ('"theta15"]', '"theta99"]', "has no parameter 'theta99'"),
    "not TOML": ('k = 2.0', 'k = ', "not valid TOML"),
    "cause of an unknown characteristic": ('characteristic = "friction_10bar_N"\nwhen = "high"',
                                           'characteristic = "friction"\nwhen = "high"',
                                           "no characteristic 'friction'"),
}


@pytest.mark.parametrize("case", BAD_SPECS)
def test_a_bad_spec_is_refused_in_one_line_before_anything_moves(case, tmp_path, capsys):
    old, new, message = BAD_SPECS[case]
    spec = spec_with(tmp_path, old, new)
    # nothing listens on these addresses: a refusal must come before any connection
    code, err = qc(capsys, "run", "--spec", spec, "--serial", "SN-0001", "--shaker", "tcp://127.0.0.1:9", "--daq",
                   "socket://127.0.0.1:9", "--out", str(tmp_path / "station"))
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith("error: spec ") and message in line, line
    assert not (tmp_path / "station").exists()


@pytest.mark.parametrize(("args", "message"), [
    (["--serial", "0042"], "serial number '0042' does not have the format of spec 'default'"),
    (["--serial", "SN-0042", "--db", "mysql://u:pw@host/db"], "unsupported database 'mysql'"),
    (["--serial", "SN-0042", "--spec", "no/such/spec.toml"], "spec 'no/such/spec.toml': no such spec and no such file"),
    (["--serial", "SN-0042", "--spec", "defualt"], "spec 'defualt': no such spec and no such file (did you mean "
                                                   "'default'?); the specs shipped: default, measurands, "
                                                   "measurands-model, transient"),
])
def test_bad_serial_database_or_spec_file_exit_2(args, message, tmp_path, capsys):
    code, err = qc(capsys, "run", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9", "--out",
                   str(tmp_path / "station"), *args)
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert message in line and "pw" not in line
    assert not (tmp_path / "station").exists()


def test_history_refuses_a_bad_date_and_judge_a_folder_without_data(tmp_path, capsys):
    code, err = qc(capsys, "history", "--db", str(tmp_path / "r.sqlite"), "--since", "yesterday")
    assert code == 2 and err.strip() == (
        "error: --since 'yesterday': not an ISO date or time (2026-11-23 or 2026-11-23T14:00)")
    code, err = qc(capsys, "judge", str(tmp_path), "--db", str(tmp_path / "r.sqlite"))
    assert code == 2 and "no dataset.json" in err and len(err.strip().splitlines()) == 1


def test_the_command_line_process_refuses_with_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "rig", "qc", "run", "--serial", "SN-42", "--shaker", "tcp://127.0.0.1:9",
                        "--daq", "socket://127.0.0.1:9", "--out", str(tmp_path / "station")],
                       capture_output=True, text=True, timeout=120)
    assert (r.returncode, r.stderr) == (2, "error: serial number 'SN-42' does not have the format of spec 'default' "
                                           "(pattern [A-Z]{2,4}-[0-9]{4,8})\n")


def test_limits_from_a_tolerance_are_exact_decimals():
    spec = load_spec("default")
    lows = [c.low for c in spec.characteristics]
    assert lows[0] == 5.70 and all(np.isfinite(x) for x in lows if x is not None)
