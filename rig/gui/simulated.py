"""The console's simulated rig (``--simulate``): the simulator's process, started with
the console and stopped with it, its addresses, and the line that says it is not
hardware.  Nothing else of the console knows what the simulator was asked for."""

from __future__ import annotations

from rig.gui.options import ConsoleOptions
from rig.virtual import VirtualRig

SIMULATOR_NICE = 5      # the simulated hardware yields the CPU to the console, as real hardware would not need it


class SimulatedRig:
    def __init__(self, args: ConsoleOptions) -> None:
        self.process = VirtualRig(speed=args.speed, params=args.params, faults=list(args.faults), unit=args.unit,
                                  nice=SIMULATOR_NICE)
        self.asked_pace = args.speed     # said beside the pace the live view measures, never used for a time
        unit = f", unit {args.unit}" if args.unit else ""
        self.line = (f"SIMULATED RIG (python -m simulator serve, asked for {args.speed:g}× real time{unit}; "
                     "not hardware)")

    @property
    def modbus_url(self) -> str:
        return self.process.modbus_url

    @property
    def daq_url(self) -> str:
        return self.process.daq_url

    @property
    def running(self) -> bool:
        return self.process.running

    def log(self) -> str:
        return self.process.log()

    def stop(self) -> None:
        self.process.stop()
