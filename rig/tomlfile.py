"""Reading the rig's TOML files (register map, rig configuration, calibration, plans)
with one error convention: the message names the file and what is wrong."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any


def read_toml(path: Path, error: type[Exception], label: str = "") -> tuple[str, dict[str, Any]]:
    """The file's text (kept for session snapshots) and its parsed content; ``error``
    (prefixed with ``label``) when it cannot be read or parsed."""
    try:
        text = path.read_text()
        return text, tomllib.loads(text)
    except OSError as exc:
        raise error(f"{label}{path}: cannot be read ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{label}{path}: not valid TOML: {exc}") from None
