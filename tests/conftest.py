"""Shared fixtures: a generated dataset with a known truth, reused by the slow tests."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # before any Qt import: CI has no display

from pathlib import Path

import pytest

# The specs and measured data sit beside the checkout (../shared); DAMPER_SHARED_DIR
# points elsewhere for a checkout that lives somewhere else.
SHARED = Path(os.environ.get("DAMPER_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")
SILVERBOX = SHARED / "data" / "silverbox"


@pytest.fixture(scope="session")
def standard_dataset(tmp_path_factory) -> Path:
    """The standard set (14 experiments, 3 periods, 2 kHz) from the simulator, nominal truth."""
    from identify.plans import STANDARD_SET
    from simulator.generate import generate
    from simulator.truth import load_truth

    out = tmp_path_factory.mktemp("standard")
    generate(out, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=7, drop=True, date="261122")
    return out
