"""``python -m simulator``: the virtual shaker rig.

``generate`` writes a dataset in the interchange format without the protocol loop.
"""

from __future__ import annotations

import argparse
import sys
import time

from identify.parameters import ParameterError
from identify.plans import STANDARD_SET, select
from simulator.generate import generate
from simulator.truth import load_truth


def run_generate(args: argparse.Namespace) -> int:
    if args.plan != "standard":
        raise ValueError(f"--plan {args.plan!r}: only the built-in 'standard' plan is available here")
    letters = [x.strip() for x in args.experiments.split(",")] if args.experiments else None
    plan = select(STANDARD_SET, letters)
    t0 = time.perf_counter()
    out = generate(args.out, plan, load_truth(args.params, args.model), periods=args.periods, rate_hz=args.rate,
                   seed=args.seed, drop=args.drop, date=args.date, noise_scale=args.noise_scale)
    print(f"wrote {out} ({len(plan)} experiments{' + drop test' if args.drop else ''}, "
          f"{time.perf_counter() - t0:.1f} s)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m simulator", description="virtual shaker rig")
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="write a dataset (steady states of a plan) without the protocol loop")
    gen.add_argument("--plan", default="standard")
    gen.add_argument("--params", help="true parameters (START.json format; default: nominal)")
    gen.add_argument("--model", choices=("2dof", "1dof"), default="2dof")
    gen.add_argument("--out", required=True, help="dataset folder to write")
    gen.add_argument("--experiments", help="comma-separated letters of the plan (default: all)")
    gen.add_argument("--periods", type=int, default=3)
    gen.add_argument("--rate", type=float, default=2000.0, help="sample rate, Hz")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--drop", action="store_true", help="add the drop test (350 kg, v0 = 0)")
    gen.add_argument("--date", help="label date yymmdd (default: today)")
    gen.add_argument("--noise-scale", type=float, default=1.0, help="multiplies the transducer noise")
    gen.set_defaults(func=run_generate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ParameterError, KeyError, ValueError) as exc:
        print(f"error: {exc.args[0] if isinstance(exc, KeyError) else exc}", file=sys.stderr)
        return 2
