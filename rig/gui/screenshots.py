"""``make screenshots``: the console's main views as PNG files at 1280 px, from a real
session on the simulated rig (offscreen): idle (connected, at rest), settling, a capture in progress, the
fit view with the 1-dof/2-dof comparison, the session browser, an alarm (an e-stop trip
during a manual sine), the console's E-STOP during a manual sine, a link lost mid-run (the
controller gone during an experiment, then the session's end), and QC mode at 1280 px (a
worn-orifice unit under test, then its FAIL).

    python -m rig.gui.screenshots [--out out/screenshots] [--speed 20] [--readme docs/gui.png]
                                  [--only session,alarm,estop,lost-link,qc]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from PySide6 import QtCore, QtWidgets  # noqa: E402

from rig.drivers.registers import ControllerState
from rig.gui.main_window import MainWindow, application  # noqa: E402

WIDTH = 1280     # px: every view at the narrowest screen the console is made for


def wait(what: str, condition: Callable[[], bool], timeout_s: float = 120.0) -> None:
    app = application()
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"screenshots: timed out waiting for {what}")
        app.processEvents()
        time.sleep(0.005)


def settle_view(seconds: float) -> None:
    """Let the window's timer draw for a moment."""
    end = time.monotonic() + seconds
    wait("the view", lambda: time.monotonic() > end)


def shoot(window: MainWindow, path: Path) -> Path:
    window.grab().save(str(path))
    print(f"wrote {path}")
    return path


def capturing(window: MainWindow, row: int) -> bool:
    """A capture under way, and the table saying so (what the screenshot must show): g's
    three periods at 0.2 Hz take 15 s of rig time, several of the console's status reads."""
    progress = window.plan.progress
    if progress is None or progress.rows[row].status != "capturing":
        return False
    item = window.plan.table.item(row, 4)
    return 0 < progress.rows[row].fraction < 1 and item is not None and item.text().startswith("capturing")


def manual_sine(window: MainWindow) -> None:
    """Hydraulics on, then a 20 mm sine at 1 Hz around 133 mm, from the Manual tab."""
    window.left_tabs.setCurrentIndex(1)
    wait("the connection", lambda: window.status is not None)
    window.manual.hyd_on.click()
    wait("hydraulics on", lambda: window.status is not None and window.status.state is ControllerState.IDLE)
    window.manual.sine_static.setValue(133.0)
    window.manual.sine_amplitude.setValue(20.0)
    window.manual.sine_frequency.setValue(1.0)
    window.manual.sine_button.click()


def closed(window: MainWindow) -> None:
    window.close()
    wait("the window to close", lambda: not window.isVisible(), 60)


def qc_view(speed: float, out: Path, sessions: Path) -> None:
    """QC mode at 1280 × 1024 px: a unit with a worn orifice tested as rig qc run tests it, while
    it settles, then its FAIL with the table and the likely cause."""
    qc = MainWindow.from_args(["--simulate", "--speed", f"{speed:g}", "--unit", "worn-orifice", "--out",
                               str(sessions)])
    qc.resize(WIDTH, 1024)
    qc.show()
    wait("the connection", lambda: qc.status is not None)
    qc.qc.serial.setText("SN-0042")
    qc.qc.test_button.click()
    # While the unit settles (its capture is a fraction of a second at 20x): the loops drawn,
    # the DAQ's rate measured on the session's stream.
    wait("the QC run's settling", lambda: "settling" in qc.qc.step.text() and "× real time" in qc.live.health.text()
         and not any(t.isVisible() for t in qc.live.placeholders), 600)
    settle_view(0.2)                       # the loops' axes laid out; a second more is the next phase
    shoot(qc, out / "qc-testing.png")
    wait("the QC verdict", lambda: qc.qc.last is not None, 900)
    wait("the console's links back", lambda: qc.station.manual.shaker is not None and qc.status is not None, 60)
    wait("the console's DAQ rate measured", lambda: "× real time" in qc.live.health.text(), 60)
    settle_view(1.0)
    shoot(qc, out / "qc-verdict.png")
    closed(qc)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="out/screenshots")
    parser.add_argument("--speed", type=float, default=20.0)
    parser.add_argument("--readme", help="also write a 1200-px-wide copy of the settling view here")
    parser.add_argument("--only", help=f"only these scenes, comma-separated ({', '.join(SCENES)})")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sessions = Path(tempfile.mkdtemp(prefix="gui-screenshots-"))
    scenes = args.only.split(",") if args.only else list(SCENES)
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        parser.error(f"--only: no scene {', '.join(unknown)} (the scenes: {', '.join(SCENES)})")
    application()
    for name in scenes:
        SCENES[name](args, out, sessions)
    print(f"sessions of this run: {sessions}")
    return 0


