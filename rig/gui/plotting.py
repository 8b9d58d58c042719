"""How every plot of the console looks: dark on light, labelled axes with their units
as written (no automatic SI prefix: "[kN] (x0.001)" reads badly), a light grid."""

from __future__ import annotations

import pyqtgraph as pg

# Antialiasing costs more than it shows at pen width 1.
pg.setConfigOptions(background="w", foreground="k", antialias=False)


def labelled(plot: pg.PlotItem, left: str, bottom: str, title: str | None = None, grid: bool = True) -> pg.PlotItem:
    for side, text in (("left", left), ("bottom", bottom)):
        axis = plot.getAxis(side)
        axis.enableAutoSIPrefix(False)
        plot.setLabel(side, text)
    if title:
        plot.setTitle(title, size="10pt")
    if grid:    # a translucent grid is blended over the whole plot at every redraw: not in live plots
        plot.showGrid(x=True, y=True, alpha=0.25)
    plot.setMenuEnabled(False)
    return plot
