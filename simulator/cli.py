"""``python -m simulator``: the virtual shaker rig.

``serve`` runs the rig behind its two real interfaces (Modbus controller, serial DAQ);
``generate`` writes a dataset in the interchange format without the protocol loop.

Exit status: 0 done (``serve``: stopped by SIGINT/SIGTERM); 2 bad input (an option, a
truth file, a fault or an endpoint; one line naming it).  Anything else is a bug and
shows its traceback.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import signal
import sys
import threading
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from identify.argparsing import OneLineParser
from identify.errors import InputError
from identify.plans import STANDARD_SET, ExperimentSpec, select
from simulator.errors import SimulatorError, UsageError
from simulator.faults import parse_fault
from simulator.generate import generate
from simulator.physics import Damper, past_the_stops
from simulator.plant import PlantDamper, load_plant, variant_names
from simulator.plant.drop import DROP_VELOCITY_M_S
from simulator.truth import load_truth
from simulator.units import UNITS


def read_plan(source: str) -> tuple[ExperimentSpec, ...]:
    """``standard`` or a plan TOML with ``[[experiment]]`` tables, the format ``rig run
    --plan`` reads (a QC spec holds its plan that way too)."""
    if source == "standard":
        return STANDARD_SET
    if not Path(source).exists():   # a misspelt name reads as a missing file
        hint = " (did you mean 'standard'?)" if difflib.get_close_matches(source, ["standard"]) else ""
        raise UsageError(f"--plan {source}: no such plan and no such file{hint}; the plans: standard (built in), "
                         "or the path of a plan TOML file")
    try:
        doc = tomllib.loads(Path(source).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise UsageError(f"--plan {source}: {exc}") from None
    try:
        return tuple(ExperimentSpec(str(e["label"]), str(e.get("group", "")), float(e["static_mm"]),
                                    float(e["amplitude_mm"]), float(e["frequency_Hz"]), str(e.get("waveform", "sine")),
                                    int(e.get("periods", doc.get("periods", 3))))
                     for e in doc.get("experiment", []))
    except (KeyError, TypeError, ValueError) as exc:
        raise UsageError(f"--plan {source}: an [[experiment]] table without a usable {exc}") from None


def run_generate(args: argparse.Namespace) -> int:
    if args.periods is not None and args.periods < 1:
        raise UsageError(f"--periods {args.periods}: at least one whole period")
    if args.rate <= 0:
        raise UsageError(f"--rate {args.rate:g}: must be positive")
    if args.ramp < 0:
        raise UsageError(f"--ramp {args.ramp:g}: must be 0 or more seconds")
    if args.drop_velocity < 0:
        raise UsageError(f"--drop-velocity {args.drop_velocity:g}: a touchdown speed, 0 or more m/s")
    if args.capture == "transient" and args.model != "2dof":
        raise UsageError("--capture transient: the record from rest needs --model 2dof (the gas temperature state)")
    letters = [x.strip() for x in args.experiments.split(",")] if args.experiments else None
    plan = select(read_plan(args.plan), letters)
    if not plan:
        raise UsageError(f"--plan {args.plan}: no [[experiment]] tables")
    for spec in plan:
        past = past_the_stops(spec)
        if past:
            raise UsageError(f"--plan {args.plan}: experiment {spec.letter} {past}; nothing generated")
    t0 = time.perf_counter()
    truth = _truth(args)
    out = generate(args.out, plan, truth, periods=args.periods, rate_hz=args.rate, seed=args.seed, drop=args.drop,
                   date=args.date, noise_scale=args.noise_scale, serial=args.serial,
                   capture=args.capture, ramp_s=args.ramp, drop_velocity_m_s=args.drop_velocity)
    print(f"wrote {out} ({len(plan)} experiments{' + drop test' if args.drop else ''}, {args.physics} physics, "
          f"{time.perf_counter() - t0:.1f} s)")
    return 0


def _truth(args: argparse.Namespace) -> Damper | PlantDamper:
    """The damper of the chosen physics tier: the model's θ (``--params``, ``--model``)
    or the plant truth (``--plant-constants``); a production unit in either."""
    if args.physics == "model":
        if args.plant_constants or args.plant_variant:
            option = "--plant-constants" if args.plant_constants else "--plant-variant"
            raise UsageError(f"{option}: only with --physics plant (the model tier takes --params)")
        return load_truth(args.params, args.model, args.unit, args.unit_seed)
    if args.params:
        raise UsageError(f"--params {args.params}: the plant truth has no θ; give its constants with "
                         "--plant-constants FILE.toml (see simulator/plant/constants.toml)")
    if args.model != "2dof":
        raise UsageError(f"--model {args.model}: only with --physics model (the plant is no identification model)")
    return load_plant(args.unit, args.unit_seed, args.plant_constants, args.plant_variant)


@dataclass(frozen=True)
class Endpoint:
    """Where the simulator serves one link: TCP (host, port) or a pseudo-terminal,
    optionally linked at ``link`` (a path the operator chose, given to ``rig`` as is)."""

    tcp: tuple[str, int] | None = None
    link: Path | None = None


MODBUS_FORMS = "tcp://HOST:PORT, HOST:PORT, rtu:pty or rtu:///PATH (a pseudo-terminal linked at PATH)"
DAQ_FORMS = "socket://HOST:PORT, tcp://HOST:PORT, pty or a PATH (a pseudo-terminal linked there)"


def _host_port(text: str, option: str, whole: str, forms: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or "/" in host or not port.isdigit() or int(port) > 65535:
        raise UsageError(f"{option} {whole!r}: expected {forms}, with a port 0…65535")
    return host.strip("[]") or "127.0.0.1", int(port)


def _link(path: str, option: str) -> Path:
    link = Path(path).absolute()
    if link.exists() or link.is_symlink():
        raise UsageError(f"{option} {path}: the path exists; the simulator links its pseudo-terminal at a new path "
                         "and replaces nothing")
    if not link.parent.is_dir():
        raise UsageError(f"{option} {path}: no folder {link.parent} to link the pseudo-terminal in")
    return link


def parse_modbus(text: str) -> Endpoint:
    """``--modbus``: the forms ``rig --shaker`` takes (``tcp://HOST:PORT``,
    ``rtu:///PATH``), the bare ``HOST:PORT`` of earlier versions, and ``rtu:pty``."""
    if text in ("rtu:pty", "rtu://pty"):
        return Endpoint()
    if text.startswith("rtu://"):
        path = text[len("rtu://"):]
        if not path.startswith("/"):
            raise UsageError(f"--modbus {text!r}: expected {MODBUS_FORMS}")
        return Endpoint(link=_link(path, "--modbus"))
    if text.startswith("tcp://"):
        return Endpoint(tcp=_host_port(text[len("tcp://"):], "--modbus", text, MODBUS_FORMS))
    if "://" in text:
        raise UsageError(f"--modbus {text!r}: expected {MODBUS_FORMS}")
    return Endpoint(tcp=_host_port(text, "--modbus", text, MODBUS_FORMS))


def parse_daq(text: str) -> Endpoint:
    """``--daq``: the forms ``rig --daq`` takes (``socket://HOST:PORT``, a device path:
    here a pseudo-terminal linked at that path), ``tcp://HOST:PORT`` of earlier
    versions, and ``pty`` (a pseudo-terminal of the system's choosing)."""
    if text == "pty":
        return Endpoint()
    for scheme in ("socket://", "tcp://"):
        if text.startswith(scheme):
            return Endpoint(tcp=_host_port(text[len(scheme):], "--daq", text, DAQ_FORMS))
    if "://" in text or not text:
        raise UsageError(f"--daq {text!r}: expected {DAQ_FORMS}")
    return Endpoint(link=_link(text, "--daq"))


def _linked(device: str, link: Path | None, made: list[Path]) -> str:
    """The pseudo-terminal's device, or ``link`` made to point at it (removed on exit)."""
    if link is None:
        return device
    try:
        link.symlink_to(device)
    except OSError as exc:
        raise UsageError(f"cannot link the pseudo-terminal at {link}: {exc.strerror or exc}") from None
    made.append(link)
    return str(link)


class StateFile:
    """``serve --state FILE``: what a program driving the simulator needs to know, as JSON
    it reads instead of the log meant for people.  Rewritten whole (atomically) once the
    endpoints are open (``state`` "serving", ``modbus``, ``daq``), at each hydraulics
    switching (``hydraulics``: [simulated s, on] pairs) and at exit (``state`` "stopped",
    ``t_s``, ``lost_frames`` and ``lost`` by kind: the DAQ frames lost to injected faults)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.doc: dict[str, Any] = {"format": 1, "pid": os.getpid(), "state": "starting", "hydraulics": []}
        self._lock = threading.Lock()

    def update(self, **fields: Any) -> None:
        with self._lock:
            self.doc.update(fields)
            tmp = self.path.with_name(f".{self.path.name}.tmp")
            tmp.write_text(json.dumps(self.doc) + "\n")
            os.replace(tmp, self.path)   # a reader sees the old document or the new one, never half


def run_serve(args: argparse.Namespace) -> int:
    from simulator.daq import Port, PtyPort, TcpPort
    from simulator.engine import VirtualRig

    if args.speed <= 0:
        raise UsageError(f"--speed {args.speed}: must be positive")
    if args.drop_velocity < 0:
        raise UsageError(f"--drop-velocity {args.drop_velocity:g}: a touchdown speed, 0 or more m/s")
    damper = _truth(args)  # refused before any endpoint opens
    faults = [parse_fault(f) for f in args.fault]
    modbus, daq = parse_modbus(args.modbus), parse_daq(args.daq)
    if daq.tcp is None and any(f.kind == "disconnect" for f in faults):
        raise UsageError("--fault disconnect needs the TCP DAQ (a pseudo-terminal cannot be unplugged)")
    bridge = None
    if modbus.tcp is None:
        from simulator.daq import PtyBridge

        bridge = PtyBridge()
    host, port = modbus.tcp or ("", 0)
    daq_port: Port
    if daq.tcp is None:
        daq_port = PtyPort()
    else:
        try:
            daq_port = TcpPort(*daq.tcp)
        except OSError as exc:
            if bridge:
                bridge.close()
            raise UsageError(f"cannot open the DAQ endpoint {args.daq}: {exc.strerror or exc}") from None
    rig = VirtualRig(damper, daq_port, speed=args.speed, seed=args.seed,
                     faults=faults, modbus_host=host, modbus_port=port,
                     modbus_serial=bridge.server_path if bridge else None, rig_type=args.rig,
                     drop_mass_kg=args.drop_mass, drop_velocity_m_s=args.drop_velocity)
    state = StateFile(Path(args.state)) if args.state else None
    if state is not None:
        rig.on_state = lambda: state.update(hydraulics=[[t, on] for t, on in rig.hydraulics])
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    links: list[Path] = []
    try:
        try:
            rig.start()
        except (OSError, RuntimeError) as exc:   # pymodbus says a busy port with a RuntimeError
            daq_port.close()
            raise UsageError(f"cannot open the Modbus endpoint {host}:{port}: "
                             f"{getattr(exc, 'strerror', None) or exc} (is another simulator using it?)") from None
        try:
            # What rig takes, verbatim: a pseudo-terminal by the path asked for, where one was.
            modbus_url = f"rtu://{_linked(bridge.client_path, modbus.link, links)}" if bridge else rig.modbus.url
            daq_url = _linked(daq_port.url, daq.link, links) if daq.tcp is None else daq_port.url
            if state is not None:   # before the lines below: whoever waits for them finds the file
                state.update(state="serving", modbus=modbus_url, daq=daq_url, speed=args.speed)
            print(f"modbus {modbus_url}", flush=True)
            print(f"daq {daq_url}", flush=True)
            print(f"rig options: --shaker {modbus_url} --daq {daq_url}", flush=True)
            while not stop.wait(0.2):
                pass
        finally:
            rig.close()
            if state is not None:
                state.update(state="stopped", t_s=rig.t, lost_frames=rig.daq.lost_frames, lost=dict(rig.daq.lost))
            print(f"simulator stopped at simulated t = {rig.t:.1f} s; DAQ frames lost by faults: "
                  f"{rig.daq.lost_frames} {rig.daq.lost}", file=sys.stderr, flush=True)
    finally:
        if bridge:
            bridge.close()
        for link in links:
            link.unlink(missing_ok=True)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m simulator", description="virtual shaker rig")
    sub = parser.add_subparsers(dest="command", required=True)
    def physics_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--physics", choices=("model", "plant"), default="model",
                       help="model: the identification model's own equations with the θ of --params (default); "
                            "plant: the plant truth, richer than any identification model (docs/plant.md)")
        p.add_argument("--plant-constants", metavar="FILE.toml",
                       help="the plant's constants (--physics plant; default simulator/plant/constants.toml)")
        p.add_argument("--plant-variant", choices=variant_names(), metavar="NAME",
                       help="a named plausible plant (--physics plant): its constants moved within their brackets, "
                            f"applied to --plant-constants; one of {', '.join(variant_names())} (docs/plant.md)")

    def unit_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--unit", choices=UNITS,
                       help="a production unit: the nominal damper with a seeded production scatter (good) or a "
                            "typical fault; parameters named in --params override the unit's")
        p.add_argument("--unit-seed", type=int, default=0, help="which unit of the batch (default 0)")

    gen = sub.add_parser("generate", help="write a dataset (steady states of a plan) without the protocol loop")
    gen.add_argument("--plan", default="standard", help="standard, or a plan TOML (a QC spec too)")
    gen.add_argument("--params", help="true parameters (START.json format; default: nominal)")
    gen.add_argument("--model", choices=("2dof", "1dof"), default="2dof")
    physics_options(gen)
    unit_options(gen)
    gen.add_argument("--serial", default="SIM-0001", help="the unit's serial number in dataset.json")
    gen.add_argument("--out", required=True, help="dataset folder to write")
    gen.add_argument("--experiments", help="comma-separated letters of the plan (default: all)")
    gen.add_argument("--periods", type=int, help="periods per experiment (default: the plan's; standard: 3)")
    gen.add_argument("--rate", type=float, default=2000.0, help="sample rate, Hz")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--drop", action="store_true",
                     help="add the drop test (350 kg touching down at --drop-velocity)")
    gen.add_argument("--drop-velocity", type=float, default=DROP_VELOCITY_M_S, metavar="M_S",
                     help=f"the drop's velocity at touchdown (q = 0), m/s (default {DROP_VELOCITY_M_S:g}: the "
                          "paper's landing; 0 releases the mass at rest on the extended damper)")
    gen.add_argument("--date", help="label date yymmdd (default: today)")
    gen.add_argument("--noise-scale", type=float, default=1.0, help="multiplies the transducer noise")
    gen.add_argument("--capture", choices=("steady", "transient"), default="steady",
                     help="record the periodic steady state (default), or from RUN on, started at rest with the "
                          "amplitude ramped over --ramp seconds (no waiting)")
    gen.add_argument("--ramp", type=float, default=2.0, help="amplitude ramp of a transient capture, s (default 2)")
    gen.set_defaults(func=run_generate)

    serve = sub.add_parser("serve", help="run the rig behind its Modbus controller and serial DAQ",
                           description="Run the virtual rig until SIGINT/SIGTERM. Once ready it prints one line "
                                       "per endpoint, the address as rig takes it ('modbus tcp://HOST:PORT', "
                                       "'daq socket://HOST:PORT' or 'daq /dev/pts/N'), then the line 'rig options: "
                                       "--shaker … --daq …'. Port 0 picks a free port.")
    serve.add_argument("--modbus", default="tcp://127.0.0.1:5020",
                       help="tcp://HOST:PORT (or HOST:PORT) of the Modbus TCP server; rtu:pty for Modbus RTU on a "
                            "pseudo-terminal, rtu:///PATH for one linked at PATH")
    serve.add_argument("--daq", default="pty", help="socket://HOST:PORT (or tcp://HOST:PORT) of the DAQ's TCP "
                                                    "line; pty for a pseudo-terminal, or a PATH to link one at")
    serve.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second")
    serve.add_argument("--params", help="true parameters (START.json format; default: nominal)")
    serve.add_argument("--model", choices=("2dof", "1dof"), default="2dof")
    physics_options(serve)
    unit_options(serve)
    serve.add_argument("--seed", type=int, default=0)
    serve.add_argument("--rig", choices=("shaker", "drop"), default="shaker",
                       help="drop: a drop-test rig; RUN (mode 2, hydraulics on) lets the mass touch down at q = 0 at "
                            "--drop-velocity")
    serve.add_argument("--drop-mass", type=float, default=350.0, help="dropped mass, kg (drop rig)")
    serve.add_argument("--drop-velocity", type=float, default=DROP_VELOCITY_M_S, metavar="M_S",
                       help=f"the mass's velocity at touchdown (q = 0), m/s (drop rig; default {DROP_VELOCITY_M_S:g})")
    serve.add_argument("--fault", action="append", default=[], metavar="KIND[@T][=V]",
                       help="inject a fault (repeatable): corrupt=P, drop=P, overflow@T=N, stall@T=D, "
                            "disconnect@T, modbus-down@T=D, hydraulic-loss@T[=D], estop@T, drift=CH:RATE[@T], "
                            "gain=CH:REL[@T], servo-drift@T=MM_PER_S; "
                            "T in simulated s, or run+T for T s after the first RUN")
    serve.add_argument("--state", metavar="FILE.json",
                       help="keep FILE.json up to date for a program driving the simulator: the endpoints once "
                            "ready, each hydraulics switching, and at exit the DAQ frames lost by faults")
    serve.set_defaults(func=run_serve)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (SimulatorError, InputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
