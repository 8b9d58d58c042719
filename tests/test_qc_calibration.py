"""Calibration certificates as station data (rig.qc.calibration) and the daily master check
(rig.qc.studies): the DAQ's coefficients read from the certificate file, an expired
certificate or another DAQ refused in one line before anything moves or is recorded, the
type-B uncertainty from sensitivity coefficients, and a load cell whose gain drifted 3 %
caught by the master check (on data generated offline) before ``qc run`` judges a unit."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np
import pytest

from rig.cli import main
from rig.config import CONFIG_DIR
from rig.drivers.daq import Calibration
from rig.qc.calibration import (
    CertificateError,
    load_certificates,
    uncertainty_budget,
)
from rig.qc.evaluate import STUDY_FIT_ITERATIONS, evaluate
from rig.qc.spec import load_spec
from rig.qc.studies import (
    gate,
    load_reference,
    master_check,
    master_check_policy,
    new_uid,
)
from simulator.generate import generate
from simulator.truth import load_truth

SAMPLE = CONFIG_DIR / "station-calibration-simulated.toml"
MASTER = CONFIG_DIR / "master-simulated.toml"


def test_the_daq_calibration_is_read_from_the_certificates_and_the_old_file_still_works():
    new, old = Calibration.from_file(SAMPLE), Calibration.from_file()
    assert new.names == old.names
    assert np.array_equal(new.gain, old.gain) and np.array_equal(new.offset, old.offset)
    certificates = load_certificates(SAMPLE)
    force = certificates.certificate("force_N")
    assert (force.serial, force.certificate, force.due) == ("LC-SIM-0001", "CAL-2026-0612", _dt.date(2027, 6, 12))
    # U = 1 N at zero, 0.1 % of the reading above: u(e₀) = 0.5 N, u(e₁) ≈ 0.05 %
    assert force.u_offset == pytest.approx(0.5) and force.u_gain == pytest.approx(5e-4, rel=1e-3)
    assert [e["certificate"] for e in certificates.equipment()] == ["CAL-2026-0611", "CAL-2026-0612",
                                                                     "CAL-2026-0613", "CAL-2026-0614"]


def test_an_expired_certificate_or_another_daq_is_refused():
    certificates = load_certificates(SAMPLE)
    assert certificates.refusal(_dt.date(2026, 11, 28), "DAQ4,SIM0001,1.00,SIMULATOR") is None
    why = certificates.refusal(_dt.date(2027, 6, 12), None)
    assert why is not None and "CAL-2026-0611" in why and "expired on 2027-06-11" in why
    why = certificates.refusal(_dt.date(2026, 11, 28), "DAQ4,SN-778,1.00")
    assert why is not None and "'SN-778'" in why and "'SIM0001'" in why


def expired_copy(tmp_path: Path) -> Path:
    text = SAMPLE.read_text().replace("due = 2027-06-12\ngain = 1.0", "due = 2026-11-01\ngain = 1.0")
    assert "due = 2026-11-01" in text
    path = tmp_path / "expired.toml"
    path.write_text(text)
    return path


def qc_run(tmp_path: Path, *extra: str) -> list[str]:
    # Ports where nothing listens: a refusal must come before any link is tried.
    return ["qc", "run", "--serial", "SN-0001", "--shaker", "tcp://127.0.0.1:9", "--daq", "socket://127.0.0.1:9",
            "--out", str(tmp_path / "station"), *extra]


def test_qc_run_on_an_expired_certificate_is_refused_in_one_line_with_nothing_recorded(tmp_path, capsys):
    code = main(qc_run(tmp_path, "--calibration", str(expired_copy(tmp_path))))
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "CAL-2026-0612" in err and "LC-SIM-0001" in err and "expired on 2026-11-01" in err
    assert not (tmp_path / "station").exists()      # no session, no record, no database, no queue


def test_a_certificate_file_that_is_wrong_names_the_file_and_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(SAMPLE.read_text().replace("due = 2027-06-12\ngain = 1.0", 'due = "soon"\ngain = 1.0'))
    with pytest.raises(CertificateError, match=r"\[\[transducer\]\] 2: 'due' must be a TOML date"):
        load_certificates(bad)


def test_the_calibration_uncertainty_comes_from_sensitivity_coefficients():
    """A characteristic y = 2·F + 0.5·p·F (F force, p pressure): its u_cal from the
    certificates' u(e₀), u(e₁) and the sensitivities ∂y/∂eᵢ by finite differences, as the
    GUM's law of propagation gives it by hand."""
    certificates = load_certificates(SAMPLE)
    F, p = np.array([400.0, 500.0]), np.array([6.0, 6.0])

    def recompute(perturb):
        f, q = (F, p) if perturb is None else (perturb("force_N", F), perturb("pressure_bar", p))
        return {"y": float(np.mean(2 * f + 0.5 * q * f))}

    budget = uncertainty_budget(recompute, certificates)["y"]
    force, pressure = certificates.certificate("force_N"), certificates.certificate("pressure_bar")
    c_f0, c_f1 = 2 + 0.5 * 6, float(np.mean((2 + 0.5 * 6) * F))   # per N of offset, per unit relative gain
    c_p0, c_p1 = float(np.mean(0.5 * F)), float(np.mean(0.5 * 6 * F))
    by_hand = np.sqrt((c_f0 * force.u_offset) ** 2 + (c_f1 * force.u_gain) ** 2
                      + (c_p0 * pressure.u_offset) ** 2 + (c_p1 * pressure.u_gain) ** 2)
    assert budget.u_cal == pytest.approx(by_hand, rel=1e-9)
    assert {(c.channel, c.component) for c in budget.contributions if c.sensitivity == 0} == \
        {("stroke_mm", "offset"), ("stroke_mm", "gain"), ("gas_temperature_C", "offset")}


