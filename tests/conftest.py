"""Shared fixtures: a generated dataset with a known truth, reused by the slow tests."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # before any Qt import: CI has no display

import shutil
import tempfile
from pathlib import Path

# Sessions keep the links' measured timing for the next rig design (rig.planning.prediction):
# the tests' sessions keep theirs here, never in the developer's own state.
os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="damper-rig-tests-state-")

import pytest

# How long a test waits for a child process or a served simulator before calling it hung.
# A guard, never a budget: what a test checks it waits for as an event (an exit, a state,
# a line), so that it holds at any host load; a test that needs longer is broken, not slow.
HANG_S = 900.0

# Kept in the repository (see its PROVENANCE.md) so that a bare clone runs every test.
SILVERBOX = Path(__file__).resolve().parent / "data" / "silverbox"


def require_program(name: str) -> str:
    """Path of an outside program a test drives.  Where it is missing the test is
    skipped on a developer's machine but fails under CI (``CI`` set), which installs
    it (.ci/run): a test that CI skips silently checks nothing."""
    path = shutil.which(name)
    if path:
        return path
    if os.environ.get("CI", "").lower() not in ("", "0", "false"):
        pytest.fail(f"{name} is not installed; under CI this test must run (.ci/run installs it)")
    pytest.skip(f"{name} is not installed")


@pytest.fixture(scope="session")
def standard_dataset(tmp_path_factory) -> Path:
    """The standard set (14 experiments, 3 periods, 2 kHz) from the simulator, nominal truth."""
    from identify.plans import STANDARD_SET
    from simulator.generate import generate
    from simulator.truth import load_truth

    out = tmp_path_factory.mktemp("standard")
    generate(out, list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0, seed=7, drop=True, date="261122")
    return out


@pytest.fixture
def vrig(tmp_path: Path):
    """A connected in-process rig with quick settling (tests/virtual_rig_inprocess.py);
    a module may define its own ``vrig`` (test_estop's runs the default configuration)."""
    from tests.virtual_rig_inprocess import InProcessRig, quick_rig_config

    rig = InProcessRig(quick_rig_config(tmp_path))
    rig.connect()
    yield rig
    rig.close()
