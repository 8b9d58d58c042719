"""The live view: the four channels as time traces over a chosen window, the work loop
(force against stroke) of the last N cycles with the energy it dissipates per cycle,
force against velocity, and the DAQ's health.

Every axis follows its data: a trace's range is the data's, at least the channel's
minimum span of the rig configuration (``[display] min_span``), so a rig at rest shows
its noise as noise; the loops draw only the current excitation's cycles (cleared when a
new one starts) and say "no cycle yet", with no axes, while there is none.

Samples come from the DAQ's ring buffer (:attr:`rig.drivers.daq.Daq.ring`), read on the GUI's
timer: the reader thread never waits on the plots.  What the ring holds (10 s) is
copied into a 60 s history here, so the longest window does not depend on the driver.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import pyqtgraph as pg
from PySide6 import QtGui, QtWidgets

from rig.config import CHANNELS
from rig.drivers.daq import Daq
from rig.gui import analysis
from rig.gui.messages import Snapshot
from rig.gui.plotting import labelled
from rig.gui.units import GAS_PRESSURE_UNIT

WINDOWS_S = (2.0, 10.0, 60.0)
HISTORY_S = 60.0
RATE_WINDOW_S = 2.0                 # the DAQ's pace is measured over this much wall clock
# (title, unit, scale from the DAQ's engineering unit to the axis unit, colour)
# Short names: four stacked plots leave a label about 120 px, and longer ones ran into each other.
TRACES = (("stroke", "mm", 1.0, "#1f77b4"), ("force", "kN", 1e-3, "#d62728"),
          ("gas p", GAS_PRESSURE_UNIT, 1.0, "#2ca02c"), ("gas T", "°C", 1.0, "#9467bd"))
LOOP_POINTS = 4000                  # a loop is drawn with at most this many points
TRACE_BUCKETS = 1000                # a trace: min and max of at most this many buckets (wider than the plot)
RANGE_PAD = 0.08                    # of the span, above and below the data
RANGE_KEEP = 0.5                    # a range is kept while the data fill at least this share of it
NO_CYCLE = "no cycle yet"
PLACEHOLDER_WIDTH_PX = 220          # narrower than a loop plot in a 1280-px window


class LiveHistory:
    """The last 60 s of samples, appended from a DAQ's ring buffer.  A new stream (the
    index starts again at 0 after every START) or another DAQ starts it afresh."""

    def __init__(self, rate_hz: float, seconds: float = HISTORY_S) -> None:
        self.rate_hz = rate_hz
        cap = int(seconds * rate_hz)
        self.index = np.zeros(cap, dtype=np.int64)
        self.values = np.zeros((cap, 4))
        self.n = 0                  # samples held (the newest at the end)
        self.mark = -1              # the sample index after which the current excitation runs
        self._source: Daq | None = None
        self._last_read = 0.0

    def clear(self) -> None:
        self.n = 0

    def set_mark(self) -> None:
        """A new excitation starts now: the loops take no sample held so far."""
        self.mark = int(self.index[self.n - 1]) if self.n else -1

    def since_mark(self) -> int:
        """How many of the newest samples came after the mark."""
        return self.n - int(np.searchsorted(self.index[:self.n], self.mark, side="right"))

    def update(self, daq: Daq | None) -> bool:
        """Take what is new in ``daq``'s ring; True if anything was."""
        if daq is not self._source:
            self._source, self.n, self.mark = daq, 0, -1
        if daq is None:
            return False
        now = time.monotonic()
        # Ask the ring for about what arrived since the last read (with room to spare),
        # not for all of it every time.
        want = len(daq.ring.index) if self.n == 0 else int(self.rate_hz * (now - self._last_read) * 2) + 256
        idx, vals = _this_stream(*daq.ring.latest(want))
        self._last_read = now
        if not len(idx):
            return False
        last = int(self.index[self.n - 1]) if self.n else -1
        if idx[-1] < last:              # a new stream (a session starts the DAQ at each RUN)
            self.n, last, self.mark = 0, -1, -1
        elif self.n and idx[0] > last + 1 and want < len(daq.ring.index):
            idx, vals = _this_stream(*daq.ring.latest(len(daq.ring.index)))   # fell behind: take the whole ring
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


