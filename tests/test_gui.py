"""The operator's console (``rig.gui``), offscreen, against the simulator at 50x: a plan
to the end with its fit, the E-STOP, a refused manual command, the session browser on
a CLI session, closing the window mid-run, and QC mode's verdict.  Every wait is on the
window's state (qtbot.waitUntil) or on the station's events, never a sleep."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

pytest.importorskip("pytestqt")
from PySide6 import QtCore, QtWidgets  # noqa: E402

from rig.config import DEFAULT_RIG_CONFIG  # noqa: E402
from rig.drivers.estop import EstopDone, LatchChanged  # noqa: E402
from rig.events import Event, Kind, Message  # noqa: E402
from rig.gui import MainWindow  # noqa: E402
from rig.gui.live import LiveView  # noqa: E402
from rig.gui.messages import LinkState, SessionClosed, SessionOpened, Snapshot  # noqa: E402
from rig.gui.qc import QcProgress  # noqa: E402
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
    qtbot.waitUntil(lambda: window.station.manual.shaker is not None and window.status is not None, timeout=HANG_MS)


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
    # " — converged after": "NOT converged" must not pass for it
    assert " — converged after " in window.fit_view.title.text(), window.fit_view.title.text()
    # Numbers by their uncertainty: σ to two significant digits, the value to the same place; units in Unicode.
    for i in range(3):
        value, std = table.item(i, 1).text(), table.item(i, 2).text()
        assert len(std.lstrip("0.").replace(".", "")) == 2, std
        assert len(value.split(".")[-1]) == len(std.split(".")[-1]) if "." in std else "." not in value, (value, std)
    assert table.item(0, 4).text() == "m²"
    # The session folder field shows the session the fit is of, until Run asks for the next one.
    assert window.plan.folder.text() == str(folder) and folder.name in window.fit_view.title.text()
    assert window.plan.run_folder() != folder
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


def subclasses(base: type) -> set[type]:
    found: set[type] = set(base.__subclasses__())
    return found.union(*(subclasses(c) for c in found))


def test_the_window_queue_carries_only_typed_messages_each_with_its_handler(qtbot, tmp_path, relaxed_config):
    # Every record declared for a queue has a handler in the window (the console's modules are imported by now).
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--experiments", "j", "--out", str(tmp_path),
                         "--rig-config", str(relaxed_config))
    assert subclasses(Message) <= set(window._handlers)
    received: list[object] = []
    handle = window._handle

    def spy(item: Message) -> None:
        received.append(item)
        handle(item)
    window._handle = spy
    connected(qtbot, window)
    window.plan.identify.setChecked(False)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: any(isinstance(r, SessionClosed) for r in received), timeout=HANG_MS)
    window.estop()                                     # at rest: the E-STOP's outcome and its latch, then the reset
    qtbot.waitUntil(lambda: any(isinstance(r, EstopDone) for r in received), timeout=HANG_MS)
    window.reset_alarm(confirm=False)
    qtbot.waitUntil(lambda: [r.latched for r in received if isinstance(r, LatchChanged)] == [True, False],
                    timeout=HANG_MS)
    assert all(isinstance(r, Message) for r in received), {type(r) for r in received if not isinstance(r, Message)}
    kinds = {r.kind for r in received if isinstance(r, Event)}
    assert {Kind.SESSION_START, Kind.PHASE, Kind.PROGRESS, Kind.EXPERIMENT_DONE, Kind.SESSION_END} <= kinds
    assert {Event, Snapshot, LinkState, SessionOpened, SessionClosed} <= {type(r) for r in received}
    closed(qtbot, window)


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
        qtbot.waitUntil(lambda: not window.station.sessions.running, timeout=HANG_MS)
        # Held, not moving: the same position across two of the console's status reads (the
        # actuator's own deceleration right after STOP is over by the end of the safe stop).
        position = client.read_input_registers(2, count=1).registers[0]
        status_reads(qtbot, window, 2)
        assert client.read_input_registers(2, count=1).registers[0] == position
        assert client.read_coils(0, count=1).bits[0] is False
        # Latched until the operator confirms a reset: hydraulics on is refused, nothing sent.
        # The console disables the control and says why; the driver's latch refuses it as well.
        button = find(window, QtWidgets.QPushButton, "hydraulicsOnButton")
        qtbot.waitUntil(lambda: not button.isEnabled(), timeout=HANG_MS)
        assert "E-STOP pressed at" in button.toolTip()
        window.manual._do(window.station.manual.hydraulics(True, window.status))
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
    window.station.emergency.press = lambda: fired.append(True)   # no rig here: only that the key reaches it
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
    assert experiments.isColumnHidden(experiments.columnCount() - 1)          # no flags: no flags column
    plots = [window.browser.plot.getItem(row, 0) for row in range(4)]
    assert [p.getAxis("left").labelText.split(" [")[0] for p in plots] == ["stroke", "force", "gas p", "gas T"]
    assert plots[0].listDataItems()[0].xData[0] == 0.0                         # time from the record's start
    log = find(window, QtWidgets.QPlainTextEdit, "browserLog").toPlainText()     # session.log read as sentences
    assert "Session started: controller at" in log and log.rstrip().endswith("Session complete."), log
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
    """A unit's test through the console's own session lifecycle: throughout it, the
    controller panel, the strip and the DAQ line say what the status poll reads from the
    session's links (never "not read", never a rate not measured), and the verdict,
    record and report are those of rig qc run."""
    window = open_window(qtbot, "--simulate", "--speed", "20", "--unit", "worn-orifice", "--out", str(tmp_path))
    connected(qtbot, window)
    verdict = find(window, QtWidgets.QLabel, "verdictLabel")
    panel_state = find(window, QtWidgets.QLabel, "controller_state")
    seen: dict[str, list[Any]] = {"snapshots": [], "health": [], "progress": []}
    handle = window._handle

    def spy(item: Message) -> None:
        handle(item)
        testing = window.station.sessions.running and window.qc.last is None and verdict.text() == "TESTING…"
        if isinstance(item, Snapshot) and testing and item.session:
            seen["snapshots"].append(item)
            # What the window shows, right after handling this read: all of it from this read.
            assert item.status is not None and item.error is None, item
            assert panel_state.text() == item.status.state, (panel_state.text(), item.status)
            assert window.rig_state().strip_text().startswith(item.status.state), window.rig_state().strip_text()
            assert "not streaming" not in window.live.placeholder_reason or not item.streaming
            seen["health"].append((item.streaming, window.live.health.text()))
        elif isinstance(item, QcProgress):
            seen["progress"].append(item)
    window._handle = spy
    window.qc.serial.setText("SN-4242")
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "qcTestButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: verdict.text() == "TESTING…", timeout=HANG_MS)
    assert window.left_tabs.currentWidget() is window.qc
    qtbot.waitUntil(lambda: window.qc.last is not None, timeout=HANG_MS)
    done = window.qc.last
    assert done.shown == "FAIL", (done, window.simulated.log()[-500:])       # a worn orifice: --unit reached the rig
    # Live throughout: the controller read on the session's links in every phase it went through ...
    states = {snap.status.state for snap in seen["snapshots"]}
    assert {"RUNNING", "AT_STATIC"} <= states and len(states) >= 3, states
    # ... and the DAQ's rate measured on its stream, said with its clock, whenever it streamed 2 s and more.
    measured = [text for streaming, text in seen["health"] if streaming and "× real time" in text]
    assert measured and all("samples per wall-clock second" in t for t in measured), seen["health"][-5:]
    assert not any("measuring" in text for streaming, text in seen["health"] if not streaming)
    assert seen["progress"] and seen["progress"][-1].fraction > 0                 # the progress bar moved
    assert verdict.text().startswith(done.shown) and "SIMULATED" in verdict.text()     # the big box says it too
    # The table as the report shows it (every number with its unit), the likely cause in full.
    table = window.qc.table
    rows = [[table.item(i, j).text() for j in range(table.columnCount())] for i in range(table.rowCount())]
    assert len(rows) == 5 and rows[1][0] == "Damping force at 0.3 m/s (identified)" and rows[1][4] == "FAIL"
    assert rows[4][0] == "Drop-test peak force (predicted)"           # a simulated drop, said so
    assert rows[3][0] == "Energy dissipated per cycle (predicted)"    # an excitation the plan does not run
    trace = find(window, QtWidgets.QLabel, "qcTrace").text()        # who, which rules, which k: beside the values
    assert trace.startswith("Operator ") and re.search(r" revision \d+\.\d+\.\d+ \(sha256 [0-9a-f]{12}…\)", trace)
    assert "k = " in trace
    assert all(cell.endswith((" bar abs.", " N", " J", " kN", " %")) for row in rows for cell in row[1:4])
    causes = find(window, QtWidgets.QLabel, "qcCauses").text()
    assert "Damping force at 0.3 m/s too low: orifice wear or wrong oil" in causes and "SIMULATED" in causes
    # The record `rig qc run` writes, with the same verdict (RETEST is the INCONCLUSIVE's remedy).
    record = json.loads((done.report.parent / "qc-record.json").read_text())
    assert record["verdict"] == "FAIL" and record["simulated"] is True
    assert record["serial"] == "SN-4242" and record["status"] == "COMPLETE"
    assert done.report.parent.parent == (tmp_path / "qc") and done.report.is_file()
    assert done.report.resolve().as_uri() in find(window, QtWidgets.QLabel, "qcReportLink").text()
    assert json.loads((done.report.parent / "session.json").read_text())["status"] == "complete"
    # The verdict stays until the next unit; a refused unit (a serial not in the spec's format) is said, nothing runs.
    qtbot.waitUntil(lambda: window.station.manual.shaker is not None, timeout=HANG_MS)     # the console's links back
    window.qc.serial.setText("4243")                                                # not the spec's format
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "qcTestButton"), QtCore.Qt.MouseButton.LeftButton)
    assert verdict.text() == "REFUSED" and "format of spec" in find(window, QtWidgets.QLabel, "qcReason").text()
    assert not window.station.sessions.running and window.station.manual.shaker is not None
    closed(qtbot, window)


MOTION_BUTTONS = ("hydraulicsOnButton", "moveButton", "sineButton", "runPlanButton", "resumeButton")


def motion_disabled(window: MainWindow) -> dict[str, str]:
    """The tooltip of every disabled motion control (an enabled one is left out)."""
    buttons = {name: find(window, QtWidgets.QPushButton, name) for name in MOTION_BUTTONS}
    return {name: b.toolTip() for name, b in buttons.items() if not b.isEnabled()}


def test_after_estop_every_motion_control_is_disabled_until_the_reset_is_confirmed(qtbot, tmp_path, monkeypatch):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--out", str(tmp_path))
    connected(qtbot, window)
    strip = find(window, QtWidgets.QLabel, "stateStrip")
    qtbot.waitUntil(lambda: "HYDRAULICS OFF" in strip.text(), timeout=10_000)
    # Hydraulics off: nothing can move, but the hydraulics may be switched on.
    assert set(motion_disabled(window)) == {"moveButton", "sineButton"}
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "hydraulicsOnButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: "IDLE" in strip.text() and "HYDRAULICS ON" in strip.text(), timeout=10_000)
    assert motion_disabled(window) == {}
    window.manual.sine_amplitude.setValue(10.0)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "sineButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: strip.text().startswith("RUNNING"), timeout=10_000)

    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "estopButton"), QtCore.Qt.MouseButton.LeftButton)
    assert window.station.emergency.wait(10) is not None
    status_reads(qtbot, window, 2)          # the registers read after the E-STOP's writes
    disabled = motion_disabled(window)
    assert set(disabled) == set(MOTION_BUTTONS)
    assert all(tip.startswith("Disabled: E-STOP") for tip in disabled.values()), disabled
    assert strip.text().startswith("ALARM") and "HYDRAULICS OFF" in strip.text()
    # The panel under the strip agrees with it: the latch, not the controller's quiet OFF.
    assert find(window, QtWidgets.QLabel, "controller_state").text().startswith("ALARM")
    assert "E-STOP" in find(window, QtWidgets.QLabel, "controller_alarm").text()
    banner = find(window, QtWidgets.QLabel, "alarmBanner").text()
    assert "hydraulics OFF" in banner and "holds the position" not in banner

    answers = [QtWidgets.QMessageBox.StandardButton.No]
    monkeypatch.setattr(QtWidgets.QMessageBox, "question", lambda *a, **k: answers[-1])
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "resetButton"), QtCore.Qt.MouseButton.LeftButton)
    status_reads(qtbot, window, 2)
    assert set(motion_disabled(window)) == set(MOTION_BUTTONS)       # not confirmed: still latched
    assert strip.text().startswith("ALARM") and "HYDRAULICS OFF" in strip.text()
    answers.append(QtWidgets.QMessageBox.StandardButton.Yes)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "resetButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: strip.text().startswith("OFF"), timeout=5_000)
    assert "HYDRAULICS OFF" in strip.text()
    qtbot.waitUntil(lambda: find(window, QtWidgets.QLabel, "controller_state").text() == "OFF", timeout=5_000)
    disabled = motion_disabled(window)
    assert set(disabled) == {"moveButton", "sineButton"}
    assert all("hydraulics OFF" in tip for tip in disabled.values()), disabled
    closed(qtbot, window)


def counters_in_this_frame(window: MainWindow) -> dict[str, Any]:
    """What the operator reads of the experiment running now, all from the same frame."""
    progress = window.plan.progress
    assert progress is not None
    row = progress.current
    i = progress.rows.index(row) if row is not None else 0
    return {"row": row, "table": window.plan.table.item(i, 4).text(),
            "steady": find(window, QtWidgets.QLabel, "settleCycles").text(),
            "controller": find(window, QtWidgets.QLabel, "controller_cycles").text(),
            "capture": find(window, QtWidgets.QProgressBar, "captureProgress"),
            "left": window.plan.table.item(i, 5).text(), "eta": find(window, QtWidgets.QLabel, "sessionEta").text()}


def test_the_counters_agree_within_one_cycle_in_the_same_frame(qtbot, tmp_path, relaxed_config):
    window = open_window(qtbot, "--simulate", "--speed", "20", "--experiments", "h", "--out", str(tmp_path),
                         "--rig-config", str(relaxed_config))
    connected(qtbot, window)
    window.plan.identify.setChecked(False)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
    rate = window.station.config.daq_rate_hz
    seen = {"settling": 0, "capturing": 0}

    def check() -> bool:
        shown = counters_in_this_frame(window)
        row = shown["row"]
        if row is None or row.status not in seen or row.samples is None:
            return False
        # the cycles the DAQ's stream has seen after the fade-in, as the acquisition counts them
        counted = (row.samples - row.lead_samples) * row.spec.frequency_hz / rate
        if row.status == "settling" and str(shown["table"]).startswith("settling "):
            settling = int(str(shown["table"]).split()[1])
            assert f"settling {settling} cycles" in str(shown["steady"]), shown
            assert abs(counted - settling) <= 1, (counted, shown)
        elif row.status == "capturing" and str(shown["table"]).startswith("capturing "):
            percent = str(shown["table"]).split()[1]
            bar = shown["capture"]
            whole = f"({percent} % of the capture)"
            assert bar.isVisible() and whole in bar.text() and whole in str(shown["steady"])
            period = int(bar.text().split("capturing period ")[1].split()[0])
            assert abs(counted - row.settled_at - (period - 0.5)) <= 1, (counted, shown)
        else:
            return False
        # the time left in the table is the one the session line gives for this experiment
        assert f"{row.label}: rig time {shown['left']} m:s" in str(shown["eta"]), shown
        seen[row.status] += 1
        return seen["settling"] >= 3 and seen["capturing"] >= 1

    qtbot.waitUntil(check, timeout=180_000)
    qtbot.waitUntil(lambda: not window.station.sessions.running, timeout=120_000)
    closed(qtbot, window)


def test_the_loop_plots_show_a_placeholder_when_no_excitation_runs(qtbot, tmp_path):
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--out", str(tmp_path))
    connected(qtbot, window)
    live = window.live
    energy = find(window, QtWidgets.QLabel, "loopEnergy")

    def placeholders_shown() -> bool:
        return (all(t.isVisible() and t.toPlainText().startswith("no cycle yet") for t in live.placeholders)
                and not live.loop_plot.getAxis("left").isVisible() and live.loop.getData()[0] is None
                and "no cycle yet" in energy.text())

    qtbot.waitUntil(lambda: live.history.n > 0, timeout=10_000)
    assert placeholders_shown()
    # At rest each trace spans at least its channel's minimum (rig configuration), not the noise.
    qtbot.waitUntil(lambda: all(p.getViewBox().viewRange()[1][1] - p.getViewBox().viewRange()[1][0] >= span
                                for p, span in zip(live.trace_plots, live.min_span, strict=True)), timeout=10_000)
    assert live.min_span[0] == window.station.config.min_span["stroke_mm"] > 0
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "hydraulicsOnButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: window.status is not None and window.status.state == "IDLE", timeout=10_000)
    assert placeholders_shown()             # pressure on, nothing moving: still no cycle
    window.manual.sine_frequency.setValue(2.0)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "sineButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: not any(t.isVisible() for t in live.placeholders), timeout=30_000)
    assert live.loop_plot.getAxis("left").isVisible() and "J (mean of the last" in energy.text()
    # The loop's range is the loop's: it holds the force drawn, not an old range.
    (_, _), (y0, y1) = live.loop_plot.getViewBox().viewRange()
    assert y0 <= live.loop.yData.min() and live.loop.yData.max() <= y1
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "stopButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(placeholders_shown, timeout=30_000)


def test_a_rig_reached_by_address_that_says_it_is_a_simulator_gets_the_banner(qtbot, tmp_path, virtual_rig):
    sim = virtual_rig(speed=float(SPEED))
    window = open_window(qtbot, "--shaker", sim.modbus_url, "--daq", sim.daq_url, "--out", str(tmp_path))
    label = find(window, QtWidgets.QLabel, "simulatedLabel")
    assert not label.isVisible()                         # not started with --simulate: nothing known yet
    connected(qtbot, window)
    qtbot.waitUntil(label.isVisible, timeout=30_000)
    assert "identifies itself as a simulator" in label.text() and "SIMULATED RIG" in window.windowTitle()
    closed(qtbot, window)


def test_the_daq_line_gives_the_measured_pace_with_its_clock(qtbot):
    """Frames arriving in bursts from a 20x simulator: the line says the frames counted per
    wall-clock second and their pace against the rig's 2000 samples/s, near 20x, not a figure
    jumping with each burst; a stream that is not running says so, and a new one is measured afresh."""
    view = LiveView(2000.0, asked_pace=20.0)
    qtbot.addWidget(view)
    paces = []
    for i in range(40):                    # every 0.25 s, 10 000 frames ± a 3 000-frame burst
        view.show_health(Snapshot(None, None, received=i * 10_000 + (3_000 if i % 2 else 0), time=100 + i / 4,
                                  streaming=True))
        text = view.health.text()
        if i >= 9:
            assert "samples per wall-clock second" in text and "at 2000 samples/s of rig time" in text, text
            assert "asked for" not in text, text           # the measured pace is the one asked for
            paces.append(float(re.search(r"([\d.]+)× real time", text).group(1)))
    assert min(paces) >= 19 and max(paces) <= 21, paces
    view.show_health(Snapshot(None, None, received=5, time=111, streaming=True))    # a new stream: measured afresh
    assert "measuring over 2 s of wall clock" in view.health.text()
    view.show_health(Snapshot(None, None, received=5, time=112, streaming=False, session=True))
    assert "not streaming (the session streams while it holds, settles and captures" in view.health.text()
    for i in range(12):                    # a simulator that keeps up with 1.3x only: said beside the 20x asked
        view.show_health(Snapshot(None, None, received=i * 650, time=200 + i / 4, streaming=True))
    assert "1.3× real time" in view.health.text() and "asked for 20×" in view.health.text()


def test_a_controller_lost_mid_run_keeps_the_daq_and_ends_in_a_safe_stop_said_incomplete(qtbot, tmp_path,
                                                                                        relaxed_config):
    """The controller's Modbus server goes away during an experiment and does not come back:
    the console says so in one short line (the driver's words in the log), shows the
    operator's Abort under way, and after the session's end says that its safe stop did not
    complete, keeps the DAQ's traces live (the one independent proof of rest) and offers
    no session until the controller is read again."""
    config = tmp_path / "rig-quick-reconnect.toml"
    config.write_text(relaxed_config.read_text().replace("reconnect_s = 20.0", "reconnect_s = 3.0"))
    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--experiments", "j", "--out", str(tmp_path),
                         "--rig-config", str(config), "--fault", "modbus-down@run+5=100000")
    connected(qtbot, window)
    window.plan.identify.setChecked(False)
    qtbot.mouseClick(find(window, QtWidgets.QPushButton, "runPlanButton"), QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: window.station.sessions.running and window.link_error is not None, timeout=HANG_MS)
    strip, banner = find(window, QtWidgets.QLabel, "stateStrip"), find(window, QtWidgets.QLabel, "alarmBanner")
    state = find(window, QtWidgets.QLabel, "controller_state")
    for label in (strip, banner, state):
        assert "Modbus Error" not in label.text() and "ModbusTcpClient" not in label.text(), label.text()
    assert "Modbus Error" in window.log.toPlainText()           # the driver's words: in the log only
    assert "hard-wired E-stop" in banner.text()
    assert "should stop the shaker within 2 s" in find(window, QtWidgets.QLabel, "controller_watchdog").text()
    assert window.minimumSizeHint().width() <= 1280
    # No excitation read: no loop energy of an older one beside it (the stream may have stopped).
    qtbot.waitUntil(lambda: "no cycle yet" in find(window, QtWidgets.QLabel, "loopEnergy").text(), timeout=HANG_MS)

    abort = find(window, QtWidgets.QPushButton, "abortButton")
    qtbot.mouseClick(abort, QtCore.Qt.MouseButton.LeftButton)
    experiments = find(window, QtWidgets.QTableWidget, "experimentTable")
    assert not abort.isEnabled() and abort.text() == "Stopping…"
    if window.station.sessions.running:                 # the session may have ended on its own meanwhile
        assert "safe stop under way" in experiments.item(0, 4).text()
        assert experiments.item(0, 5).text() == ""      # no time left while stopping
        # the controller is not answering: the stop is asked for, its steps not said to be under way
        eta = find(window, QtWidgets.QLabel, "sessionEta").text()
        assert eta.startswith("Safe stop asked for") and "not confirmed" in eta, eta

    qtbot.waitUntil(lambda: not window.station.sessions.running, timeout=HANG_MS)
    qtbot.waitUntil(lambda: strip.text().startswith("SAFE STOP INCOMPLETE"), timeout=HANG_MS)
    assert "HYDRAULICS MAY BE ON" in strip.text()
    assert "SAFE STOP DID NOT COMPLETE" in banner.text() and "hard-wired E-stop" in banner.text()
    assert "within 0 s" not in window.log.toPlainText()
    # The controller is gone, the DAQ is not: the console reads it alone and the traces go on.
    qtbot.waitUntil(lambda: "the DAQ alone is read" in find(window, QtWidgets.QLabel, "linkLabel").text(),
                    timeout=HANG_MS)
    assert window.station.manual.daq is not None and window.station.manual.shaker is None
    qtbot.waitUntil(lambda: window.live.history.n > 0 and "× real time" in window.live.health.text(),
                    timeout=HANG_MS)
    disabled = motion_disabled(window)
    assert {"runPlanButton", "resumeButton", "hydraulicsOnButton"} <= set(disabled), disabled
    assert window.minimumSizeHint().width() <= 1280

    # Nothing reads the controller: no reset is offered that nothing could check, and the banner says why.
    reset = find(window, QtWidgets.QPushButton, "resetButton")
    assert not reset.isEnabled() and "not answering" in reset.toolTip()
    assert "Reset…" not in banner.text() and "nothing confirms the rig at rest" in banner.text()
    closed(qtbot, window)



def test_a_status_read_that_does_not_come_back_is_not_shown_as_the_rigs_state(qtbot, tmp_path):
    """A status read waits on the link while a command reconnects (up to the reconnect time):
    the last answer must not stand on the strip as the rig's state meanwhile.  The poller is
    stopped here, as a read stuck on the link stops it."""
    from rig.gui.main_window import SILENT

    window = open_window(qtbot, "--simulate", "--speed", SPEED, "--out", str(tmp_path))
    connected(qtbot, window)
    strip = find(window, QtWidgets.QLabel, "stateStrip")
    qtbot.waitUntil(lambda: "HYDRAULICS OFF" in strip.text(), timeout=HANG_MS)
    window.station.poller.close()
    qtbot.waitUntil(lambda: window.status is None, timeout=HANG_MS)
    assert window.link_error == SILENT and strip.text().startswith("NOT READ") and "HYDRAULICS ?" in strip.text()
    assert find(window, QtWidgets.QLabel, "controller_state").text() == "no answer"
    assert "runPlanButton" in motion_disabled(window)
    closed(qtbot, window)
