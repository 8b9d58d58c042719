"""The E-STOP's press-to-answer time on a served virtual rig (rig.drivers.estop).

The rig runs a sine (hydraulics on, RUNNING); another thread keeps the main link busy
with back-to-back status reads, as a session's acquisition does; the E-STOP is pressed
``--presses`` times, the rig set running again between presses.  Printed: the time from
each press to both writes (STOP, hydraulics off) answered by the controller, median
and worst, beside the target of 0.3 s (rig.drivers.estop.BUDGET_S).

    python benchmarks/bench_estop.py [--presses 20] [--speed 10]

The last line reads ``e-stop: median M ms, worst W ms (target 300 ms)``.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from rig.config import load_rig_config  # noqa: E402
from rig.drivers.estop import BUDGET_S, EStop  # noqa: E402
from rig.drivers.registers import (
    ControllerState,
    load_register_map,  # noqa: E402
)
from rig.drivers.shaker import Shaker  # noqa: E402
from rig.virtual import VirtualRig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presses", type=int, default=20)
    ap.add_argument("--speed", type=float, default=10.0)
    args = ap.parse_args()
    limits, register_map = load_rig_config().limits, load_register_map()
    with VirtualRig(speed=args.speed) as sim:
        main_link = Shaker(sim.modbus_url, limits, register_map)
        main_link.connect(heartbeat=False)
        estop = EStop(limits, register_map, fallback=lambda: main_link)
        estop.open(sim.modbus_url)
        stop = threading.Event()

        def busy() -> None:
            while not stop.is_set():
                main_link.status()
        poller = threading.Thread(target=busy, name="main-link-busy", daemon=True)
        times = []
        try:
            for _ in range(args.presses):
                estop.confirm_reset()
                main_link.move_to(0.133, switch_on=True)
                main_link.wait_for({ControllerState.AT_STATIC}, 60.0)
                main_link.run(0.133, 0.005, 2.0, "sine", 0.5)
                main_link.wait_for({ControllerState.RUNNING}, 60.0)
                if not poller.is_alive():
                    poller.start()
                estop.press()
                done = estop.wait(30.0)
                if done is None or done.failures:
                    raise SystemExit(f"the E-STOP failed: {done}")
                times.append(done.elapsed_s)
        finally:
            stop.set()
            estop.close()
            main_link.close()
    ms = np.array(times) * 1e3
    print(f"{len(ms)} presses at {args.speed:g}x with the main link busy: "
          + ", ".join(f"{t:.0f}" for t in ms) + " ms")
    print(f"e-stop: median {np.median(ms):.0f} ms, worst {ms.max():.0f} ms (target {BUDGET_S * 1e3:.0f} ms)")


if __name__ == "__main__":
    main()
