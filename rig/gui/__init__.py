"""The operator's console (``python -m rig gui``): Qt and pyqtgraph live in this package only.

``rig.gui.MainWindow`` is imported on first use, so that importing ``rig.gui`` (or the
command line) does not load Qt.
"""

from __future__ import annotations

from typing import Any

__all__ = ["MainWindow"]


def __getattr__(name: str) -> Any:
    if name == "MainWindow":
        from rig.gui.main_window import MainWindow

        return MainWindow
    raise AttributeError(f"module 'rig.gui' has no attribute {name!r}")