def _this_stream(idx: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples after the last restart of the index: the ring may still hold the end of
    the previous stream before the new one."""
    restart = np.flatnonzero(np.diff(idx) < 0)
    if len(restart):
        return idx[restart[-1] + 1:], vals[restart[-1] + 1:]
    return idx, vals


def _plot(layout: pg.GraphicsLayoutWidget, row: int, col: int, title: str | None, left: str, bottom: str,
          **kw: object) -> pg.PlotItem:
    return labelled(layout.addPlot(row=row, col=col, **kw), left, bottom, title, grid=False)


def follow(plot: pg.PlotItem, axis: str, values: np.ndarray, min_span: float = 0.0) -> None:
    """Set the axis to the data's range, at least ``min_span`` wide around their middle;
    the range is kept while it still holds the data and they fill enough of it, so that
    the axis does not breathe with the noise at every frame."""
    if not len(values):
        return
    lo, hi = float(np.min(values)), float(np.max(values))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return
    span = max(hi - lo, min_span)
    vb = plot.getViewBox()
    (x0, x1), (y0, y1) = vb.viewRange()
    a, b = (x0, x1) if axis == "x" else (y0, y1)
    if a <= lo and hi <= b and span >= RANGE_KEEP * (b - a) * (1 - 2 * RANGE_PAD):
        return
    mid, half = 0.5 * (lo + hi), 0.5 * span * (1 + 2 * RANGE_PAD)
    if axis == "x":
        vb.setXRange(mid - half, mid + half, padding=0)
    else:
        vb.setYRange(mid - half, mid + half, padding=0)


def _curve(plot: pg.PlotItem, colour: str) -> pg.PlotDataItem:
    # Decimated here (analysis.peak_decimate), in numpy, before pyqtgraph sees the data:
    # cheaper than its own downsampling, which runs in Python at every paint.
    curve = plot.plot(pen=pg.mkPen(colour, width=1), skipFiniteCheck=True)
    curve.setClipToView(True)       # plot(clipToView=True) raises in pyqtgraph 0.14
    return curve


class LiveView(QtWidgets.QWidget):
    def __init__(self, rate_hz: float, min_span: dict[str, float] | None = None, asked_pace: float = 1.0,
                 parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.rate_hz = rate_hz
        self.asked_pace = asked_pace          # the simulator's --speed (1 on hardware): said beside the measured one
        spans = min_span or {}
        # in the axes' units (force in kN)
        self.min_span = [spans.get(c, 0.0) * scale for c, (_, _, scale, _) in zip(CHANNELS, TRACES, strict=True)]
        self._excitation: object = None
        self.why_none = "no excitation running"
        self.history = LiveHistory(rate_hz)
        self.frequency_hz: float | None = None     # the excitation's, for the loops (None: not known)
        self.window_s = 10.0
        # (wall time, frames received) of the last health updates, for a rate over RATE_WINDOW_S
        self._counts: collections.deque[tuple[float, int]] = collections.deque()

        bar = QtWidgets.QHBoxLayout()
        bar.addWidget(QtWidgets.QLabel("Window (rig time)"))
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
        bar.addStretch(1)
        self.health = QtWidgets.QLabel("DAQ: not streaming")
        self.health.setObjectName("daqHealth")
        # Text that changes 4 times a second must not change the layout: a plot area resized
        # by a pixel is a full re-layout and redraw of every plot.
        # On a line of its own, wrapped rather than cut (it was cut beside the boxes at 1280 px).
        self.health.setWordWrap(True)
        self.health.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)

        self.layout_widget = pg.GraphicsLayoutWidget()
        self.traces: list[pg.PlotDataItem] = []
        self.trace_plots: list[pg.PlotItem] = []
        first = None
        for i, (title, unit, _, colour) in enumerate(TRACES):
            p = _plot(self.layout_widget, i, 0, None, f"{title} [{unit}]",
                      "rig time relative to the newest sample [s]" if i == len(TRACES) - 1 else "")
            p.setXRange(-self.window_s, 0, padding=0)
            p.enableAutoRange(enable=False)         # follow() sets the value axis
            p.getAxis("left").setWidth(62)
            if first is None:
                first = p
            else:
                p.setXLink(first)
            if i < len(TRACES) - 1:
                p.getAxis("bottom").setStyle(showValues=False)
            self.traces.append(_curve(p, colour))
            self.trace_plots.append(p)
        self.loop_plot = _plot(self.layout_widget, 0, 1, "Work loop", "force [kN]", "stroke [mm]", rowspan=2)
        self.loop = self.loop_plot.plot(pen=pg.mkPen("#d62728", width=1), skipFiniteCheck=True)
        self.fv_plot = _plot(self.layout_widget, 2, 1, "Force against velocity", "force [kN]", "velocity [m/s]",
                             rowspan=2)
        self.fv = self.fv_plot.plot(pen=pg.mkPen("#ff7f0e", width=1), skipFiniteCheck=True)
        self.placeholders: list[pg.TextItem] = []
        for p in (self.loop_plot, self.fv_plot):
            p.enableAutoRange(enable=False)
            text = pg.TextItem(NO_CYCLE, color="#616161", anchor=(0.5, 0.5))
            font = QtGui.QFont()             # the window's own face: "" fell back to a serif one
            font.setPointSize(12)            # 16 pt was cut at both sides in a 1280-px window
            text.setFont(font)
            text.textItem.setTextWidth(PLACEHOLDER_WIDTH_PX)    # a long reason wraps, never cut
            p.addItem(text, ignoreBounds=True)
            self.placeholders.append(text)
        self.placeholder_reason = ""
        self.layout_widget.ci.layout.setColumnStretchFactor(0, 3)
        self.layout_widget.ci.layout.setColumnStretchFactor(1, 2)
        self.energy = QtWidgets.QLabel("Energy dissipated per cycle: –")
        self.energy.setObjectName("loopEnergy")
        self.energy.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        self._show_placeholders("no excitation running")

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(bar)
        layout.addWidget(self.health)
        layout.addWidget(self.layout_widget, 1)
        layout.addWidget(self.energy)

    def _window_changed(self) -> None:
        self.window_s = float(self.window_box.currentData())
        self.traces[0].getViewBox().setXRange(-self.window_s, 0, padding=0)

    def set_excitation(self, key: object, frequency_hz: float | None, why_none: str = "no excitation running") -> None:
        """The excitation running now (``key`` None: none, for the reason ``why_none``); a new
        key clears the loops."""
        if key != self._excitation:
            self._excitation = key
            self.history.set_mark()
        self.frequency_hz = frequency_hz if key is not None else None
        self.why_none = why_none

    def refresh(self, daq: Daq | None) -> bool:
        """Take new samples and redraw; False when there was nothing new."""
        if not self.history.update(daq):
            if self.history.n == 0:
                for curve in self.traces:           # no samples of this link: no old trace drawn as if live
                    curve.setData([], [])
                self._show_placeholders("no DAQ link" if daq is None else "no samples yet: the DAQ is not streaming"
                                        if not daq.streaming else "no samples yet")
            elif not self.frequency_hz:
                # the excitation ended (or is no longer read): its loop and energy are not shown as if current
                self._show_placeholders(self.why_none)
            return False
        t, v = self.history.latest(self.window_s)
        for curve, plot, span, (_, _, scale, _), column in zip(self.traces, self.trace_plots, self.min_span, TRACES,
                                                               v.T, strict=True):
            td, yd = analysis.peak_decimate(t, column * scale if scale != 1.0 else column, TRACE_BUCKETS)
            curve.setData(td, yd)
            follow(plot, "y", yd, span)
        self._refresh_loops()
        return True

    def _show_placeholders(self, reason: str) -> None:
        if reason == self.placeholder_reason:
            return
        self.placeholder_reason = reason
        self.loop.setData([], [])
        self.fv.setData([], [])
        for plot, text in zip((self.loop_plot, self.fv_plot), self.placeholders, strict=True):
            # Axes without data would be pyqtgraph's 0-1 dummies: none at all, a sentence instead.
            for side in ("left", "bottom"):
                plot.hideAxis(side)
            plot.getViewBox().setRange(xRange=(0, 1), yRange=(0, 1), padding=0)
            text.setText(f"{NO_CYCLE}\n({reason})")
            text.setPos(0.5, 0.5)
            text.setVisible(True)
        self.energy.setText(f"Energy dissipated per cycle: – ({NO_CYCLE}: {reason})")

    def _refresh_loops(self) -> None:
        f = self.frequency_hz
        if not f:
            self._show_placeholders(self.why_none)
            return
        n = analysis.last_cycles(self.history.since_mark(), self.rate_hz, f, self.cycles_box.value())
        _, v = self.history.latest(n / self.rate_hz)
        if len(v) < 3:
            self._show_placeholders(f"the first whole cycle at {f:g} Hz is on its way")
            return
        if self.placeholder_reason:
            self.placeholder_reason = ""
            for plot, text in zip((self.loop_plot, self.fv_plot), self.placeholders, strict=True):
                text.setVisible(False)
                for side in ("left", "bottom"):
                    plot.showAxis(side)
        whole = round(n * f / self.rate_hz)
        stroke_m, force_n = v[:, 0] * 1e-3, v[:, 1]
        velocity = analysis.velocity_m_s(stroke_m, self.rate_hz, f)
        step = max(1, len(v) // LOOP_POINTS)
        stroke_mm, force_kn, velocity = v[::step, 0], force_n[::step] * 1e-3, velocity[::step]
        self.loop.setData(stroke_mm, force_kn)
        self.fv.setData(velocity, force_kn)
        follow(self.loop_plot, "x", stroke_mm, self.min_span[0])
        follow(self.loop_plot, "y", force_kn, self.min_span[1])
        follow(self.fv_plot, "x", velocity)
        follow(self.fv_plot, "y", force_kn, self.min_span[1])
        energy = analysis.loop_energy_j(stroke_m, force_n, whole)
        self.energy.setText(f"Energy dissipated per cycle: {energy:.1f} J (mean of the last {whole} cycles at "
                            f"{f:g} Hz)")

    def show_health(self, snap: Snapshot) -> None:
        """The DAQ's rate as the rig runs it (samples per second of rig time: each frame is one
        sample), and how fast the frames arrive against the wall clock, over at least a second.
        Frames per wall second alone read 29 000 then 42 000 on a simulator at 20x, which an
        operator takes for a fault; on hardware the pace is 1.0x, and below it the reader lags."""
        counts = self._counts
        if counts and (snap.received < counts[-1][1] or snap.time <= counts[-1][0]):
            counts.clear()                          # a new stream: its count starts again
        counts.append((snap.time, snap.received))
        while len(counts) > 2 and snap.time - counts[1][0] >= RATE_WINDOW_S:
            counts.popleft()
        self.health.setText(f"DAQ {self._pace(snap)} · lost {snap.lost} · CRC errors {snap.crc_errors} · "
                            f"over range {snap.over_range} · overflow flags {snap.overflow_flags}")
        style = "color: #b00020; font-weight: bold" if snap.lost or snap.crc_errors or snap.over_range else ""
        self.health.setStyleSheet(style)

    def _pace(self, snap: Snapshot) -> str:
        """What the DAQ does, from this stream's counts only: not streaming, being measured,
        or the frames counted per second of the wall clock over the last 2 s, and what
        that is against the rig's own rate (frames are samples of rig time)."""
        if not snap.streaming:
            # a session streams while it holds, settles and captures, not while it moves or stops
            said = "not streaming" + (" (the session streams while it holds, settles and captures, and stops the "
                                      "stream first in its safe stop)" if snap.session else "")
            return said + ("; the traces end at the last sample received" if self.history.n else "")
        (t0, n0), (t1, n1) = self._counts[0], self._counts[-1]
        if t1 - t0 < RATE_WINDOW_S:
            return f"rate: measuring over {RATE_WINDOW_S:g} s of wall clock"
        per_s = (n1 - n0) / (t1 - t0)
        if per_s == 0:
            return f"streaming, but no frame in the last {t1 - t0:.1f} s of wall clock"
        pace = per_s / self.rate_hz
        asked = f"; asked for {self.asked_pace:g}×" if abs(pace / self.asked_pace - 1) > 0.2 else ""
        return (f"{per_s:,.0f} samples per wall-clock second (last {t1 - t0:.1f} s): {pace:.1f}× real time "
                f"at {self.rate_hz:g} samples/s of rig time{asked}").replace(",", " ")
