"""What the console is started with (``python -m rig gui …``), as a typed record: the
command line builds it, the window reads it, and neither imports the other (no Qt here).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from identify.argparsing import OneLineParser


def add_link_arguments(p: argparse.ArgumentParser, shaker_required: bool = True) -> None:
    """The controller's address and its configuration files (every ``rig`` command that talks to it)."""
    p.add_argument("--shaker", required=shaker_required, help="tcp://HOST:PORT or rtu:///dev/DEVICE")
    p.add_argument("--register-map", help="register map TOML (default: the datasheet's)")
    p.add_argument("--rig-config", help="limits and steady-state criteria TOML (default: rig/config/rig-default.toml)")


def add_console_arguments(p: argparse.ArgumentParser) -> None:
    add_link_arguments(p, shaker_required=False)
    p.add_argument("--daq", help="device path, socket://HOST:PORT or any pyserial URL")
    p.add_argument("--simulate", action="store_true",
                   help="start the virtual rig (python -m simulator serve) on free loopback ports and use it")
    p.add_argument("--speed", type=float, default=1.0, help="--simulate: simulated seconds per wall second")
    p.add_argument("--unit", choices=("good", "gas-leak", "worn-seal", "worn-orifice"),
                   help="--simulate: the production unit the simulated rig holds (QC practice)")
    p.add_argument("--params", help="--simulate: the simulated damper's true parameters (TRUTH.json)")
    p.add_argument("--fault", action="append", default=[], metavar="KIND[@T][=V]",
                   help="--simulate: a fault to inject (repeatable; see python -m simulator serve --help)")
    p.add_argument("--plan", default="standard", help="standard or PLAN.toml")
    p.add_argument("--experiments", help="comma-separated letters of the plan (default: all)")
    p.add_argument("--out", default="sessions", help="folder in which new session folders are made")
    p.add_argument("--calibration", help="DAQ calibration TOML of this rig")


@dataclass(frozen=True)
class ConsoleOptions:
    shaker: str | None = None
    daq: str | None = None
    simulate: bool = False
    speed: float = 1.0                       # simulated seconds per wall second (--simulate)
    params: str | None = None                # the simulated damper's truth (--simulate)
    faults: tuple[str, ...] = ()             # injected into the simulator (--simulate)
    unit: str | None = None                  # the production unit the simulator holds (--simulate)
    plan: str = "standard"
    experiments: str | None = None           # comma-separated letters, as typed
    out: Path = Path("sessions")
    calibration: str | None = None
    rig_config: str | None = None
    register_map: str | None = None

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> ConsoleOptions:
        return cls(shaker=args.shaker, daq=args.daq, simulate=args.simulate, speed=args.speed, params=args.params,
                   faults=tuple(args.fault), unit=args.unit, plan=args.plan, experiments=args.experiments,
                   out=Path(args.out),
                   calibration=args.calibration, rig_config=args.rig_config, register_map=args.register_map)

    @classmethod
    def parse(cls, argv: Sequence[str]) -> ConsoleOptions:
        """The options of ``python -m rig gui ARGV`` (``gui`` itself may be left out)."""
        argv = list(argv)
        parser = OneLineParser(prog="python -m rig gui")
        add_console_arguments(parser)
        return cls.from_namespace(parser.parse_args(argv[1:] if argv[:1] == ["gui"] else argv))
