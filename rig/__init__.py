"""Shaker-rig acquisition: drivers, sessions, and the scripting API (``rig.open``)."""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    # The API is loaded on first use, so that `python -m rig` starts without it.
    if name in ("open", "Rig", "Session", "SessionFailed"):
        from rig.session import api

        return getattr(api, name)
    raise AttributeError(f"module 'rig' has no attribute {name!r}")
