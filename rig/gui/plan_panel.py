"""The plan runner: which plan and experiments, where the session goes, identification
after it; the table of experiments with their state and time left; Run, Abort (a safe
stop) and Resume; and the steady-state indicator of the experiment settling now.

One source per number: the table's state, the settling count, the capture's progress and
the times left are drawn together, from the session's one progress
(:class:`~rig.session.session_progress.SessionProgress`, through :class:`PlanProgress`),
in the same frame as each event that changes them.  Every time says its clock and its unit."""

from __future__ import annotations

import datetime as _dt
import math
import threading
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from identify.notation import at_place, significant
from rig.config import CHANNELS, RigConfig
from rig.events import Event
from rig.gui.plan_state import PlanProgress
from rig.gui.state_strip import short_link_error
from rig.planning.criterion import DAQ_LAG_S
from rig.planning.plans import Plan, comma_list, load_plan
from rig.session.session_progress import ACTIVE, ExperimentProgress

STATUS_COLOURS = {"done": "#c8e6c9", "failed": "#ffcdd2", "aborted": "#ffcdd2", "skipped": "#ffe0b2",
                  "interrupted": "#ffe0b2", "moving": "#e3f2fd", "settling": "#fff9c4", "capturing": "#bbdefb",
                  "stopping": "#e3f2fd"}
UNITS = {"stroke_mm": "mm", "force_N": "N", "pressure_bar": "bar", "gas_temperature_C": "°C"}
TABLE_COLUMNS = ("exp.", "static\n[mm]", "ampl.\n[mm]", "freq.\n[Hz]", "state", "left\n[rig m:s]")
# Under the drift criterion the changes are for information: grey under their threshold, pale orange over it, never
# green, so that a column of bars under their thresholds does not read as a pass the deciding bound has not given.
INFO_UNDER, INFO_OVER = "#cfd8dc", "#ffb74d"
DRIFT_PASS, DRIFT_WAIT = "#2e7d32", "#e65100"
ENDED_CHARS = 160                 # of a session's end status under the table


def _clock(seconds: float) -> str:
    """m:ss, or h:mm:ss from an hour on (the unit is the caller's to say)."""
    if math.isnan(seconds):
        return "–"
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def clock_text(seconds: float, clock: str) -> str:
    """A duration with its clock and unit: "rig time 3:12 m:s", "wall 0:09 m:s"."""
    unit = "h:m:s" if not math.isnan(seconds) and round(seconds) >= 3600 else "m:s"
    return f"{clock} {_clock(seconds)} {unit}"


def capture_text(row: ExperimentProgress) -> str:
    """A capture's progress in periods, from the row's fraction (the acquisition's event)."""
    periods = row.spec.periods if row.spec is not None else 1
    period = min(int(row.fraction * periods) + 1, periods)
    return f"capturing period {period} of {periods} ({100 * row.fraction:.0f} % of the capture)"


def _item(table: QtWidgets.QTableWidget, row: int, col: int) -> QtWidgets.QTableWidgetItem:
    item = table.item(row, col)
    assert item is not None  # every cell is filled when the table is laid out
    return item


