"""The pytest plugin for simulator-backed tests: the ``virtual_rig`` fixture.

Installing the project registers it (entry point ``pytest11``), so any test suite
gets the fixture with no conftest copying::

    def test_j_settles(virtual_rig, tmp_path):
        sim = virtual_rig(faults=["drop=0.001"])
        with rig.open(shaker=sim.modbus_url, daq=sim.daq_url) as r:
            session = r.run_plan("standard", experiments=["j"], out=tmp_path / "s")

Each call starts ``python -m simulator serve`` on free loopback ports, exactly as an
operator would, and returns a :class:`VirtualRig` handle.  Every rig a test started
is stopped at teardown, pass or fail; a failing test gets the simulator's log in its
report.  ``--virtual-rig-speed`` overrides the speed of every rig in a run (e.g. 1 to
watch a test at the rig's own pace); ``@pytest.mark.virtual_rig(speed=…, seed=…)``
sets a test's defaults.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator
from typing import Any

import pytest

from .virtual import VirtualRig

__all__ = ["VirtualRig", "virtual_rig"]


_RIGS = pytest.StashKey[list[VirtualRig]]()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.getgroup("virtual-rig").addoption(
        "--virtual-rig-speed", type=float, default=None,
        help="simulated seconds per wall second for every virtual_rig of the run (overrides the tests' own)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "virtual_rig(**defaults): defaults for the virtual_rig fixture of a test "
                                       "(speed, params, seed, faults, daq, rig, modbus)")


@pytest.fixture
def virtual_rig(request: pytest.FixtureRequest) -> Iterator[Callable[..., VirtualRig]]:
    """Factory: ``virtual_rig(speed=50, params=None, seed=1, faults=(), daq="tcp", rig="shaker",
    modbus="tcp", unit=None, unit_seed=None)`` starts a simulated rig and returns its :class:`VirtualRig`."""
    marker = request.node.get_closest_marker("virtual_rig")
    defaults: dict[str, Any] = dict(marker.kwargs) if marker else {}
    speed_override = request.config.getoption("--virtual-rig-speed")
    rigs: list[VirtualRig] = []
    request.node.stash[_RIGS] = rigs

    def start(**kwargs: Any) -> VirtualRig:
        options = {**defaults, **kwargs}
        if speed_override is not None:
            options["speed"] = speed_override
        rig = VirtualRig(**options)
        rigs.append(rig)
        return rig

    try:
        yield start
    finally:
        for rig in rigs:
            rig.stop()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item,
                              call: pytest.CallInfo[None]) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    rigs = item.stash.get(_RIGS, [])
    if report.failed and rigs:
        for i, rig in enumerate(rigs, 1):
            report.sections.append((f"virtual rig {i} log ({rig.modbus_url}, {rig.daq_url})", rig.log()))
    return report
