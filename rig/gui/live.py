"""The live view: the four channels as time traces over a chosen window, the work loop
(force against stroke) of the last N cycles with the energy it dissipates per cycle,
force against velocity, and the DAQ's health.

Samples come from the DAQ's ring buffer (:attr:`rig.daq.Daq.ring`), read on the GUI's
timer: the reader thread never waits on the plots.  What the ring holds (10 s) is
copied into a 60 s history here, so the longest window does not depend on the driver.
"""

from __future__ import annotations

import time

import numpy as np
import pyqtgraph as pg
from PySide6 import QtWidgets

from rig.daq import Daq
from rig.gui import analysis
from rig.gui.plotting import labelled
from rig.gui.station import Snapshot

WINDOWS_S = (2.0, 10.0, 60.0)
HISTORY_S = 60.0
# (title, unit, scale from the DAQ's engineering unit to the axis unit, colour)
TRACES = (("stroke", "mm", 1.0, "#1f77b4"), ("force", "kN", 1e-3, "#d62728"),
          ("gas pressure (abs.)", "bar", 1.0, "#2ca02c"), ("gas temperature", "°C", 1.0, "#9467bd"))
LOOP_POINTS = 4000                  # a loop is drawn with at most this many points
TRACE_BUCKETS = 1000                # a trace: min and max of at most this many buckets (wider than the plot)