@pytest.fixture(scope="module")
def master_values(tmp_path_factory) -> dict[str, dict[str, float | None]]:
    """The master (the nominal unit) measured offline with the default spec's plan: once
    as calibrated, once with its load cell reading 3 % high."""
    spec = load_spec("default")
    out = {}
    for name, gain in (("calibrated", 0.0), ("drifted", 0.03)):
        folder = generate(tmp_path_factory.mktemp(name), list(spec.plan.experiments), load_truth(), periods=None,
                          seed=11, date="261128", serial="MU-0001", gain_error=(0.0, gain, 0.0, 0.0))
        out[name] = {m.name: m.value for m in evaluate(spec, folder, STUDY_FIT_ITERATIONS).measured}
    return out


def _master_run(values: dict[str, float | None]):
    """qc run's outcome of the master, as the master check gets it from test_unit."""
    from types import SimpleNamespace

    from rig.qc.judge import Outcome
    from rig.qc.records import CharacteristicRecord, QcRecord, RecordStatus

    spec = load_spec("default")
    chars = tuple(CharacteristicRecord(c.name, c.unit, values[c.name], 0.01, 0.01, 0.0, c.low, c.high, c.nominal,
                                       Outcome.PASS, c.title) for c in spec.characteristics)
    record = QcRecord(new_uid(), "MU-0001", "qe", "rig", None, None, "now", "x", spec.name, spec.version, spec.sha256,
                      None, None, Outcome.PASS, RecordStatus.COMPLETE, "s", "d", {}, chars, simulated=True)
    return lambda opt, subscribers: SimpleNamespace(record=record)


