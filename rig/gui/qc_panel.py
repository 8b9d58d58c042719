"""QC mode: the unit's serial number, Test unit, and the verdict in letters large enough
to read from the rig — PASS, FAIL or RETEST — which stays until the next unit is tested.
While it is tested, a progress bar with the rig time left; after, the characteristics as a
table (value ± kσ, limits, acceptance limits, outcome, each number with its unit, as
rig.qc.present formats them), the likely causes in full and a link to the report."""

from __future__ import annotations

from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from rig.gui.qc import ORIGINS, SHOWN, QcDone, QcProgress, QcRequest
from rig.qc import DEFAULT_SPEC
from rig.qc.present import verdict_colours

TESTING = ("#e3f2fd", "#0d47a1")                     # (background, text) while a unit is tested
OUTCOME_SHOWN = {word: outcome for outcome, word in SHOWN.items()}   # RETEST → INCONCLUSIVE
COLUMNS = ("Characteristic", "Value ± kσ", "Limits (spec)", "Acceptance limits", "Outcome")


class QcPanel(QtWidgets.QWidget):
    testRequested = QtCore.Signal(object)      # QcRequest
    abortRequested = QtCore.Signal()

    def __init__(self, out: Path, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.out = out
        self.last: QcDone | None = None
        form = QtWidgets.QFormLayout()
        self.serial = QtWidgets.QLineEdit()
        self.serial.setObjectName("qcSerial")
        self.serial.setPlaceholderText("scan or type the unit's serial number")
        self.serial.returnPressed.connect(self._test)
        form.addRow("Serial number", self.serial)
        self.spec = QtWidgets.QLineEdit(DEFAULT_SPEC)
        self.spec.setObjectName("qcSpec")
        self.spec.setToolTip(f"{DEFAULT_SPEC} (the default), a shipped spec's name, or a QC.toml spec file")
        form.addRow("Spec", self.spec)
        self.operator = QtWidgets.QLineEdit()
        self.operator.setPlaceholderText("default: the login name")
        form.addRow("Operator", self.operator)
        self.folder = QtWidgets.QLineEdit(str(out / "qc"))
        self.folder.setObjectName("qcFolder")
        self.folder.setToolTip("the station's folder: a session folder per unit, and qc-records.sqlite")
        form.addRow("Station folder", self.folder)

        buttons = QtWidgets.QHBoxLayout()
        self.test_button = QtWidgets.QPushButton("Test unit")
        self.test_button.setObjectName("qcTestButton")
        self.test_button.clicked.connect(self._test)
        self.retest_button = QtWidgets.QPushButton("Retest")
        self.retest_button.setObjectName("qcRetestButton")
        self.retest_button.setToolTip("the same unit with the spec's retest periods (an INCONCLUSIVE's remedy)")
        self.retest_button.clicked.connect(self._retest)
        self.retest_button.setEnabled(False)
        self.abort_button = QtWidgets.QPushButton("Abort (safe stop)")
        self.abort_button.setObjectName("qcAbortButton")
        self.abort_button.clicked.connect(self.abortRequested.emit)
        self.abort_button.setEnabled(False)
        for b in (self.test_button, self.retest_button, self.abort_button):
            buttons.addWidget(b)

        self.unit = QtWidgets.QLabel("")
        self.unit.setObjectName("qcUnit")
        self.unit.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.unit.setStyleSheet("font-size: 13pt; font-weight: bold")
        self.verdict = QtWidgets.QLabel("—")
        self.verdict.setObjectName("verdictLabel")
        self.verdict.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.verdict.setMinimumHeight(90)
        self.reason = QtWidgets.QLabel("No unit tested yet.")
        self.reason.setObjectName("qcReason")
        self.reason.setWordWrap(True)
        self.report = QtWidgets.QLabel("")
        self.report.setObjectName("qcReportLink")
        self.report.setOpenExternalLinks(True)
        self.report.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextBrowserInteraction)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setObjectName("qcProgress")
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(True)
        self.progress.setFormat("%p %")
        self.progress.setVisible(False)
        self.step = QtWidgets.QLabel("")
        self.step.setObjectName("qcStep")
        self.step.setWordWrap(True)
        self.trace = QtWidgets.QLabel("")
        self.trace.setObjectName("qcTrace")
        self.trace.setWordWrap(True)            # operator, spec revision and hash, k: beside the values
        self.causes = QtWidgets.QLabel("")
        self.causes.setObjectName("qcCauses")
        self.causes.setWordWrap(True)           # the likely cause in full, never clipped
        self.causes.setStyleSheet("font-weight: bold; color: #c62828")
        self.table = QtWidgets.QTableWidget(0, len(COLUMNS))
        self.table.setObjectName("qcTable")
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setWordWrap(True)
        self.table.verticalHeader().setVisible(False)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.Stretch)
        for i in range(1, len(COLUMNS)):
            header.setSectionResizeMode(i, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.table.setVerticalScrollMode(QtWidgets.QAbstractItemView.ScrollMode.ScrollPerPixel)

        layout = QtWidgets.QVBoxLayout(self)
        layout.addLayout(form)
        layout.addLayout(buttons)
        layout.addWidget(self.unit)
        layout.addWidget(self.verdict)
        layout.addWidget(self.reason)
        layout.addWidget(self.step)
        layout.addWidget(self.progress)
        layout.addWidget(self.causes)
        layout.addWidget(self.report)
        layout.addWidget(self.trace)
        layout.addWidget(self.table, 1)
        none = verdict_colours(None)
        self._paint("—", (none.banner, none.banner_text))

    def _request(self, periods: int | None = None) -> QcRequest:
        return QcRequest(self.serial.text().strip(), self.spec.text().strip() or DEFAULT_SPEC,
                         Path(self.folder.text().strip() or str(self.out / "qc")),
                         self.operator.text().strip() or None, periods)

    def _test(self) -> None:
        if self.test_button.isEnabled():
            self.testRequested.emit(self._request())

    def _retest(self) -> None:
        if self.last is not None and self.last.retest_periods:
            self.serial.setText(self.last.serial)
            self.testRequested.emit(self._request(self.last.retest_periods))

    def set_running(self, running: bool) -> None:
        self.test_button.setEnabled(not running)
        self.abort_button.setEnabled(running)
        self.retest_button.setEnabled(not running and self.last is not None and bool(self.last.retest_periods))

    def show_started(self, request: QcRequest) -> None:
        """The next unit: the last verdict goes only now."""
        self.last = None
        self.unit.setText(f"Unit {request.serial}" + (f" — retest, {request.periods} periods" if request.periods
                                                      else ""))
        self._paint("TESTING…", TESTING, size_pt=36)
        self.reason.setText("The spec's plan runs, then identification and judging: the same test as "
                            "python -m rig qc run, in this console's session.")
        self.report.setText("")
        self.causes.setText("")
        self.trace.setText("")
        self.table.setRowCount(0)
        self.progress.setValue(0)
        self.step.setText("starting: the spec's checks, then the links")
        self.step.setVisible(True)
        self.progress.setVisible(True)
        self.set_running(True)

    def show_progress(self, progress: QcProgress) -> None:
        self.progress.setValue(round(1000 * progress.fraction))
        # no time left while a link is lost, as the plan tab and the terminal (one progress: the session's)
        left = " — time left not known while a link is lost" if progress.rig_left_s is None else \
            f" — about {int(progress.rig_left_s // 60)}:{int(progress.rig_left_s % 60):02d} m:s of rig time left"
        basis = (f" (predicted again after {progress.predicted_after} from the parameters identified so far)"
                 if progress.predicted_after else " (the session's prediction for a nominal unit)"
                 if progress.rig_left_s is not None else "")
        self.step.setText(f"{progress.text}{left}{basis}")

    def show_done(self, done: QcDone) -> None:
        self.last = done
        self.unit.setText(f"Unit {done.serial}")
        # The verdict itself says SIMULATED: the line below it is easily missed across the room.
        shown = (f"{done.shown}<div style='font-size: 16pt'>SIMULATED — not a production verdict</div>"
                 if done.simulated else done.shown)
        colours = verdict_colours(OUTCOME_SHOWN.get(done.shown))   # no verdict (ABORTED, ERROR…): grey
        self._paint(shown, (colours.banner, colours.banner_text), size_pt=48)
        reason = {"PASS": "Every characteristic within its limits, uncertainty included.",
                  "FAIL": "At least one characteristic outside its limits, uncertainty included.",
                  "RETEST": "Inconclusive: a characteristic's uncertainty straddles a limit. Test again with "
                            f"more periods ({done.retest_periods or 'the spec’s retest'} periods): Retest."}
        self.reason.setText(reason.get(done.shown, f"No verdict: {done.reason}"))
        if done.report is not None:
            self.report.setText(f'<a href="{done.report.resolve().as_uri()}">Open the report</a> — {done.report}')
        else:
            self.report.setText("")
        self.progress.setVisible(False)
        self.step.setText("")
        self.step.setVisible(False)
        lines = [f"Likely cause: {c}" for c in done.causes] + ([f"Remedy: {done.remedy}"] if done.remedy else [])
        if done.simulated:
            lines.append("SIMULATED: measured on a simulator, not a production record")
        self.causes.setText("\n".join(lines))
        self.trace.setText(done.trace)
        self._fill(done)
        self.set_running(False)

    def _fill(self, done: QcDone) -> None:
        self.table.setRowCount(len(done.rows))
        for i, row in enumerate(done.rows):
            # what is a prediction of the identified model (a drop test) says so beside its name
            title = row.title + (f" ({row.origin})" if row.origin else "")
            for j, text in enumerate((title, row.value, row.limits, row.acceptance, row.outcome)):
                item = QtWidgets.QTableWidgetItem(text)
                if j:
                    item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
                if j == 4:
                    font = item.font()
                    font.setBold(True)
                    item.setFont(font)
                    item.setForeground(QtGui.QColor(verdict_colours(text).text))
                if j == 1 and row.sigma:
                    item.setToolTip(f"σ {row.sigma}")
                if j == 0 and row.origin:
                    item.setToolTip(f"{row.origin}: {ORIGINS[row.origin]}")
                self.table.setItem(i, j, item)
        QtCore.QTimer.singleShot(0, self._fit_rows)

    def _fit_rows(self) -> None:
        """Every row whole: wrapped to the columns' widths, the table as tall as its rows."""
        self.table.resizeRowsToContents()
        rows = sum(self.table.rowHeight(i) for i in range(self.table.rowCount()))
        self.table.setMinimumHeight(rows + self.table.horizontalHeader().height() + 2 * self.table.frameWidth() + 2)

    def resizeEvent(self, event: QtGui.QResizeEvent) -> None:  # noqa: N802 — Qt's name
        super().resizeEvent(event)
        if self.table.rowCount():
            QtCore.QTimer.singleShot(0, self._fit_rows)

    def _paint(self, text: str, colours: tuple[str, str], size_pt: int = 64) -> None:
        background, colour = colours
        self.verdict.setText(text)
        self.verdict.setStyleSheet(f"background: {background}; color: {colour}; font-size: {size_pt}pt; "
                                   "font-weight: bold; border-radius: 10px; padding: 8px")
