"""The session browser: any session folder (made by ``rig run`` or by this console) or
dataset folder — its experiments and captured periods, session.log, the result and
report — and a re-fit with another model, start file or parameter set."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from identify.dataset import read_manifest
from identify.model import DEFAULT_ESTIMATE
from rig.gui.fit_view import fill_parameter_table, parameter_table
from rig.gui.fitting import IdentifySettings
from rig.gui.plotting import labelled
from rig.gui.units import GAS_PRESSURE_UNIT
from rig.session.progress import log_text

EXPERIMENT_COLUMNS = ("experiment", "f [Hz]", "static [mm]", "amplitude [mm]", "periods", "settle cycles",
                      "steady", "lost samples", "flags")
# (column, axis label, scale from the file's unit to the axis', colour): the live view's units and colours
PLOTTED = (("stroke_mm", "stroke [mm]", 1.0, "#1f77b4"), ("force_N", "force [kN]", 1e-3, "#d62728"),
           ("pressure_bar", f"gas p [{GAS_PRESSURE_UNIT}]", 1.0, "#2ca02c"),
           ("gas_temperature_C", "gas T [°C]", 1.0, "#9467bd"))
FLAGS_COLUMN = EXPERIMENT_COLUMNS.index("flags")


class SessionBrowser(QtWidgets.QWidget):
    refitRequested = QtCore.Signal(object, object)     # folder, IdentifySettings
    resumeRequested = QtCore.Signal(str)

    def __init__(self, start_folder: Path, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.start_folder = start_folder
        self.folder: Path | None = None
        self.entries: list[dict[str, Any]] = []
        self.resumable = False          # the folder shown is an unfinished session (the window gates the button)

        top = QtWidgets.QHBoxLayout()
        self.path = QtWidgets.QLineEdit()
        self.path.setObjectName("browserPath")
        self.path.setPlaceholderText("a session or dataset folder")
        self.path.returnPressed.connect(lambda: self.open_folder(Path(self.path.text())))
        open_button = QtWidgets.QPushButton("Open…")
        open_button.setObjectName("browserOpenButton")
        open_button.clicked.connect(self._choose)
        self.resume_button = QtWidgets.QPushButton("Resume this session")
        self.resume_button.setObjectName("browserResumeButton")
        self.resume_button.setEnabled(False)
        self.resume_button.clicked.connect(lambda: self.folder and self.resumeRequested.emit(str(self.folder)))
        top.addWidget(QtWidgets.QLabel("Folder"))
        top.addWidget(self.path, 1)
        top.addWidget(open_button)
        top.addWidget(self.resume_button)
        self.summary = QtWidgets.QLabel("Open a session folder (CLI or GUI) to see what it holds.")
        self.summary.setObjectName("browserSummary")
        self.summary.setWordWrap(True)

        self.table = QtWidgets.QTableWidget(0, len(EXPERIMENT_COLUMNS))
        self.table.setObjectName("browserExperiments")
        self.table.setHorizontalHeaderLabels(EXPERIMENT_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.table.horizontalHeader().setStretchLastSection(True)     # the last shown: flags when there are any
        self.table.itemSelectionChanged.connect(self._plot_selected)

        self.plot = pg.GraphicsLayoutWidget()
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.setObjectName("browserTabs")
        self.log = QtWidgets.QPlainTextEdit()
        self.log.setObjectName("browserLog")
        self.log.setReadOnly(True)
        self.log.setLineWrapMode(QtWidgets.QPlainTextEdit.LineWrapMode.NoWrap)
        self.report = QtWidgets.QPlainTextEdit()
        self.report.setObjectName("browserReport")
        self.report.setReadOnly(True)
        self.params = parameter_table()
        self.params.setObjectName("browserParameters")
        self.tabs.addTab(self.plot, "Captured periods")
        self.tabs.addTab(self.log, "session.log")
        self.tabs.addTab(self.params, "Result")
        self.tabs.addTab(self.report, "report.txt")

        refit = QtWidgets.QGroupBox("Re-fit")
        form = QtWidgets.QHBoxLayout(refit)
        self.model = QtWidgets.QComboBox()
        self.model.setObjectName("refitModelBox")
        self.model.addItems(["2dof", "1dof"])
        self.model.currentTextChanged.connect(self._model_changed)
        self.estimate = QtWidgets.QLineEdit(",".join(DEFAULT_ESTIMATE["2dof"]))
        self.estimate.setObjectName("refitEstimateEdit")
        self.start = QtWidgets.QLineEdit()
        self.start.setObjectName("refitParamsEdit")
        self.start.setPlaceholderText("start values / priors JSON (default: nominal)")
        start_browse = QtWidgets.QPushButton("…")
        start_browse.setFixedWidth(30)
        start_browse.clicked.connect(self._choose_start)
        self.refit_button = QtWidgets.QPushButton("Re-fit")
        self.refit_button.setObjectName("refitButton")
        self.refit_button.setEnabled(False)
        self.refit_button.clicked.connect(self._refit)
        for label, w in (("Model", self.model), ("Estimate", self.estimate), ("Start", self.start)):
            form.addWidget(QtWidgets.QLabel(label))
            form.addWidget(w, 2 if w is not self.model else 0)
        form.addWidget(start_browse)
        form.addWidget(self.refit_button)

        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        split.addWidget(self.table)
        split.addWidget(self.tabs)
        split.setStretchFactor(0, 1)
        split.setStretchFactor(1, 2)
        layout = QtWidgets.QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.summary)
        layout.addWidget(split, 1)
        layout.addWidget(refit)

    def _choose(self) -> None:
        path = QtWidgets.QFileDialog.getExistingDirectory(self, "Session folder", str(self.start_folder))
        if path:
            self.open_folder(Path(path))

    def _choose_start(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Start values", "", "JSON (*.json)")
        if path:
            self.start.setText(path)

    def _model_changed(self, model: str) -> None:
        self.estimate.setText(",".join(DEFAULT_ESTIMATE.get(model, DEFAULT_ESTIMATE["2dof"])))

    def open_folder(self, folder: Path) -> bool:
        """Show a session or dataset folder; False (and why, in the summary) if it is neither."""
        self.path.setText(str(folder))
        try:
            manifest = read_manifest(folder)
        except Exception as exc:  # noqa: BLE001 — identify's reader names the file and what is wrong
            self.summary.setText(f"Not a dataset: {exc}")
            self.refit_button.setEnabled(False)
            return False
        self.folder = folder
        raw = json.loads((folder / "dataset.json").read_text())
        self.entries = raw.get("experiments", [])
        meta = _read_json(folder / "session.json")
        if meta:
            status = meta.get("status", "?")
            self.summary.setText(
                f"<b>{raw.get('name', folder.name)}</b> — status <b>{status}</b>; plan {meta.get('plan')}, "
                f"started {meta.get('started', '?')}, finished {meta.get('finished', '–')}; "
                f"{len(manifest.experiments)} of {len(meta.get('experiments', []))} experiments captured")
            self.resumable = status != "complete"
            self.resume_button.setEnabled(self.resumable)
        else:
            self.summary.setText(f"<b>{raw.get('name', folder.name)}</b> — a dataset without session.json "
                                 f"({len(manifest.experiments)} experiments)")
            self.resumable = False
            self.resume_button.setEnabled(False)
        self.table.setRowCount(len(self.entries))
        for i, e in enumerate(self.entries):
            steady = {True: "yes", False: "NO"}[bool(e["steady_state"])] if "steady_state" in e else ""
            cells = (e.get("label", ""), e.get("frequency_Hz", ""), e.get("static_position_mm", ""),
                     e.get("amplitude_mm", ""), e.get("periods", ""), e.get("settle_cycles", ""),
                     steady, e.get("lost_samples", ""),
                     "; ".join(e.get("flags", [])))
            for j, value in enumerate(cells):
                self.table.setItem(i, j, QtWidgets.QTableWidgetItem(f"{value:g}" if isinstance(value, float)
                                                                    else str(value)))
        # The flags column only where there are flags: empty, it took half the table's width.
        self.table.setColumnHidden(FLAGS_COLUMN, not any(e.get("flags") for e in self.entries))
        log = folder / "session.log"
        self.log.setPlainText(log_text(log) if log.is_file() else "(no session.log)")
        self.report.setPlainText(_read_text(folder / "report.txt") or "(no report.txt: not identified yet)")
        doc = _read_json(folder / "RESULT.json")
        self.params.setRowCount(0)
        if doc:
            fill_parameter_table(self.params, doc)
        self.refit_button.setEnabled(True)
        if self.entries:
            self.table.selectRow(0)
        return True

    def _plot_selected(self) -> None:
        rows = self.table.selectionModel().selectedRows()
        self.plot.clear()
        if not rows or self.folder is None:
            return
        entry = self.entries[rows[0].row()]
        try:
            data = pd.read_csv(self.folder / entry["file"])
        except (OSError, ValueError, KeyError) as exc:
            self.plot.addLabel(f"cannot read the experiment's file: {exc}")
            return
        time_s = data["time_s"].to_numpy()
        t = time_s - time_s[0] if len(time_s) else time_s     # the record's own time, not the stream's
        first = None
        plotted = [c for c in PLOTTED if c[0] in data.columns]
        for row, (column, label, scale, colour) in enumerate(plotted):
            p = labelled(self.plot.addPlot(row=row, col=0), label,
                         "rig time from the record's start [s]" if row == len(plotted) - 1 else "")
            p.getAxis("left").setWidth(62)
            curve = p.plot(t, np.asarray(data[column]) * scale, pen=pg.mkPen(colour, width=1),
                           skipFiniteCheck=True)
            curve.setDownsampling(auto=True, method="peak")
            if first is None:
                first = p
                p.setTitle(f"{entry['label']}: {entry.get('periods', '?')} captured periods at "
                           f"{entry.get('frequency_Hz', '?')} Hz", size="10pt")
            else:
                p.setXLink(first)

    def _refit(self) -> None:
        if self.folder is None:
            return
        estimate = [x.strip() for x in self.estimate.text().split(",") if x.strip()]
        self.refitRequested.emit(self.folder, IdentifySettings(self.model.currentText(),
                                                               self.start.text().strip() or None, estimate))


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None