def session_views(args: argparse.Namespace, out: Path, sessions: Path) -> None:
    """idle, settling, capturing, fit and browser, from one session of j and g."""
    window = MainWindow.from_args(["--simulate", "--speed", f"{args.speed:g}", "--experiments", "j,g",
                                   "--out", str(sessions)])
    window.resize(WIDTH, 1000)
    window.show()
    wait("the connection", lambda: window.status is not None)
    wait("the DAQ's rate measured", lambda: "× real time" in window.live.health.text(), 60)
    settle_view(0.5)
    shoot(window, out / "idle.png")
    folder = Path(window.plan.folder.text())
    window.run_plan()
    wait("settling", lambda: window.plan.progress is not None and window.plan.progress.rows[0].cycles >= 40)
    settle_view(1.0)
    settling = shoot(window, out / "settling.png")
    if args.readme:
        window.grab().scaledToWidth(1200, QtCore.Qt.TransformationMode.SmoothTransformation).save(args.readme)
        print(f"wrote {args.readme}")
    wait("a capture in progress", lambda: capturing(window, 1))
    shoot(window, out / "capturing.png")
    wait("the fit", lambda: window.fit_view.result is not None, 300)
    window.compare()
    wait("the comparison", lambda: window.fit_view.comparison is not None, 300)
    settle_view(0.5)
    shoot(window, out / "fit.png")
    window.tabs.setCurrentWidget(window.browser)
    window.browser.open_folder(folder)
    settle_view(0.5)
    shoot(window, out / "browser.png")
    closed(window)
    print(f"first view {settling}")


def alarm_view(args: argparse.Namespace, out: Path, sessions: Path) -> None:
    """An alarm: the e-stop trips 10 s (simulated) into a manual sine."""
    alarm = MainWindow.from_args(["--simulate", "--speed", f"{args.speed:g}", "--fault", "estop@run+10",
                                  "--out", str(sessions)])
    alarm.resize(WIDTH, 1000)
    alarm.show()
    manual_sine(alarm)
    wait("the trip", lambda: alarm.status is not None and alarm.status.state is ControllerState.ALARM, 60)
    settle_view(1.0)
    shoot(alarm, out / "alarm.png")
    closed(alarm)


def estop_view(args: argparse.Namespace, out: Path, sessions: Path) -> None:
    """The console's E-STOP pressed during a manual sine: STOP and hydraulics off, latched."""
    estop = MainWindow.from_args(["--simulate", "--speed", f"{args.speed:g}", "--out", str(sessions)])
    estop.resize(WIDTH, 1000)
    estop.show()
    manual_sine(estop)
    wait("the sine", lambda: estop.status is not None and estop.status.state is ControllerState.RUNNING and
         estop.status.cycles >= 3, 60)
    estop.estop()
    wait("the E-STOP's writes", lambda: estop.station.emergency.wait(0) is not None, 30)
    wait("the controller off", lambda: estop.status is not None and estop.status.state is ControllerState.OFF, 30)
    settle_view(1.0)
    shoot(estop, out / "alarm-after-estop.png")
    closed(estop)


def lost_link_view(args: argparse.Namespace, out: Path, sessions: Path) -> None:
    """A link lost mid-run, at 1280 px: the controller's Modbus server goes away 20 s (rig
    time) into the experiment's run and does not come back; lost-link.png while the session
    waits for it, lost-link-stopping.png in its safe stop, lost-link-ended.png after the
    session has ended (aborted, the safe stop incomplete, the DAQ read alone)."""
    window = MainWindow.from_args(["--simulate", "--speed", f"{args.speed:g}", "--experiments", "j",
                                   "--fault", "modbus-down@run+20=100000", "--out", str(sessions)])
    window.resize(WIDTH, 1000)
    window.show()
    wait("the connection", lambda: window.status is not None)
    window.plan.identify.setChecked(False)
    window.run_plan()
    wait("the link lost", lambda: window.station.sessions.running and window.status is None
         and window.link_error is not None, 300)
    settle_view(1.5)
    shoot(window, out / "lost-link.png")
    wait("the safe stop", lambda: window.plan.stopping is not None or not window.station.sessions.running, 300)
    if window.station.sessions.running:
        settle_view(0.5)
        shoot(window, out / "lost-link-stopping.png")
    wait("the session's end", lambda: not window.station.sessions.running, 300)
    wait("the console's reconnect tried", lambda: "not connected" in window.link_label.text(), 120)
    wait("the DAQ read alone", lambda: "× real time" in window.live.health.text(), 60)
    settle_view(1.0)
    shoot(window, out / "lost-link-ended.png")
    closed(window)


SCENES: dict[str, Callable[[argparse.Namespace, Path, Path], None]] = {
    "session": session_views, "alarm": alarm_view, "estop": estop_view, "lost-link": lost_link_view,
    # At most 10x: at 20x the unit's settling is over before the DAQ line has measured its stream.
    "qc": lambda args, out, sessions: qc_view(min(args.speed, 10.0), out, sessions)}


if __name__ == "__main__":
    QtWidgets.QApplication.setApplicationName("damper-rig")
    sys.exit(main())
