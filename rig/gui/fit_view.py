"""The fit view: per experiment the measured period against the model's (stroke,
pressure), the residuals with the ±2σ band of the fit's noise estimate, and the
parameter table (value ± std, % std, correlation warnings, converged).  The 1-dof vs
2-dof comparison is one click away; a stored RESULT.json shows its table alone."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from identify.notation import plus_minus, rounded, significant, unit_text
from identify.result import CORRELATION_REPORT, RELATIVE_STD_WARNING
from rig.gui.fits import FitSummary
from rig.gui.plotting import labelled
from rig.gui.units import GAS_PRESSURE_UNIT

UNITS = {"stroke_mm": "mm", "pressure_bar": GAS_PRESSURE_UNIT, "gas_temperature_C": "°C", "force_N": "N"}
NAMES = {"stroke_mm": "stroke", "pressure_bar": "gas pressure", "gas_temperature_C": "gas temperature",
         "force_N": "force"}
PARAMETER_COLUMNS = ("parameter", "value", "± σ", "% σ", "unit", "start", "moved")
NOT_MOVED = "#fff59d"           # an estimate within one σ of where it started: the data did not move it


def fill_parameter_table(table: QtWidgets.QTableWidget, doc: dict[str, Any]) -> list[str]:
    """The estimated parameters of a RESULT.json document, each value to its std's decimal
    place (σ to two significant digits, identify.notation) and its unit in Unicode;
    returns its warnings plus one line per strongly correlated pair.  Beside the start (as
    given) the move from it in σ: an estimate within one σ of its start is marked and
    warned about, for it cannot be told from one the fit never moved."""
    params = {k: p for k, p in doc.get("parameters", {}).items() if p.get("estimated")}
    table.setRowCount(len(params))
    warnings = list(doc.get("warnings", []))
    for i, (name, p) in enumerate(params.items()):
        value, std, start = p["value"], p.get("std"), p.get("initial")
        usable = std is not None and math.isfinite(std) and std > 0
        rel = abs(std / value) if usable and value else math.nan
        title = f"{name} ({p['alias']})" if p.get("alias") else name
        shown, sigma = rounded(value, std)
        moved_sigma = (value - start) / std if usable and start is not None else math.nan
        still = abs(moved_sigma) <= 1.0
        start_text = "" if start is None else f"{start:.6g}"      # as the operator or the model gave it
        moved = "–" if math.isnan(moved_sigma) else f"{significant(moved_sigma)} σ"
        cells = (title, shown, sigma, "–" if math.isnan(rel) else f"{100 * rel:.2g} %", unit_text(p.get("unit", "")),
                 start_text, moved)
        for j, text in enumerate(cells):
            item = QtWidgets.QTableWidgetItem(text)
            item.setToolTip(f"{text}: within 1 σ of its start, not told from one never moved" if still and j == 6
                            else text)
            if j in (1, 2, 3, 5, 6):
                item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
            if rel > RELATIVE_STD_WARNING:
                item.setBackground(QtGui.QColor("#ffe0b2"))
            elif still and j in (1, 5, 6):
                item.setBackground(QtGui.QColor(NOT_MOVED))
            table.setItem(i, j, item)
        if still:
            warnings.append(f"{name}: the estimate is within 1 σ of its start value {start_text}: it cannot be told "
                            "from a parameter the fit did not move (check it with another start)")
    corr = doc.get("correlation", {})
    names = list(corr)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            c = corr[a].get(b)
            if c is not None and abs(c) >= CORRELATION_REPORT:
                warnings.append(f"correlation C({a}, {b}) = {c:+.3f}")
    return warnings


def parameter_table() -> QtWidgets.QTableWidget:
    table = QtWidgets.QTableWidget(0, len(PARAMETER_COLUMNS))
    table.setHorizontalHeaderLabels(PARAMETER_COLUMNS)
    table.verticalHeader().setVisible(False)
    table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
    header = table.horizontalHeader()
    header.setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
    # The numbers whole; the name takes what is left (elided, whole in its tooltip).
    header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.Stretch)
    return table


class FitView(QtWidgets.QWidget):
    compareRequested = QtCore.Signal()

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.result: FitSummary | None = None
        self.comparison: dict[str, FitSummary] | None = None
        self.folder: Path | None = None

        head = QtWidgets.QHBoxLayout()
        self.title = QtWidgets.QLabel("No fit yet: run a plan with identification, or re-fit a session.")
        self.title.setObjectName("fitTitle")
        self.title.setStyleSheet("font-weight: bold")
        head.addWidget(self.title, 1)
        self.progress = QtWidgets.QLabel("")
        self.progress.setObjectName("fitProgress")
        head.addWidget(self.progress)
        self.compare_button = QtWidgets.QPushButton("Compare 1-dof / 2-dof")
        self.compare_button.setObjectName("compareButton")
        self.compare_button.setEnabled(False)
        self.compare_button.clicked.connect(self.compareRequested)
        head.addWidget(self.compare_button)

        pick = QtWidgets.QHBoxLayout()
        pick.addWidget(QtWidgets.QLabel("Experiment"))
        self.experiment = QtWidgets.QComboBox()
        self.experiment.setObjectName("fitExperimentBox")
        self.experiment.currentIndexChanged.connect(self._draw)
        pick.addWidget(self.experiment)
        pick.addStretch(1)

        self.plots = pg.GraphicsLayoutWidget()
        self.table = parameter_table()
        self.table.setObjectName("parameterTable")
        self.notes = QtWidgets.QLabel("")
        self.notes.setObjectName("fitNotes")
        self.notes.setWordWrap(True)
        self.notes.setAlignment(QtCore.Qt.AlignmentFlag.AlignTop | QtCore.Qt.AlignmentFlag.AlignLeft)
        self.compare_table = QtWidgets.QTableWidget(0, 4)
        self.compare_table.setObjectName("comparisonTable")
        self.compare_table.setHorizontalHeaderLabels(["experiment", "f [Hz]", "1-dof [mm]", "2-dof [mm]"])
        self.compare_label = QtWidgets.QLabel("")
        self.compare_label.setObjectName("comparisonLabel")
        self.compare_label.setWordWrap(True)
        self.compare_table.verticalHeader().setVisible(False)
        self.compare_table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.compare_table.setVisible(False)

        side = QtWidgets.QVBoxLayout()
        side.addWidget(QtWidgets.QLabel("Estimated parameters"))
        side.addWidget(self.table, 2)
        side.addWidget(self.notes, 1)
        side.addWidget(self.compare_label)
        side.addWidget(self.compare_table, 2)
        side_box = QtWidgets.QWidget()
        side_box.setLayout(side)
        split = QtWidgets.QSplitter()
        left = QtWidgets.QWidget()
        left_layout = QtWidgets.QVBoxLayout(left)
        left_layout.setContentsMargins(0, 0, 0, 0)
        left_layout.addLayout(pick)
        left_layout.addWidget(self.plots, 1)
        split.addWidget(left)
        split.addWidget(side_box)
        split.setStretchFactor(0, 1)
        split.setStretchFactor(1, 1)
        # Half each: the two columns of plots need that much for their titles and axes (a
        # narrower view clips them instead of shrinking them); the parameter table's names elide.
        split.setSizes([530, 530])
        layout = QtWidgets.QVBoxLayout(self)
        layout.addLayout(head)
        layout.addWidget(split, 1)

    # ----- showing ---------------------------------------------------------------------------------
    def show_progress(self, title: str, iteration: int, objective: float) -> None:
        self.progress.setText(f"{title}: iteration {iteration}, objective {objective:.6g}")

    def show_result(self, title: str, result: FitSummary, folder: Path) -> None:
        self.result, self.folder, self.comparison = result, folder, None
        self.compare_table.setVisible(False)
        self.compare_label.setText("")
        self.progress.setText("")
        self._header(title, result.document)
        self.compare_button.setEnabled(True)
        self.experiment.blockSignals(True)
        self.experiment.clear()
        for e in result.experiments:
            self.experiment.addItem(f"{e.label} ({e.frequency_hz:g} Hz)")
        self.experiment.blockSignals(False)
        self._draw()

    def _header(self, title: str, doc: dict[str, Any]) -> None:
        converged = doc.get("converged")
        self.title.setText(f"{title} — {'converged' if converged else 'NOT converged'} "
                           f"after {doc.get('iterations', '?')} iterations")
        self.title.setStyleSheet("font-weight: bold; color: " + ("#1b5e20" if converged else "#b00020"))
        warnings = fill_parameter_table(self.table, doc)
        self.notes.setText("Warnings:\n• " + "\n• ".join(warnings) if warnings else "No warnings.")
        self.notes.setStyleSheet("color: #8a4b00" if warnings else "")

    def show_comparison(self, results: dict[str, FitSummary]) -> None:
        self.comparison = results
        one, two = results["1dof"], results["2dof"]
        self.compare_table.setRowCount(len(one.experiments))
        for i, (e1, e2) in enumerate(zip(one.experiments, two.experiments, strict=True)):
            (m1, s1), (m2, s2) = e1.stats("stroke_mm"), e2.stats("stroke_mm")
            for j, text in enumerate((e1.label, f"{e1.frequency_hz:g}", plus_minus(m1, 2 * s1),
                                      plus_minus(m2, 2 * s2))):
                self.compare_table.setItem(i, j, QtWidgets.QTableWidgetItem(text))
        self.compare_table.setVisible(True)
        self.progress.setText("")
        self.compare_label.setText(
            f"1-dof (θ5, θ6, θ7) against 2-dof, both fitted to the stroke: residual mean ± 2σ per experiment; "
            f"residual std 1-dof {significant(math.sqrt(one.channel_variances['stroke_mm']))} mm, "
            f"2-dof {significant(math.sqrt(two.channel_variances['stroke_mm']))} mm")
        self._draw()

    def _draw(self) -> None:
        result = self.result
        i = self.experiment.currentIndex()
        self.plots.clear()
        if result is None or i < 0:
            return
        e = result.experiments[i]
        # The legend in a row of its own above the plots: inside a plot it lay over the curves.
        key = [("#1f77b4", "● measured (folded)"), ("#d62728", f"━ model {result.model}")]
        if self.comparison is not None:
            key.append(("#2ca02c", "╍ model 1dof"))
        self.plots.addLabel("&nbsp;&nbsp;&nbsp;".join(f'<span style="color:{c}">{t}</span>' for c, t in key),
                            row=0, col=0, colspan=len(result.outputs), size="10pt")
        for col, out in enumerate(result.outputs):
            n = len(e.measured[out])
            t = np.arange(n) / (n * e.frequency_hz)
            unit = UNITS.get(out, "")
            p = labelled(self.plots.addPlot(row=1, col=col), f"{NAMES.get(out, out)} [{unit}]",
                         "time in the period [s]", f"{e.label}: {NAMES.get(out, out)}")
            p.plot(t, e.measured[out], pen=None, symbol="o", symbolSize=3, symbolPen=None,
                   symbolBrush=(31, 119, 180, 110), name="measured (folded)")
            model = p.plot(t, e.predicted[out], pen=pg.mkPen("#d62728", width=2), name=f"model {result.model}")
            model.setZValue(10)
            if self.comparison is not None and out in self.comparison["1dof"].outputs:
                e1 = self.comparison["1dof"].experiments[i]
                p.plot(t, e1.predicted[out], pen=pg.mkPen("#2ca02c", width=2, style=QtCore.Qt.PenStyle.DashLine),
                       name="model 1dof").setZValue(11)
            r = labelled(self.plots.addPlot(row=2, col=col), f"residual [{unit}]", "time in the period [s]",
                         "measured − model, ±2σ")
            sigma = math.sqrt(result.channel_variances[out])
            upper = r.plot(t[[0, -1]], [2 * sigma, 2 * sigma], pen=pg.mkPen("#9e9e9e", width=1))
            lower = r.plot(t[[0, -1]], [-2 * sigma, -2 * sigma], pen=pg.mkPen("#9e9e9e", width=1))
            r.addItem(pg.FillBetweenItem(upper, lower, brush=pg.mkBrush(158, 158, 158, 60)))
            r.plot(t, e.residual(out), pen=pg.mkPen("#1f77b4", width=1))
            r.setXLink(p)