class SteadyStateView(QtWidgets.QGroupBox):
    """Per channel the cycle-to-cycle change of the mean against its threshold, the
    settling cycles so far and the cycles predicted to be left.  Under the drift
    criterion its bias bound decides the capture: it is shown as the deciding line, and
    the changes, for information, without the verdict colours of thresholds that do not
    apply (orange 12x over a threshold read as far from steady while the bound was
    passing)."""

    def __init__(self, config: RigConfig, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QtWidgets.QVBoxLayout(self)
        # The deciding line first, above the changes that are for information only.
        self.bound = QtWidgets.QLabel("")
        self.bound.setObjectName("driftBound")
        self.bound.setWordWrap(True)
        layout.addWidget(self.bound)
        self.table = QtWidgets.QTableWidget(len(CHANNELS), 3)
        self.table.setObjectName("steadyStateTable")
        self.table.setHorizontalHeaderLabels(["change / cycle", "threshold", "÷ threshold"])
        self.table.setVerticalHeaderLabels(["stroke", "force", "pressure", "temperature"])
        self.table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setFixedHeight(150)
        self.bars: list[QtWidgets.QProgressBar] = []
        for i in range(len(CHANNELS)):
            self.table.setItem(i, 0, QtWidgets.QTableWidgetItem("–"))
            self.table.setItem(i, 1, QtWidgets.QTableWidgetItem(""))
            bar = QtWidgets.QProgressBar()
            bar.setRange(0, 300)              # change ÷ threshold up to 3, in hundredths
            bar.setFormat("–")
            bar.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            self.bars.append(bar)
            self.table.setCellWidget(i, 2, bar)
        layout.addWidget(self.table)
        self.cycles = QtWidgets.QLabel("Settling: –")
        self.cycles.setWordWrap(True)
        self.cycles.setObjectName("settleCycles")
        layout.addWidget(self.cycles)
        self.configure(config)

    def configure(self, config: RigConfig) -> None:
        """The criterion and thresholds of the session shown (a QC spec brings its own)."""
        self.config = config
        ss = config.steady_state
        self.drift = ss.drift if ss.criterion == "drift" else None
        self.setTitle("Steady state (drift criterion decides; changes for information)" if self.drift
                      else "Steady state (change criterion)")
        for i, c in enumerate(CHANNELS):
            _item(self.table, i, 1).setText(f"{ss.thresholds[c]:g} {UNITS[c]}")
        self.table.setHorizontalHeaderLabels(["change / cycle", "threshold",
                                              "÷ threshold (info)" if self.drift else "÷ threshold"])
        self.bound.setText("")
        self.bound.setVisible(self.drift is not None)

    def clear(self) -> None:
        """No experiment settles now: no change of an ended one is shown as if current."""
        for i, bar in enumerate(self.bars):
            _item(self.table, i, 0).setText("–")
            bar.setValue(0)
            bar.setFormat("–")
            bar.setProperty("colour", None)
            bar.setStyleSheet("")
        self.bound.setText("")

    def show_row(self, row: ExperimentProgress | None) -> None:
        """The changes against their thresholds at the row's last settling report."""
        if row is None or not row.settling:
            return
        ss = self.config.steady_state
        change = row.settling[-1][1]
        for i, c in enumerate(CHANNELS):
            x, limit = change.get(c, math.nan), ss.thresholds[c]
            # A tenth of the threshold is the last digit that means anything to the criterion.
            shown = at_place(x, math.floor(math.log10(limit)) - 1) if math.isfinite(x) else "–"
            _item(self.table, i, 0).setText(f"{shown} {UNITS[c]}")
            ratio = x / limit
            bar = self.bars[i]
            bar.setValue(int(min(ratio, 3.0) * 100))
            bar.setFormat(significant(ratio))
            if self.drift:
                colour = INFO_UNDER if ratio < 1 else INFO_OVER
            else:
                colour = "#43a047" if ratio < 1 else "#fb8c00"
            if bar.property("colour") != colour:     # a style sheet is costly to apply: only on a change
                bar.setProperty("colour", colour)
                bar.setStyleSheet(f"QProgressBar::chunk {{ background: {colour}; }}")
        if self.drift:
            bound = change.get("bias_sigma")
            passed = bound is not None and bound < self.drift.fraction
            verdict = ("steady by the drift criterion" if passed else "NOT STEADY yet by the drift criterion"
                       if bound is not None else "drift criterion")
            self.bound.setText(f"{verdict} (it decides): " + (
                f"the transient left could bias the fit by up to {significant(bound)} σ; captures below "
                f"{self.drift.fraction:g} σ" if bound is not None else "waiting for the first blocks"))
            self.bound.setStyleSheet(f"color: {DRIFT_PASS if passed else DRIFT_WAIT}; font-weight: bold")

    def show_count(self, row: ExperimentProgress | None, left: int | None = None) -> None:
        """The settling count and the cycles ``left`` (the session's progress has them), from the
        same row as the plan table."""
        ss = self.config.steady_state
        if row is None or row.status not in ("settling", "capturing") or not row.cycles:
            self.cycles.setText("Settling: –" if row is None else f"{row.label}: {row.status_text()}")
            return
        if row.status == "capturing":
            self.cycles.setText(f"{row.label}: settled after {row.cycles} cycles; {capture_text(row)}")
            return
        after_run = ss.ramp_time_s + DAQ_LAG_S
        self.cycles.setText(f"{row.label}: settling {row.cycles} cycles, counted from {after_run:g} s (rig time) "
                            f"after RUN (min {ss.min_cycles}, max {ss.max_cycles}); "
                            f"predicted cycles left: {'?' if left is None else left}")


class PlanPanel(QtWidgets.QWidget):
    runRequested = QtCore.Signal()
    resumeRequested = QtCore.Signal(str)
    abortRequested = QtCore.Signal()
    _previewed = QtCore.Signal(int, object, object)     # preview number, Plan, PlanProgress or why not (its thread)

    def __init__(self, config: RigConfig, plan: str, experiments: str | None, out: Path,
                 parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.config, self.out = config, out
        self.progress: PlanProgress | None = None
        self.stopping: str | None = None          # why the running session's safe stop was asked for
        self._rows: list[ExperimentProgress] = []
        self._preview_number = 0
        self._previewed.connect(self._show_preview)
        form = QtWidgets.QFormLayout()
        plan_row = QtWidgets.QHBoxLayout()
        self.plan = QtWidgets.QLineEdit(plan)
        self.plan.setObjectName("planEdit")
        self.plan.setToolTip("standard, or a plan TOML file")
        browse = QtWidgets.QPushButton("…")
        browse.setFixedWidth(30)
        browse.clicked.connect(self._browse_plan)
        plan_row.addWidget(self.plan, 1)
        plan_row.addWidget(browse)
        form.addRow("Plan", plan_row)
        self.experiments = QtWidgets.QLineEdit(experiments or "")
        self.experiments.setObjectName("experimentsEdit")
        self.experiments.setPlaceholderText("all (or letters: a,h,j)")
        self.experiments.editingFinished.connect(self.preview)
        self.plan.editingFinished.connect(self.preview)
        form.addRow("Experiments", self.experiments)
        self.folder = QtWidgets.QLineEdit()
        self.folder.setObjectName("sessionFolderEdit")
        self.folder_label = QtWidgets.QLabel("Session folder")
        self.finished: str | None = None          # the finished session's folder the field still shows
        form.addRow(self.folder_label, self.folder)
        self.identify = QtWidgets.QCheckBox("Identify after the capture (2-dof: θ4, θ6, θ16)")
        self.identify.setObjectName("identifyBox")
        self.identify.setChecked(True)
        form.addRow("", self.identify)

        buttons = QtWidgets.QHBoxLayout()
        self.run_button = QtWidgets.QPushButton("Run plan")
        self.run_button.setObjectName("runPlanButton")
        self.run_button.clicked.connect(self.runRequested)
        self.abort_button = QtWidgets.QPushButton("Abort (safe stop)")
        self.abort_button.setObjectName("abortButton")
        self.abort_button.setEnabled(False)
        self.abort_button.clicked.connect(self.abortRequested)
        self.resume_button = QtWidgets.QPushButton("Resume…")
        self.resume_button.setObjectName("resumeButton")
        self.resume_button.setToolTip("continue an interrupted session folder")
        self.resume_button.clicked.connect(self._browse_resume)
        for b in (self.run_button, self.abort_button, self.resume_button):
            buttons.addWidget(b)

        self.table = QtWidgets.QTableWidget(0, len(TABLE_COLUMNS))
        self.table.setObjectName("experimentTable")
        self.table.setHorizontalHeaderLabels(TABLE_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(4, QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.table.setMinimumHeight(120)         # the header and three experiments at least
        self.eta = QtWidgets.QLabel("")
        self.eta.setObjectName("sessionEta")
        self.eta.setWordWrap(True)
        self.capture = QtWidgets.QProgressBar()
        self.capture.setObjectName("captureProgress")
        self.capture.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.capture.setVisible(False)
        self.capture.setStyleSheet("QProgressBar { font-weight: bold; min-height: 24px } "
                                   "QProgressBar::chunk { background: #64b5f6; }")
        self.steady = SteadyStateView(config)
        # Its own height always: a long status line above takes it from the table, never from it.
        self.steady.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred, QtWidgets.QSizePolicy.Policy.Fixed)

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addLayout(form)
        layout.addLayout(buttons)
        layout.addWidget(self.table, 1)
        layout.addWidget(self.eta)
        layout.addWidget(self.capture)
        layout.addWidget(self.steady)
        self.new_folder()
        self.preview()

    # ----- choosing --------------------------------------------------------------------------------
    def letters(self) -> list[str] | None:
        return comma_list(self.experiments.text())

    def new_folder(self) -> None:
        stamp = _dt.datetime.now().strftime("%y%m%d-%H%M%S")
        self.folder.setText(str(self.out / f"session-{stamp}"))
        self.finished = None
        self.folder_label.setText("Session folder")

    def session_ended(self, folder: Path) -> None:
        """The field goes on showing the session that ended (the fit shown is of it), until
        Run asks for the next one (:meth:`run_folder`)."""
        self.folder.setText(str(folder))
        self.finished = str(folder)
        self.folder_label.setText("Last session")
        self.folder.setToolTip("the session that ended; Run starts the next one in a new folder")

    def run_folder(self) -> Path:
        """Where Run writes: a new folder unless the operator typed one."""
        if self.finished is not None and self.folder.text().strip() == self.finished:
            self.new_folder()
        return Path(self.folder.text().strip())

    def _browse_plan(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Plan", "", "Plan (*.toml)")
        if path:
            self.plan.setText(path)
            self.preview()

    def _browse_resume(self) -> None:
        path = QtWidgets.QFileDialog.getExistingDirectory(self, "Session folder to resume", str(self.out))
        if path:
            self.resumeRequested.emit(path)

    def preview(self) -> None:
        """The chosen plan's experiments, all pending, before anything runs.  Their times
        come from a thread: predicting the standard plan's settling is seconds of Python
        (rig.planning.settling), which in the GUI thread would freeze the window at every edit."""
        if self.progress is not None and self.progress.ended is None:
            return
        try:
            plan = load_plan(self.plan.text().strip() or "standard").select(self.letters())
        except Exception as exc:  # noqa: BLE001 — the plan is checked again, with its reasons, on Run
            self.eta.setText(f"plan: {exc}")
            return
        self._preview_number += 1
        number = self._preview_number
        self.eta.setText(f"{len(plan.experiments)} experiments; estimating the rig time…")
        threading.Thread(target=self._estimate, args=(number, plan), name="plan-preview", daemon=True).start()

    def _estimate(self, number: int, plan: Plan) -> None:
        """The preview's times, in its thread: the one prediction (rig.planning.prediction)."""
        result: PlanProgress | str
        try:
            result = PlanProgress.preview(plan, self.config)
        except Exception as exc:  # noqa: BLE001 — said where the times would be; Run checks the plan again
            result = f"plan: its rig time could not be predicted ({type(exc).__name__}: {exc})"
        try:
            self._previewed.emit(number, plan, result)
        except RuntimeError:      # the panel was closed while the times were computed: nobody to show them to
            return

    def _show_preview(self, number: int, plan: Plan, progress: PlanProgress | str) -> None:
        if number != self._preview_number or (self.progress is not None and self.progress.ended is None):
            return          # a later edit, or a session started meanwhile
        if isinstance(progress, str):
            self.eta.setText(progress)
            return
        self.show_progress(progress)
        self.progress = None
        self.eta.setText(f"{len(plan.experiments)} experiments as listed, about "
                         f"{clock_text(progress.estimate_s, 'rig time')} ({progress.basis})")

    # ----- running ---------------------------------------------------------------------------------
    def set_running(self, running: bool) -> None:
        self.stopping = None
        self.abort_button.setText("Abort (safe stop)")
        self.run_button.setEnabled(not running)
        self.resume_button.setEnabled(not running)
        self.abort_button.setEnabled(running)
        for w in (self.plan, self.experiments, self.folder, self.identify):
            w.setEnabled(not running)

    def show_stopping(self, why: str) -> None:
        """The session's safe stop is under way: Abort has been pressed (or the session ends
        on its own), so no time left is shown and Abort is not offered again."""
        if self.progress is None or self.progress.ended is not None or self.stopping is not None:
            return
        self.stopping = short_link_error(why)
        self.abort_button.setEnabled(False)
        self.abort_button.setText("Stopping…")
        self.refresh()

    def show_progress(self, progress: PlanProgress) -> None:
        self.progress = progress
        self.steady.configure(progress.config)
        self._rows = progress.rows
        self.table.setRowCount(len(progress.rows))
        for i, r in enumerate(progress.rows):
            spec = r.spec
            assert spec is not None    # a plan's rows carry their experiment
            cells = (r.label, f"{spec.static_position_mm:g}", f"{spec.amplitude_mm:g}", f"{spec.frequency_hz:g}")
            for j, text in enumerate(cells):
                item = QtWidgets.QTableWidgetItem(text)
                if j:
                    item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
                self.table.setItem(i, j, item)
            self.table.setItem(i, 4, QtWidgets.QTableWidgetItem(""))
            self.table.setItem(i, 5, QtWidgets.QTableWidgetItem(""))
        self.refresh()

    def apply(self, event: Event) -> None:
        if self.progress is None:
            return
        row = self.progress.apply(event)
        if row is not None and event.kind == "progress" and event.data.get("phase") == "settling":
            self.steady.show_row(row)
        if event.kind == "session-end":
            self.steady.clear()
        if row is not None or event.kind == "session-end":
            self.refresh()

    def refresh(self) -> None:
        """Statuses and times left (called on the window's timer)."""
        progress = self.progress
        if progress is None:
            return
        # Not read, or not being told: the link is lost (the bus says so) or the status poll has no answer.
        silent = progress.unread is not None or bool(progress.session.gone)
        for i, r in enumerate(progress.rows):
            status = _item(self.table, i, 4)
            unread = silent and r.status in ("moving", "settling", "capturing", "stopping")
            stopping = self.stopping is not None and progress.ended is None and r.status in ACTIVE
            text = f"safe stop under way (was {r.status_text()})" if stopping else r.status_text()
            # the count stands where it was last read: said so, beside "Settling: –" below
            status.setText(text + (" when last read — the controller is not answering" if unread else ""))
            status.setBackground(QtGui.QColor(STATUS_COLOURS["stopping" if stopping else r.status]
                                              if (stopping or r.status in STATUS_COLOURS) else "#ffffff"))
            # no time left while stopping, nor while the controller is not read (the count stands still)
            _item(self.table, i, 5).setText("" if r.status == "done" or stopping else "–" if unread
                                            else _clock(progress.rig_left_s(r)))
        current = progress.current
        stopping = self.stopping is not None and progress.ended is None
        if stopping or (silent and progress.ended is None):
            # The last report's changes are not the rig's now: no table of them beside a count that stands still.
            self.steady.clear()
            self.steady.cycles.setText("Settling: – (the session's safe stop is under way)" if stopping else
                                       "Settling: – (not counted while the controller is not answering)")
        else:
            self.steady.show_count(current, progress.cycles_left(current) if current is not None else None)
        capturing = current is not None and current.status == "capturing" and self.stopping is None
        self.capture.setVisible(capturing)
        if current is not None and capturing:
            self.capture.setValue(int(round(100 * current.fraction)))
            self.capture.setFormat(f"{current.label}: {capture_text(current)}")
        if stopping and silent:
            watchdog = self.config.limits.watchdog_timeout_s
            self.eta.setText(f"Safe stop asked for ({self.stopping}); the controller is not answering, so its fade "
                             f"out, STOP and hydraulics off are not confirmed: its watchdog stops the shaker "
                             f"{watchdog:g} s after its last message. No time left is shown")
            self.eta.setToolTip("")
        elif stopping:
            self.eta.setText(f"Safe stop under way ({self.stopping}): fade out, STOP, hydraulics off; no time left "
                             "is shown until the session has ended")
            self.eta.setToolTip("")
        elif progress.ended is not None:
            # A status can run to several sentences (a safe stop's failures): its head here, the
            # whole of it in the tooltip and the log below, so the settling view keeps its height.
            whole = f"Session {progress.ended}"
            head = whole.split(" (", 1)[0]          # a driver's words in parentheses: the log's
            head = head if len(head) <= ENDED_CHARS else head[:ENDED_CHARS].rsplit(" ", 1)[0]
            self.eta.setText(whole if head == whole else f"{head} … (the whole status: the log below)")
            self.eta.setToolTip(whole)
        elif silent:
            self.eta.setText("Session: time left not known while the controller is not answering")
            self.eta.setToolTip("")
        else:
            wall, rig = progress.session_left_s(), progress.session_rig_left_s()
            self.eta.setText(f"Session: about {clock_text(wall or 0.0, 'wall')} left "
                             f"({clock_text(rig or 0.0, 'rig time')})"
                             + (f"; {current.label}: {clock_text(progress.rig_left_s(current), 'rig time')}"
                                if current else ""))
