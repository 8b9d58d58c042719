"""What a fit reports beyond its estimates: Floquet multipliers per scheme, the last
iterate of an interrupted fit, bounds, progress, warnings and the experiments table.

The data are a linear oscillator's exact multisine response (tests/linear_oscillator.py)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from tests import linear_oscillator as lin


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "identify", *args], capture_output=True, text=True, timeout=600)


def _start(tmp_path: Path, **values: float) -> Path:
    path = tmp_path / "start.json"
    path.write_text(json.dumps({"model": "linear-1dof", "parameters": values}))
    return path


def test_stability_under_the_spectral_scheme_gives_the_damped_oscillators_multiplier(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    result = tmp_path / "R.json"
    proc = identify("fit", str(data), "--model", model, "--scheme", "spectral", "--params",
                    str(_start(tmp_path, c=12.0, k=4.5e4)), "--estimate", "c,k", "--stability",
                    "--output", str(result), "--quiet")
    assert proc.returncode == 0, proc.stderr + proc.stdout
    doc = json.loads(result.read_text())
    p = doc["parameters"]
    period = 1.0 / doc["experiments"]["lin"]["frequency_Hz"]
    # Free motion decays as exp(−c/(2m)·t); both multipliers of the underdamped pair have that size.
    expected = math.exp(-p["c"]["value"] / (2 * p["m"]["value"]) * period)
    assert abs(doc["experiments"]["lin"]["floquet_max_multiplier"] / expected - 1) < 0.01
    assert "Floquet |μ|max" in proc.stdout


def _fit(tmp_path: Path, name: str, data: Path, model: str, params: Path, *extra: str) -> tuple[int, dict, str]:
    result = tmp_path / f"{name}.json"
    proc = identify("fit", str(data), "--model", model, "--scheme", "spectral", "--params", str(params),
                    "--estimate", "c,k,m", "--output", str(result), *extra)
    return proc.returncode, json.loads(result.read_text()), proc.stdout + proc.stderr


def test_a_fit_stopped_by_the_iteration_cap_restarts_from_its_result_to_the_same_estimates(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    start = _start(tmp_path, m=2.6, c=7.0, k=3.5e4)
    code, full, out = _fit(tmp_path, "full", data, model, start, "--quiet")
    assert code == 0 and full["converged"], out
    assert full["iterations"] > 3  # else a cap of 2 would not interrupt it
    code, shown, out = _fit(tmp_path, "shown", data, model, start)  # one progress row per step taken
    rows = [ln.split() for ln in out.splitlines() if ln.strip().split(" ", 1)[0].isdigit()]
    assert code == 0 and [int(r[0]) for r in rows] == list(range(1, shown["iterations"] + 1)), out
    code, cut, out = _fit(tmp_path, "cut", data, model, start, "--quiet", "--max-iterations", "2")
    assert code == 1, out
    assert cut["converged"] is False and cut["iterations"] == 2
    assert cut["parameters"]["k"]["value"] not in (3.5e4, full["parameters"]["k"]["value"])  # an iterate, not the start
    code, again, out = _fit(tmp_path, "again", data, model, tmp_path / "cut.json", "--quiet")
    assert code == 0 and again["converged"], out
    for name in ("m", "c", "k"):
        p, q = full["parameters"][name], again["parameters"][name]
        assert abs(p["value"] - q["value"]) < 0.1 * p["std"], name


def test_a_time_limit_stops_the_fit_with_its_last_iterate(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    # A nanosecond has passed once the start is evaluated: no iteration begins.
    code, doc, out = _fit(tmp_path, "r", data, model, _start(tmp_path, m=2.6, c=7.0, k=3.5e4), "--time-limit", "1e-9")
    assert code == 1, out
    assert doc["converged"] is False and doc["iterations"] == 0 and "time limit" in doc["message"]
    assert doc["parameters"]["k"]["value"] == 3.5e4


def test_ctrl_c_writes_the_last_iterate_and_exits_130(tmp_path, monkeypatch, capsys):
    from identify import cli

    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    seen = []

    def progress(console, params, estimate):
        def report(iteration, objective, values):
            seen.append(values.copy())
            if iteration == 2:
                raise KeyboardInterrupt  # as a Ctrl-C arriving while iteration 2 is reported
        return report

    monkeypatch.setattr(cli, "_progress", progress)
    result = tmp_path / "R.json"
    code = cli.main(["fit", str(data), "--model", model, "--scheme", "spectral", "--params",
                     str(_start(tmp_path, m=2.6, c=7.0, k=3.5e4)), "--estimate", "m,c,k", "--output", str(result)])
    assert code == 130
    doc = json.loads(result.read_text())
    assert doc["converged"] is False and doc["interrupted"] is True and doc["iterations"] == 2
    # The estimator reports values in declaration order: m, c, k.
    assert [doc["parameters"][n]["value"] for n in ("m", "c", "k")] == list(seen[-1])
    assert "restart with --params RESULT.json" in capsys.readouterr().err


def test_progress_columns_are_named_in_the_order_of_estimate(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    code, _, out = _fit(tmp_path, "r", data, model, _start(tmp_path, m=2.0, c=13.0, k=4.0e4), "--estimate", "k,c")
    assert code == 0, out
    lines = out.splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.split()[:2] == ["iteration", "objective"])
    assert lines[head].split()[2:] == ["k", "c"]
    rows = [ln.split() for ln in lines[head + 1:] if ln.split() and ln.split()[0].isdigit()]
    assert rows
    for row in rows:
        assert float(row[2]) > 1000 > float(row[3])  # k (tens of thousands) under k, c (tens) under c


def test_per_experiment_mode_prints_the_warnings(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data", noise=2.0)  # noise twice the signal: c poorly identifiable
    code, doc, out = _fit(tmp_path, "r", data, model, _start(tmp_path), "--per-experiment", "--quiet")
    warnings = doc["per_experiment"]["lin"]["warnings"]
    assert warnings, out
    assert f"warning (lin): {warnings[0]}" in " ".join(out.split())


def test_the_experiments_table_lists_every_fitted_output(tmp_path):
    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    code, _, out = _fit(tmp_path, "r", data, model, _start(tmp_path, c=12.0), "--quiet",
                        "--outputs", "displacement_mm,acceleration_m_s2")
    assert code == 0, out
    lines = out.splitlines()
    table = lines[next(i for i, ln in enumerate(lines) if ln.startswith("[[Experiments]]")) + 1]
    assert table.split()[0] == "lin" and "displacement_mm" in table and "acceleration_m_s2" in table


def test_a_declared_minimum_holds_the_damping_at_zero_and_the_report_flags_it(tmp_path):
    model = lin.write_model(tmp_path, damping_bounds=", minimum=0.0")
    # Data that want a negative damping (an energy source), as model error can.
    data = lin.write_dataset(tmp_path / "data", theta={"m": 2.0, "c": -0.5, "k": 5.0e4})
    code, doc, out = _fit(tmp_path, "r", data, model, _start(tmp_path, c=5.0), "--quiet")
    c = doc["parameters"]["c"]
    assert c["value"] == 0.0 and c["at_bound"] == "minimum" and c["min"] == 0.0
    assert any(w.startswith("c (damping) ended on its minimum 0") and "no physical value" in w
               for w in doc["warnings"])
    assert "[AT MINIMUM" in out
    report = identify("report", str(tmp_path / "r.json"))
    assert report.returncode == 0 and "[AT MINIMUM]" in report.stdout


def test_start_file_bounds_narrow_the_range_and_are_checked(tmp_path):
    model = lin.write_model(tmp_path, damping_bounds=", minimum=0.0")
    data = lin.write_dataset(tmp_path / "data")
    start = tmp_path / "bounded.json"
    start.write_text(json.dumps({"model": "linear-1dof", "parameters": {"k": {"value": 4.8e4, "max": 4.9e4}}}))
    code, doc, out = _fit(tmp_path, "r", data, model, start, "--quiet")
    k = doc["parameters"]["k"]
    assert k["value"] == 4.9e4 and k["at_bound"] == "maximum"
    assert any("outside the range the START file allows" in w for w in doc["warnings"])
    for bad, says in (({"c": {"value": 1.0, "min": -1.0}}, "below its physical minimum 0"),
                      ({"k": {"value": 6e4, "max": 5.5e4}}, "lies outside its bounds"),
                      ({"k": {"value": 5e4, "min": 6e4, "max": 5.5e4}}, "above max"),
                      ({"k": {"value": 5e4, "minimum": 4e4}}, "unknown key 'minimum'")):
        start.write_text(json.dumps({"model": "linear-1dof", "parameters": bad}))
        proc = identify("fit", str(data), "--model", model, "--params", str(start), "--estimate", "c,k",
                        "--output", str(tmp_path / "x.json"))
        assert proc.returncode == 2 and says in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


def test_under_a_wrong_model_structure_the_residual_based_sigma_covers_another_realisation(tmp_path):
    """A Duffing oscillator fitted to a two-mode chain, once per random-phase realisation
    of the same multisine: the estimates differ by far more than the noise-only σ say,
    and by no more than 2√2 residual-based σ; the report says which σ to quote."""
    docs, reports = [], []
    for seed in (1, 2):
        data = lin.write_two_mode_dataset(tmp_path / f"data{seed}", phase_seed=seed)
        result = tmp_path / f"R{seed}.json"
        start = tmp_path / "start.json"  # k3's nominal is 0: its prior std must be given
        start.write_text(json.dumps({"model": "duffing", "parameters": {"k3": {"value": 0.0, "prior_std": 0.1}}}))
        proc = identify("fit", str(data), "--model", "duffing", "--scheme", "spectral", "--estimate", "m,d,k,k3",
                        "--params", str(start), "--output", str(result), "--quiet")
        assert proc.returncode == 0, proc.stderr + proc.stdout
        docs.append(json.loads(result.read_text()))
        reports.append(" ".join(proc.stdout.split()))
    noise_only_covers = []
    for name in ("m", "d", "k", "k3"):
        a, b = (d["parameters"][name] for d in docs)
        diff = abs(a["value"] - b["value"])
        assert diff <= 2 * math.sqrt(2) * max(a["std_residual"], b["std_residual"]), name
        noise_only_covers.append(diff <= 2 * math.sqrt(2) * max(a["std"], b["std"]))
    assert not any(noise_only_covers)
    for report in reports:
        assert "* residual-based σ" in report and "covers the noise only: quote the one marked *" in report
        assert "excited frequency lines" in report


def test_multisine_records_get_a_frequency_response_figure_and_sines_do_not(tmp_path):
    import numpy as np

    from identify.preparation import MULTISINE_LINES, excited_lines

    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    figures = tmp_path / "figures"
    code, _, out = _fit(tmp_path, "r", data, model, _start(tmp_path, c=12.0), "--quiet", "--figures", str(figures))
    assert code == 0, out
    assert (figures / "frf_displacement_mm.png").stat().st_size > 10_000
    assert f"figure {figures / 'frf_displacement_mm.png'}" in " ".join(out.split())
    tau = np.arange(800) / 800
    sine = 3.0 + np.sin(2 * np.pi * tau) + 0.02 * np.sin(2 * np.pi * 3 * tau)  # a sine with a little distortion
    assert excited_lines(sine[None]).tolist() == [1]
    assert excited_lines(np.fft.irfft(lin.multisine(1, 256, 256.0, (2.0, 60.0), 1.0), n=256)).size == 59
    assert MULTISINE_LINES > 1


def test_qc_guard_bands_propagate_the_residual_based_covariance_where_the_fit_gives_one():
    from types import SimpleNamespace

    import numpy as np

    from identify.model import load_model
    from identify.parameters import Parameters
    from identify.result import FitResult
    from rig.qc.characteristics import Identified, _propagate

    model = load_model("2dof")
    i = model.parameter_index("theta4")
    for residual, expected in ((None, 1e-6), (np.array([[9e-12]]), 3e-6)):
        fit = SimpleNamespace(params=Parameters(model), estimated=["theta4"], covariance=np.array([[1e-12]]),
                              covariance_residual=residual, converged=True, findings=[])
        fit.honest_covariance = lambda fit=fit: FitResult.honest_covariance(fit)
        value, std = _propagate(model, Identified.from_fit(fit), lambda theta: 2.0 * theta[i], integrated=False)
        assert math.isclose(std, 2 * expected, rel_tol=1e-6)


def test_a_stop_after_a_slow_creep_says_so_and_a_brisk_one_does_not():
    """Issue 28 point 8: a 4-mode fit moved one term by 6 % over 17 iterations, then stopped
    on the χ² rule without a word about the flat direction it crept along."""
    from identify.estimator import CREEP_ITERATIONS, Estimator

    creep = [100.0, 40.0] + [40.0 - 0.1 * i for i in range(1, CREEP_ITERATIONS + 2)]
    said = Estimator._creep(creep)
    assert f"the last {CREEP_ITERATIONS + 1} iterations lowered the objective by 0.5 in all" in said
    assert "shallow" in said
    assert Estimator._creep([100.0, 40.0, 10.0, 9.95]) == ""


def test_a_fit_without_a_result_writes_result_json_with_the_same_fields(tmp_path, monkeypatch):
    """RESULT.json has one writer: a fit interrupted before its first iterate keeps the
    start values under the same fields (alias, unit, bounds, initial) as a fit's result."""
    from identify import cli

    model = lin.write_model(tmp_path)
    data = lin.write_dataset(tmp_path / "data")
    argv = ["fit", str(data), "--model", model, "--scheme", "spectral", "--params",
            str(_start(tmp_path, m=2.6, c=7.0, k=3.5e4)), "--estimate", "m,c,k", "--quiet", "--output"]
    assert cli.main([*argv, str(tmp_path / "good.json")]) == 0
    good = json.loads((tmp_path / "good.json").read_text())

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt   # while the start is evaluated: no iterate yet

    monkeypatch.setattr(cli, "fit_experiments", interrupted)
    assert cli.main([*argv, str(tmp_path / "failed.json")]) == 130
    failed = json.loads((tmp_path / "failed.json").read_text())
    assert (failed["converged"], failed["iterations"]) == (False, 0)
    assert set(failed) <= set(good)
    for name, entry in failed["parameters"].items():
        result_only = {"std_residual", "at_bound"}
        assert set(entry) == set(good["parameters"][name]) - result_only, name
        assert (entry["alias"], entry["unit"], entry["std"]) == \
            (good["parameters"][name]["alias"], good["parameters"][name]["unit"], None)
        assert entry["value"] == entry["initial"] == good["parameters"][name]["initial"]