class LiveHistory:
    """The last 60 s of samples, appended from a DAQ's ring buffer.  A new stream (the
    index starts again at 0 after every START) or another DAQ starts it afresh."""

    def __init__(self, rate_hz: float, seconds: float = HISTORY_S) -> None:
        self.rate_hz = rate_hz
        cap = int(seconds * rate_hz)
        self.index = np.zeros(cap, dtype=np.int64)
        self.values = np.zeros((cap, 4))
        self.n = 0                  # samples held (the newest at the end)
        self._source: Daq | None = None
        self._last_read = 0.0

    def clear(self) -> None:
        self.n = 0

    def update(self, daq: Daq | None) -> bool:
        """Take what is new in ``daq``'s ring; True if anything was."""
        if daq is not self._source:
            self._source, self.n = daq, 0
        if daq is None:
            return False
        now = time.monotonic()
        # Ask the ring for about what arrived since the last read (with room to spare),
        # not for all of it every time.
        want = len(daq.ring.index) if self.n == 0 else int(self.rate_hz * (now - self._last_read) * 2) + 256
        idx, vals = daq.ring.latest(want)
        self._last_read = now
        if not len(idx):
            return False
        last = int(self.index[self.n - 1]) if self.n else -1
        if idx[-1] < last:              # a new stream
            self.n, last = 0, -1
        elif self.n and idx[0] > last + 1 and want < len(daq.ring.index):
            idx, vals = daq.ring.latest(len(daq.ring.index))   # fell behind: take the whole ring
        new = idx > last
        idx, vals = idx[new], vals[new]
        if not len(idx):
            return False
        cap = len(self.index)
        if len(idx) >= cap:
            idx, vals = idx[-cap:], vals[-cap:]
        keep = min(self.n, cap - len(idx))
        self.index[:keep] = self.index[self.n - keep:self.n]
        self.values[:keep] = self.values[self.n - keep:self.n]
        self.index[keep:keep + len(idx)] = idx
        self.values[keep:keep + len(idx)] = vals
        self.n = keep + len(idx)
        return True

    def latest(self, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        """Sample times relative to the newest sample [s] and values, over ``seconds``."""
        if not self.n:
            return np.zeros(0), np.zeros((0, 4))
        last = self.index[self.n - 1]
        start = max(0, self.n - int(seconds * self.rate_hz))
        idx = self.index[start:self.n]
        return (idx - last) / self.rate_hz, self.values[start:self.n]


def _plot(layout: pg.GraphicsLayoutWidget, row: int, col: int, title: str | None, left: str, bottom: str,
          **kw: object) -> pg.PlotItem:
    return labelled(layout.addPlot(row=row, col=col, **kw), left, bottom, title, grid=False)


def _curve(plot: pg.PlotItem, colour: str) -> pg.PlotDataItem:
    # Decimated here (analysis.peak_decimate), in numpy, before pyqtgraph sees the data:
    # cheaper than its own downsampling, which runs in Python at every paint.
    curve = plot.plot(pen=pg.mkPen(colour, width=1), skipFiniteCheck=True)
    curve.setClipToView(True)       # plot(clipToView=True) raises in pyqtgraph 0.14
    return curve


class LiveView(QtWidgets.QWidget):
    def __init__(self, rate_hz: float, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.rate_hz = rate_hz
        self.history = LiveHistory(rate_hz)
        self.frequency_hz: float | None = None     # the excitation's, for the loops (None: not known)
        self.window_s = 10.0
        self._counts: tuple[float, int] | None = None   # (time, frames received) of the last health update

        bar = QtWidgets.QHBoxLayout()
        bar.addWidget(QtWidgets.QLabel("Window"))
        self.window_box = QtWidgets.QComboBox()
        self.window_box.setObjectName("windowBox")
        for w in WINDOWS_S:
            self.window_box.addItem(f"{w:g} s", w)
        self.window_box.setCurrentIndex(WINDOWS_S.index(self.window_s))
        self.window_box.currentIndexChanged.connect(self._window_changed)
        bar.addWidget(self.window_box)
        bar.addSpacing(20)
        bar.addWidget(QtWidgets.QLabel("Loop: last"))
        self.cycles_box = QtWidgets.QSpinBox()
        self.cycles_box.setRange(1, 20)
        self.cycles_box.setValue(3)
        self.cycles_box.setSuffix(" cycles")
        bar.addWidget(self.cycles_box)
        bar.addSpacing(20)
        self.health = QtWidgets.QLabel("DAQ: not streaming")
        self.health.setObjectName("daqHealth")
        # Text that changes 4 times a second must not change the layout: a plot area resized
        # by a pixel is a full re-layout and redraw of every plot.
        self.health.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        bar.addWidget(self.health, 1)

        self.layout_widget = pg.GraphicsLayoutWidget()
        self.traces: list[pg.PlotDataItem] = []
        first = None
        for i, (title, unit, _, colour) in enumerate(TRACES):
            p = _plot(self.layout_widget, i, 0, None, f"{title} [{unit}]",
                      "time relative to the newest sample [s]" if i == len(TRACES) - 1 else "")
            p.setXRange(-self.window_s, 0, padding=0)
            p.enableAutoRange(axis="x", enable=False)
            p.getAxis("left").setWidth(62)
            if first is None:
                first = p
            else:
                p.setXLink(first)
            if i < len(TRACES) - 1:
                p.getAxis("bottom").setStyle(showValues=False)
            self.traces.append(_curve(p, colour))
        self.loop_plot = _plot(self.layout_widget, 0, 1, "Work loop", "force [kN]", "stroke [mm]", rowspan=2)
        self.loop = self.loop_plot.plot(pen=pg.mkPen("#d62728", width=1), skipFiniteCheck=True)
        self.fv_plot = _plot(self.layout_widget, 2, 1, "Force against velocity", "force [kN]", "velocity [m/s]",
                             rowspan=2)
        self.fv = self.fv_plot.plot(pen=pg.mkPen("#ff7f0e", width=1), skipFiniteCheck=True)
        self.layout_widget.ci.layout.setColumnStretchFactor(0, 3)
        self.layout_widget.ci.layout.setColumnStretchFactor(1, 2)
        self.energy = QtWidgets.QLabel("Energy dissipated per cycle: –")
        self.energy.setObjectName("loopEnergy")
        self.energy.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(bar)
        layout.addWidget(self.layout_widget, 1)
        layout.addWidget(self.energy)

    def _window_changed(self) -> None:
        self.window_s = float(self.window_box.currentData())
        self.traces[0].getViewBox().setXRange(-self.window_s, 0, padding=0)

    def refresh(self, daq: Daq | None) -> bool:
        """Take new samples and redraw; False when there was nothing new."""
        if not self.history.update(daq):
            return False
        t, v = self.history.latest(self.window_s)
        for curve, (_, _, scale, _), column in zip(self.traces, TRACES, v.T, strict=True):
            curve.setData(*analysis.peak_decimate(t, column * scale if scale != 1.0 else column, TRACE_BUCKETS))
        self._refresh_loops()
        return True

    def _refresh_loops(self) -> None:
        f = self.frequency_hz
        n = analysis.last_cycles(self.history.n, self.rate_hz, f, self.cycles_box.value()) if f else 0
        _, v = self.history.latest(n / self.rate_hz)
        if not f or len(v) < 3:
            # Without a running excitation a "loop" is the transducers' noise: nothing to read in it.
            self.loop.setData([], [])
            self.fv.setData([], [])
            self.energy.setText("Energy dissipated per cycle: – (no whole cycle of a running excitation yet)")
            return
        whole = round(n * f / self.rate_hz)
        stroke_m, force_n = v[:, 0] * 1e-3, v[:, 1]
        velocity = analysis.velocity_m_s(stroke_m, self.rate_hz, f)
        step = max(1, len(v) // LOOP_POINTS)
        self.loop.setData(v[::step, 0], force_n[::step] * 1e-3)
        self.fv.setData(velocity[::step], force_n[::step] * 1e-3)
        energy = analysis.loop_energy_j(stroke_m, force_n, whole)
        self.energy.setText(f"Energy dissipated per cycle: {energy:.1f} J (mean of the last {whole} cycles at "
                            f"{f:g} Hz)")

    def show_health(self, snap: Snapshot) -> None:
        rate = 0.0
        if self._counts is not None and snap.time > self._counts[0] and snap.received >= self._counts[1]:
            rate = (snap.received - self._counts[1]) / (snap.time - self._counts[0])
        self._counts = (snap.time, snap.received)
        self.health.setText(f"DAQ {rate:6.0f} frames/s   lost {snap.lost}   CRC errors {snap.crc_errors}   "
                            f"over range {snap.over_range}   overflow flags {snap.overflow_flags}")
        style = "color: #b00020; font-weight: bold" if snap.lost or snap.crc_errors or snap.over_range else ""
        self.health.setStyleSheet(style)