def test_a_drifted_load_cell_fails_the_master_check_and_qc_run_then_refuses(master_values, tmp_path, capsys,
                                                                           monkeypatch):
    from rig.qc import msa_run
    from rig.qc.run import QcOptions

    spec = load_spec("default")
    policy = master_check_policy(SAMPLE)
    assert policy is not None and policy.fraction == 0.1
    reference = load_reference(MASTER, spec)
    ok = master_check(spec, reference, master_values["calibrated"], policy)
    assert all(d.passed for d in ok), [(d.characteristic, d.deviation, d.limit) for d in ok]

    station = tmp_path / "station"
    assert not gate(station, SAMPLE).allowed and "no master check on record" in gate(station, SAMPLE).sentence
    opt = QcOptions(spec="default", serial="MU-0001", shaker="tcp://127.0.0.1:9", daq="socket://127.0.0.1:9",
                    out=station, calibration=str(SAMPLE))
    said: list[str] = []
    monkeypatch.setattr(msa_run, "test_unit", _master_run(master_values["drifted"]))
    assert msa_run.run_check(opt, "MU-0001", str(MASTER), said.append) == msa_run.EXIT_GOALS_MISSED
    # the force-based characteristics drifted beyond 0.1·T and are named; the drop test's
    # peak force and the friction moved less than their limits (friction: 3.6 N of ±9 N)
    first = said[0]
    assert first.startswith("master check of MU-0001: FAIL: drifted: ") and "Damping force at 0.3 m/s +" in first \
        and "Drop-test peak force" not in first, first
    # every characteristic of the default spec is identified from the force channel (the gas
    # pre-charge too, through θ5): the damping force, the most sensitive, drifts past its limit
    assert "DRIFT Damping force at 0.3 m/s" in {line.split(":")[0].strip() for line in said
                                                if line.startswith("  DRIFT")}
    state = gate(station, SAMPLE)
    assert not state.allowed and "FAILED" in state.sentence and "Damping force" in state.sentence
    files_before = sorted(p.name for p in station.rglob("*"))
    code = main(qc_run(tmp_path, "--calibration", str(SAMPLE)))
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "master check" in err and "Damping force" in err, err
    assert sorted(p.name for p in station.rglob("*")) == files_before    # nothing recorded
    # the load cell recalibrated: the check passes, production goes on today, not tomorrow
    monkeypatch.setattr(msa_run, "test_unit", _master_run(master_values["calibrated"]))
    assert msa_run.run_check(opt, "MU-0001", str(MASTER), said.append) == msa_run.EXIT_GOALS_MET
    assert gate(station, SAMPLE).allowed
    assert not gate(station, SAMPLE, _dt.datetime.now(_dt.UTC) + _dt.timedelta(days=1)).allowed


def test_a_station_without_certificates_is_not_gated(tmp_path):
    assert gate(tmp_path, None).allowed and gate(tmp_path, CONFIG_DIR / "daq-calibration-datasheet.toml").allowed


def test_a_derived_u_cal_is_kept_per_spec_and_certificate_file(tmp_path):
    from rig.qc.calibration import Budget, Contribution, derived_u_cal, store_budget

    spec = load_spec("default")
    budget = {c.name: Budget(c.name, c.nominal, (Contribution("force_N", "offset", 0.5, 0.01 * (i + 1)),))
              for i, c in enumerate(spec.characteristics)}
    assert derived_u_cal(tmp_path, spec, SAMPLE) is None          # not derived yet: the spec's u_cal stands
    store_budget(tmp_path, spec, SAMPLE, tmp_path / "MU-0001-x", budget)
    got = derived_u_cal(tmp_path, spec, SAMPLE)
    assert got is not None and got[1] == str(tmp_path / "MU-0001-x")
    assert got[0] == {name: pytest.approx(b.u_cal) for name, b in budget.items()}
    other = tmp_path / "recalibrated.toml"
    other.write_text(SAMPLE.read_text().replace("CAL-2026-0612", "CAL-2026-0999"))
    assert derived_u_cal(tmp_path, spec, other) is None            # a new certificate: derived again
    assert derived_u_cal(tmp_path, spec, CONFIG_DIR / "daq-calibration-datasheet.toml") is None


def test_the_gain_fault_names_its_channel_by_number_or_name():
    from simulator.faults import FaultError, parse_fault
    from simulator.sensors import SensorSet

    fault = parse_fault("gain=force_N:0.03")
    assert (fault.kind, fault.channel, fault.value, fault.at_s) == ("gain", 1, 0.03, None)
    assert parse_fault("gain=1:0.03@run+2").after_run
    with pytest.raises(FaultError, match="channel 'forc' is none of"):
        parse_fault("gain=forc:0.03")
    # what the fault sets: the channel reads 1.03 times the truth
    truth = np.array([[0.1], [400.0], [6e5], [293.15]])
    plain, drifted = SensorSet(noise_scale=0.0), SensorSet(noise_scale=0.0, gain_error=(0.0, 0.03, 0.0, 0.0))
    f0 = plain.engineering(plain.counts(truth, np.zeros(1))[0])[1, 0]
    f1 = drifted.engineering(drifted.counts(truth, np.zeros(1))[0])[1, 0]
    assert f1 == pytest.approx(1.03 * f0, abs=1.0)    # within a count (1 N)
