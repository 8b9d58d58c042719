"""``python -m rig``: run a planned session, or look at and command the rig by hand.

``run``      a plan of experiments → a session folder (and identification with --identify)
``status``   the controller's state, alarm, position, force
``move``     hydraulics on and move to a static position
``stop``     stop motion, fade out or switch the hydraulics off; reset a latched alarm
``monitor``  live channel values and loss counters in the terminal
``gui``      the operator's console: live view, manual control, plans, fits, sessions
``qc``       quality control of production dampers (run, judge, history)
``design``   a plan of experiments for a precision goal at the least predicted rig time
``log-times`` a session's predicted against real rig time, phase by phase, from its session.log

Exit status (every command): 0 done; 1 identification did not converge (``run
--identify``); 2 bad input (a file, address or argument; one line naming it, and
nothing moved or written); 3 the rig failed or refused (a dead link, an alarm, a
controller or DAQ fault) after the safe stop; 70 an internal error (a bug: traceback
shown) after the safe stop; 130 interrupted after the safe stop.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import traceback
from pathlib import Path

from identify.argparsing import OneLineParser
from identify.errors import InputError
from identify.exit_codes import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK
from identify.model import DEFAULT_ESTIMATE
from rig.config import load_rig_config
from rig.drivers.daq import Calibration, Daq
from rig.drivers.registers import ControllerState, load_register_map
from rig.drivers.shaker import LimitError, Shaker
from rig.errors import BadInput, RigFault
from rig.gui.options import ConsoleOptions, add_console_arguments, add_link_arguments
from rig.planning.plans import comma_list
from rig.qc.cli import add_parser as add_qc_parser
from rig.session.run import RunOptions, run_session


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


def _shaker(args: argparse.Namespace) -> Shaker:
    """A connection for one manual command.  Nothing feeds the watchdog once the command
    returns, so manual commands switch it off; ``run`` switches it on again."""
    config = load_rig_config(args.rig_config)
    shaker = Shaker(args.shaker, config.limits, load_register_map(args.register_map), reconnect_s=2.0)
    shaker.connect(heartbeat=False)
    shaker.disable_watchdog()
    return shaker


def cmd_run(args: argparse.Namespace) -> int:
    if not args.resume and not (args.shaker and args.daq):
        raise BadInput("run: --shaker and --daq are needed (only --resume takes them from the session)")
    opt = RunOptions(plan=args.plan, shaker=args.shaker, daq=args.daq, out=Path(args.out),
                     experiments=comma_list(args.experiments), periods=args.periods, order=args.order,
                     resume=args.resume,
                     reset_alarm=args.reset_alarm, identify=args.identify, on_alarm=args.on_alarm,
                     rig_config=args.rig_config, calibration=args.calibration, register_map=args.register_map,
                     model=args.model, params=args.params, estimate=comma_list(args.estimate) or [], date=args.date,
                     unit_serial=args.unit)
    return run_session(opt)


def cmd_log_times(args: argparse.Namespace) -> int:
    from rig.session.timing import format_times, log_times

    print(format_times(log_times(args.session)))
    return EXIT_OK


def cmd_status(args: argparse.Namespace) -> int:
    shaker = _shaker(args)
    try:
        st = shaker.status()
    finally:
        shaker.close()
    print(f"state {st.state}  alarm {st.alarm}  position {st.position_m * 1e3:.2f} mm  "
          f"force {st.force_n / 1e3:.2f} kN  cycles {st.cycles}  supply {st.hydraulic_pressure_pa / 1e5:.0f} bar")
    return EXIT_OK if st.state is not ControllerState.ALARM else EXIT_ABORTED


def cmd_move(args: argparse.Namespace) -> int:
    shaker = _shaker(args)
    try:
        try:
            shaker.move_to(args.position_mm * 1e-3, switch_on=True)
            if args.wait:
                st = shaker.wait_for({ControllerState.AT_STATIC}, timeout_s=args.wait)
                print(f"at static position {st.position_m * 1e3:.2f} mm")
        except LimitError:
            raise  # refused before anything was sent: nothing moves, nothing to stop
        except BaseException:
            # The actuator may be moving and nobody will watch it: hold it and take the pressure off.
            for step in (shaker.stop, lambda: shaker.hydraulics(False)):
                try:
                    step()
                except Exception as exc:  # noqa: BLE001 — the original error is the one to report
                    print(f"safe stop step failed: {exc}", file=sys.stderr)
            raise
    finally:
        shaker.close()
    return EXIT_OK


def cmd_stop(args: argparse.Namespace) -> int:
    shaker = _shaker(args)
    try:
        if args.reset:
            shaker.reset_alarm()
        elif args.fade and shaker.status().state is ControllerState.RUNNING:
            shaker.fade_out()
        else:
            if args.fade:
                print("nothing runs: no waveform to fade out; STOP sent", file=sys.stderr)
            shaker.stop()
        if args.hydraulics_off:
            shaker.hydraulics(False)
        st = shaker.status()
        print(f"state {st.state}  alarm {st.alarm}")
    finally:
        shaker.close()
    return EXIT_OK


def cmd_monitor(args: argparse.Namespace) -> int:
    from rich.live import Live
    from rich.table import Table

    daq = Daq(args.daq, Calibration.from_file(args.calibration), rate_hz=args.rate)
    print(daq.open(), file=sys.stderr)
    daq.start()
    deadline = time.monotonic() + args.duration if args.duration else None

    def table() -> Table:
        t = Table(title=f"DAQ {args.daq}")
        for col in ("channel", "value", "unit"):
            t.add_column(col)
        _, values = daq.ring.latest(max(args.rate // 10, 1))
        mean = values.mean(axis=0) if len(values) else [float("nan")] * 4
        for name, unit, v in zip(daq.calibration.names, daq.calibration.units, mean, strict=True):
            t.add_row(name, f"{v:10.3f}", unit)
        c = daq.counters
        t.caption = (f"received {daq.parser.received}  lost {c.lost_samples}  overflow flags {c.overflow_flags}  "
                     f"CRC errors {c.crc_errors}  over range {c.over_range}")
        return t

    try:
        with Live(table(), refresh_per_second=5, transient=False) as live:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.2)
                live.update(table())
    except KeyboardInterrupt:
        pass
    finally:
        daq.close()
    return EXIT_OK


def cmd_design(args: argparse.Namespace) -> int:
    from rig.design import DesignOptions, run_design  # numerics only this command needs

    return run_design(DesignOptions.from_args(args))


def cmd_gui(args: argparse.Namespace) -> int:
    from rig.gui.main_window import run_gui  # Qt is loaded for this command only

    return run_gui(ConsoleOptions.from_namespace(args))


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m rig", description=(__doc__ or "").replace("``", ""),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a plan of experiments into a session folder")
    add_link_arguments(run, shaker_required=False)
    run.add_argument("--plan", default="standard", help="standard or PLAN.toml")
    run.add_argument("--daq", help="device path, socket://HOST:PORT or any pyserial URL")
    run.add_argument("--out", required=True, help="session folder")
    run.add_argument("--experiments", help="comma-separated letters of the plan (default: all)")
    run.add_argument("--periods", type=_positive_int, help="whole periods to capture (default: the plan's)")
    run.add_argument("--order", choices=("thermal", "fixed"),
                     help="thermal: the order of least predicted rig time; fixed: as listed (default: the plan's "
                          "order: thermal for the standard plan, a plan file's as listed unless it says "
                          "order = \"thermal\"; a --experiments list as given)")
    run.add_argument("--resume", action="store_true",
                     help="continue an interrupted session in --out (addresses default to the session's)")
    run.add_argument("--reset-alarm", action="store_true",
                     help="clear an alarm the controller latched before this session (it is read and logged first)")
    run.add_argument("--identify", action="store_true", help="identify right after the last capture")
    run.add_argument("--on-alarm", choices=("abort", "skip"), default="abort",
                     help="after an alarm and the safe stop: end the session, or reset and go on")
    run.add_argument("--calibration", help="DAQ calibration TOML of this rig")
    run.add_argument("--model", default="2dof", help="model for --identify")
    run.add_argument("--params", help="start values and priors for --identify (default: nominal)")
    run.add_argument("--estimate", help="parameters for --identify (default: those the plan was designed for, its "
                                        "[purpose]; else " + ",".join(DEFAULT_ESTIMATE["2dof"]) + " for 2dof)")
    run.add_argument("--date", help="label date yymmdd (default: today)")
    run.add_argument("--unit", default="unknown", help="serial number of the damper under test")
    run.set_defaults(func=cmd_run)

    status = sub.add_parser("status", help="controller state, alarm, position, force")
    add_link_arguments(status)
    status.set_defaults(func=cmd_status)

    move = sub.add_parser("move", help="hydraulics on and move to a static position")
    add_link_arguments(move)
    move.add_argument("position_mm", type=float)
    move.add_argument("--wait", type=float, default=60.0, help="seconds to wait for AT_STATIC (0: do not wait)")
    move.set_defaults(func=cmd_move)

    stop = sub.add_parser("stop", help="stop motion (or fade out, or reset an alarm)")
    add_link_arguments(stop)
    stop.add_argument("--fade", action="store_true", help="fade the waveform out instead of stopping at once")
    stop.add_argument("--reset", action="store_true", help="reset a latched alarm")
    stop.add_argument("--hydraulics-off", action="store_true")
    stop.set_defaults(func=cmd_stop)

    mon = sub.add_parser("monitor", help="live channel values and loss counters")
    mon.add_argument("--daq", required=True)
    mon.add_argument("--calibration")
    mon.add_argument("--rate", type=int, default=1000)
    mon.add_argument("--duration", type=float, help="seconds (default: until Ctrl-C)")
    mon.set_defaults(func=cmd_monitor)

    gui = sub.add_parser("gui", help="the operator's console (live view, manual control, plans, fits)")
    add_console_arguments(gui)
    gui.set_defaults(func=cmd_gui)

    des = sub.add_parser("design", help="a plan for a precision goal at the least predicted rig time")
    goal = des.add_mutually_exclusive_group(required=True)
    goal.add_argument("--target", help="parameters whose σ the plan must reach, e.g. theta4,theta6,theta16")
    goal.add_argument("--qc-spec", help="a QC spec (default or SPEC.toml): its characteristics to a quarter of "
                                        "their tolerance half-width")
    goal.add_argument("--predict", choices=("drop",), help="drop: the drop test's (350 kg, 0.5 m/s) peak force "
                                                           "and peak stroke predicted to --accuracy")
    des.add_argument("--accuracy", type=float, default=0.02, help="--predict: relative σ wanted (default 0.02)")
    des.add_argument("--discrepancy", type=float, default=0.0,
                     help="--predict: relative model-discrepancy σ of the drop (from a type test; default 0)")
    des.add_argument("--estimate", help="--predict: estimated parameters (default theta3,theta4,theta5,theta6,theta8,"
                                        "theta16)")
    des.add_argument("--no-worse-than", metavar="PLAN", help="--target: every σ at most this plan's (standard or "
                                                              "PLAN.toml)")
    des.add_argument("--sigma", help="--target: the σ wanted, SI, one per parameter (comma-separated)")
    des.add_argument("--compare", metavar="PLAN", help="a reference plan predicted beside the design (standard or "
                                                       "PLAN.toml)")
    des.add_argument("--model", default="2dof", help="--target, --predict: the model")
    des.add_argument("--params", help="--target, --predict: prior parameter values (START.json; default: nominal)")
    des.add_argument("--rig-config", help="limits, criteria and transducer noise TOML (default: rig-default.toml)")
    des.add_argument("--out", required=True, help="the plan file to write")
    des.add_argument("--shaker", help="with --daq: measure these links' pace and latencies now (nothing moves) and "
                                      "predict the rig time at them (default: the last measured on this computer)")
    des.add_argument("--daq", help="with --shaker (see there)")
    des.set_defaults(func=cmd_design)

    times = sub.add_parser("log-times", help="a session's predicted against real rig time, phase by phase")
    times.add_argument("session", help="session folder (its session.log)")
    times.set_defaults(func=cmd_log_times)

    add_qc_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The command line's one error boundary: known errors become one line and their
    exit status; anything else is a bug and keeps its traceback."""
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    # The drivers say in their own words when a link fails; pymodbus's log lines would
    # put a second, rawer message before the one that counts.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        return int(args.func(args))
    except (BadInput, InputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RigFault as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ABORTED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception:
        traceback.print_exc()
        print("internal error: a bug, please report it with the traceback above", file=sys.stderr)
        return EXIT_INTERNAL
