"""The operator's console (``rig.gui``), offscreen, against the simulator at 50x: a plan
to the end with its fit, the E-STOP, a refused manual command, the session browser on
a CLI session, closing the window mid-run, and QC mode's verdict.  Every wait is on the
window's state (qtbot.waitUntil) or on the station's events, never a sleep."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

pytest.importorskip("pytestqt")
from PySide6 import QtCore, QtWidgets  # noqa: E402

from rig.config import DEFAULT_RIG_CONFIG  # noqa: E402
from rig.gui import MainWindow  # noqa: E402
from tests.conftest import HANG_S  # noqa: E402

STATE_OFF, STATE_MOVING, STATE_RUNNING = 0, 2, 4
HANG_MS = int(HANG_S * 1000)   # qtbot's unit: every wait below is for a state, this only guards a hang
SPEED = "50"


@pytest.fixture
def relaxed_config(tmp_path: Path) -> Path:
    """The default rig on the change criterion with looser thresholds and no conditioning
    holds, so that the tests' experiments settle in a few seconds of wall time (the criteria
    and holds themselves are the acquisition's tests' business)."""
    text = DEFAULT_RIG_CONFIG.read_text()
    for key, value in (("pressure_bar", "0.005"), ("gas_temperature_C", "0.03"), ("force_N", "20.0"),
                       ("criterion", '"change"'), ("max_hold_s", "0.0")):
        text = "\n".join(f"{key} = {value}" if line.startswith(f"{key} =") else line for line in text.splitlines())
    path = tmp_path / "rig-relaxed.toml"
    path.write_text(text + "\n")
    return path


def open_window(qtbot, *argv: str) -> MainWindow:
    window = MainWindow.from_args(list(argv))
    qtbot.addWidget(window)
    window.show()
    return window


def connected(qtbot, window: MainWindow) -> None:
    qtbot.waitUntil(lambda: window.station.shaker is not None and window.status is not None, timeout=HANG_MS)


def find(window: MainWindow, kind: type, name: str):
    widget = window.findChild(kind, name)
    assert widget is not None, name
    return widget


def row_status(window: MainWindow, row: int) -> str:
    progress = window.plan.progress
    return progress.rows[row].status if progress is not None and row < len(progress.rows) else ""


def raw_client(url: str) -> ModbusTcpClient:
    host, port = url.removeprefix("tcp://").rsplit(":", 1)
    client = ModbusTcpClient(host, port=int(port), timeout=1)
    assert client.connect()
    return client


def status_reads(qtbot, window: MainWindow, n: int) -> None:
    """Wait for ``n`` more of the console's reads of the controller's status."""
    seen = [window.status]

    def more() -> bool:
        if window.status is not seen[-1]:
            seen.append(window.status)
        return len(seen) > n
    qtbot.waitUntil(more, timeout=HANG_MS)


def closed(qtbot, window: MainWindow) -> None:
    window.close()
    qtbot.waitUntil(lambda: not window.isVisible(), timeout=HANG_MS)


def test_plan_to_the_end_fills_the_fit_table(qtbot, tmp_path, relaxed_config):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--experiments", "j,n", "--out", str(tmp_path),
                         "--rig-config", str(relaxed_config))
    assert "SIMULATED" in find(window, QtWidgets.QLabel, "simulatedLabel").text()
    connected(qtbot, window)
    folder = Path(window.plan.folder.text())
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: row_status(window, 0) in ("moving", "settling"), timeout=HANG_MS)
    table = find(window, QtWidgets.QTableWidget, "parameterTable")
    qtbot.waitUntil(lambda: table.rowCount() == 3, timeout=HANG_MS)
    assert [table.item(i, 0).text().split()[0] for i in range(3)] == ["theta4", "theta6", "theta16"]
    assert "converged" in window.fit_view.title.text()
    assert [row_status(window, i) for i in range(2)] == ["done", "done"]
    experiments = find(window, QtWidgets.QTableWidget, "experimentTable")
    assert [experiments.item(i, 4).text() for i in range(2)] == ["done", "done"]
    # The same files as a session of `rig run`, the journal starting with the handshake's answers
    assert json.loads((folder / "session.json").read_text())["status"] == "complete"
    labels = [e["label"] for e in json.loads((folder / "dataset.json").read_text())["experiments"]]
    assert [label[-1] for label in labels] == ["j", "n"]
    for name in ("config/rig.toml", "config/daq-calibration.toml", "config/register-map.toml", "config/plan.txt",
                 "config/software.json", "session.log", "journal/daq-raw.bin", "RESULT.json", "report.txt",
                 f"{labels[0]}.csv", f"{labels[1]}.csv"):
        assert (folder / name).is_file(), name
    assert (folder / "journal" / "daq-raw.bin").read_bytes().startswith(b"OK STOP 0\nDAQ4,")
    assert json.loads((folder / "RESULT.json").read_text())["converged"]
    closed(qtbot, window)
    assert not window.simulated.running


def test_estop_during_settling_stops_motion_and_hydraulics_within_0_3_s(qtbot, tmp_path, relaxed_config):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--experiments", "h", "--out", str(tmp_path),
                         "--rig-config", str(relaxed_config))
    connected(qtbot, window)
    window.plan.identify.setChecked(False)
    folder = Path(window.plan.folder.text())
    client = raw_client(window.simulated.modbus_url)
    try:
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda: row_status(window, 0) == "settling", timeout=HANG_MS)
        # The row says settling from RUN's command on; the controller is RUNNING once its move ends.
        qtbot.waitUntil(lambda: client.read_input_registers(0, count=1).registers[0] == STATE_RUNNING,
                        timeout=HANG_MS)
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "estopButton"), QtCore.Qt.MouseButton.LeftButton)
        # The E-STOP says when the controller has answered both writes.  Their time from the
        # press is tested on a fake clock in test_estop.py (a wall-clock bound here would
        # measure the host's load); benchmarks/bench_estop.py prints it on a served rig.
        done = window.station.emergency.wait(10)
        assert done is not None
        state, hydraulics = client.read_input_registers(0, count=1).registers[0], client.read_coils(0, count=1).bits[0]
        assert (state, hydraulics) == (STATE_OFF, False)
        assert not done.failures and done.line == "E-STOP line"
        qtbot.waitUntil(lambda: "E-STOP" in find(window, QtWidgets.QLabel, "alarmBanner").text(), timeout=HANG_MS)
        qtbot.waitUntil(lambda: not window.station.session_running, timeout=HANG_MS)
        # Held, not moving: the same position across two of the console's status reads (the
        # actuator's own deceleration right after STOP is over by the end of the safe stop).
        position = client.read_input_registers(2, count=1).registers[0]
        status_reads(qtbot, window, 2)
        assert client.read_input_registers(2, count=1).registers[0] == position
        assert client.read_coils(0, count=1).bits[0] is False
        # Latched until the operator confirms a reset: hydraulics on is refused, nothing sent.
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "hydraulicsOnButton"), QtCore.Qt.MouseButton.LeftButton)
        assert "E-STOP pressed at" in find(window, QtWidgets.QLabel, "refusalLabel").text()
        status_reads(qtbot, window, 2)
        assert client.read_coils(0, count=1).bits[0] is False
    finally:
        client.close()
    assert json.loads((folder / "session.json").read_text())["status"].startswith("interrupted")
    assert "E-STOP pressed by the operator" in (folder / "session.log").read_text()
    closed(qtbot, window)


def test_estop_shortcut(qtbot, tmp_path):
    window = open_window(qtbot, "--out", str(tmp_path))
    fired = []
    window.station.estop = lambda: fired.append(True)     # no rig here: only that the key reaches the E-STOP
    with qtbot.waitActive(window):
        window.activateWindow()
    qtbot.keyClick(window.shaker_edit, QtCore.Qt.Key.Key_Escape)
    assert fired == [True]
    assert "E-STOP" in find(window, QtWidgets.QLabel, "alarmBanner").text()
    closed(qtbot, window)


def test_manual_move_beyond_the_limits_is_refused_and_nothing_written(qtbot, tmp_path):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--out", str(tmp_path))
    connected(qtbot, window)
    client = raw_client(window.simulated.modbus_url)
    try:
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "hydraulicsOnButton"), QtCore.Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda: client.read_coils(0, count=1).bits[0], timeout=HANG_MS)
        qtbot.waitUntil(lambda: window.status is not None and window.status.state != "OFF", timeout=HANG_MS)
        before = client.read_holding_registers(0, count=5).registers
        window.manual.position.setValue(290.0)                      # the stroke limit is 270 mm
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "moveButton"), QtCore.Qt.MouseButton.LeftButton)
        refusal = find(window, QtWidgets.QLabel, "refusalLabel").text()
        assert "Refused, nothing sent" in refusal and "outside the stroke limits" in refusal
        window.manual.sine_static.setValue(133.0)
        window.manual.sine_amplitude.setValue(100.0)                # 2π·0.1 m·2 Hz = 1.26 m/s > 0.6 m/s
        window.manual.sine_frequency.setValue(2.0)
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "sineButton"), QtCore.Qt.MouseButton.LeftButton)
        assert "peak velocity" in find(window, QtWidgets.QLabel, "refusalLabel").text()
        assert client.read_holding_registers(0, count=5).registers == before
        # The same path does write what is within the limits (so the read above can tell).
        window.manual.position.setValue(140.0)
        qtbot.mouseClick(find(window, QtWidgets.QPushButton, "moveButton"), QtCore.Qt.MouseButton.LeftButton)
        assert find(window, QtWidgets.QLabel, "refusalLabel").text() == ""
        qtbot.waitUntil(lambda: client.read_holding_registers(2, count=1).registers[0] == 14000, timeout=HANG_MS)
    finally:
        client.close()
    closed(qtbot, window)
    log = window.simulated.log()
    assert "hydraulics on" in log and "refused" not in log, log


def test_browser_opens_a_session_written_by_rig_run_and_refits_it(qtbot, tmp_path, virtual_rig):
    sim = virtual_rig(speed=float(SPEED))
    out = tmp_path / "cli-session"
    r = subprocess.run([sys.executable, "-m", "rig", "run", "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out",
                        str(out), "--experiments", "j", "--identify"], capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-3000:]
    window = open_window(qtbot, "--out", str(tmp_path))
    assert window.browser.open_folder(out)
    assert "complete" in find(window, QtWidgets.QLabel, "browserSummary").text()
    experiments = find(window, QtWidgets.QTableWidget, "browserExperiments")
    assert experiments.rowCount() == 1 and experiments.item(0, 0).text().endswith("j")
    assert "session-start" in find(window, QtWidgets.QPlainTextEdit, "browserLog").toPlainText()
    assert "[[Variables]]" in find(window, QtWidgets.QPlainTextEdit, "browserReport").toPlainText()
    assert find(window, QtWidgets.QTableWidget, "browserParameters").rowCount() == 3
    window.browser.model.setCurrentText("1dof")
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "refitButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: window.fit_view.result is not None, timeout=HANG_MS)
    assert window.fit_view.result.model == "1dof"
    table = find(window, QtWidgets.QTableWidget, "parameterTable")
    assert [table.item(i, 0).text().split()[0] for i in range(table.rowCount())] == ["theta5", "theta6", "theta7"]
    closed(qtbot, window)


def test_closing_mid_run_is_a_safe_stop_and_the_session_resumes(qtbot, tmp_path, virtual_rig, relaxed_config):
    sim = virtual_rig(speed=float(SPEED))
    window = open_window(qtbot, "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--experiments", "j,n",
                         "--out", str(tmp_path), "--rig-config", str(relaxed_config))
    connected(qtbot, window)
    window.plan.identify.setChecked(False)
    folder = Path(window.plan.folder.text())
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: row_status(window, 1) == "settling", timeout=HANG_MS)
    first = next(folder.glob("*j.csv"))
    digest = hashlib.sha256(first.read_bytes()).hexdigest()
    closed(qtbot, window)
    meta = json.loads((folder / "session.json").read_text())
    assert meta["status"].startswith("interrupted")
    assert "the window was closed: safe stop" in (folder / "session.log").read_text()
    client = raw_client(sim.modbus_url)
    try:
        assert client.read_coils(0, count=1).bits[0] is False                 # hydraulics off after the safe stop
    finally:
        client.close()
    r = subprocess.run([sys.executable, "-m", "rig", "run", "--resume", "--out", str(folder), "--shaker",
                        sim.modbus_url, "--daq", sim.daq_url, "--rig-config", str(relaxed_config)],
                       capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads((folder / "session.json").read_text())["status"] == "complete"
    assert len(json.loads((folder / "dataset.json").read_text())["experiments"]) == 2
    assert hashlib.sha256(first.read_bytes()).hexdigest() == digest


def test_qc_mode_gives_the_verdict_of_rig_qc_run_with_its_report(qtbot, tmp_path):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--out", str(tmp_path))
    connected(qtbot, window)
    verdict = find(window, QtWidgets.QLabel, "verdictLabel")
    window.qc.serial.setText("SN-4242")
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "qcTestButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: verdict.text() == "TESTING…", timeout=HANG_MS)
    assert window.left_tabs.currentWidget() is window.qc
    qtbot.waitUntil(lambda: window.qc.last is not None, timeout=HANG_MS)
    done = window.qc.last
    assert done.shown in ("PASS", "FAIL", "RETEST"), (done, window.simulated.log()[-500:])
    assert verdict.text() == done.shown
    # The record `rig qc run` writes, with the same verdict (RETEST is the INCONCLUSIVE's remedy).
    record = json.loads((done.report.parent / "qc-record.json").read_text())
    assert {"PASS": "PASS", "FAIL": "FAIL", "RETEST": "INCONCLUSIVE"}[done.shown] == record["verdict"]
    assert record["serial"] == "SN-4242" and record["status"] == "COMPLETE"
    assert done.report.parent.parent == (tmp_path / "qc").resolve() and done.report.is_file()
    assert done.report.resolve().as_uri() in find(window, QtWidgets.QLabel, "qcReportLink").text()
    assert json.loads((done.report.parent / "session.json").read_text())["status"] == "complete"
    # The verdict stays until the next unit; a refused unit (a serial not in the spec's format) is said, nothing runs.
    qtbot.waitUntil(lambda: window.station.shaker is not None, timeout=HANG_MS)     # the console's links back
    window.qc.serial.setText("4243")                                                # not the spec's format
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "qcTestButton"), QtCore.Qt.MouseButton.LeftButton)
    assert verdict.text() == "REFUSED" and "format of spec" in find(window, QtWidgets.QLabel, "qcReason").text()
    assert not window.station.session_running and window.station.shaker is not None
    closed(qtbot, window)
