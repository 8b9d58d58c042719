"""Do two versions of the code fit the benchmark sessions to the same numbers?  The check
behind every speed change of the fit: estimates and standard deviations at full
precision, dumped by one checkout and compared with another's dump.

Sessions: bench_fit's standard set (14 experiments, seed 1) and the first ``--sessions``
of bench_batch's generated sessions (3-5 experiments each), every fit from
examples/start-2dof.json as the benchmarks run it.

    python benchmarks/fit_digits.py dump BEFORE.json [--sessions 12]   # in the old checkout
    python benchmarks/fit_digits.py dump AFTER.json                    # in the new one
    python benchmarks/fit_digits.py compare BEFORE.json AFTER.json

``compare`` prints the largest relative difference of the estimates, their standard
deviations and the residual-based ones, the significant digits they share, and any fit
whose Gauss-Newton or Newton iteration counts changed; its exit status is 1 where fewer
than ``--digits`` (default 8) digits agree.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

from _setup import ESTIMATE, START  # first: one BLAS thread, set before numpy loads

# isort: split
from bench_batch import make_session

from identify.dataset import read_dataset
from identify.fit import fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.plans import STANDARD_SET
from identify.preparation import model_columns, resolve_outputs
from identify.result import FitResult
from simulator.generate import generate
from simulator.truth import load_truth

FIGURES = ("values", "std", "std_residual")


def record(result: FitResult) -> dict[str, object]:
    return {"values": [result.value(k) for k in ESTIMATE], "std": [result.std[k] for k in ESTIMATE],
            "std_residual": None if result.std_residual is None else [result.std_residual[k] for k in ESTIMATE],
            "iterations": result.iterations, "newton": [e.newton_iterations for e in result.experiments]}


def dump(out: Path, sessions: int) -> None:
    model = load_model("2dof")
    columns = model_columns(model, resolve_outputs(model, None))
    params = Parameters.from_file(model, str(START))
    fits: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folders = [Path(generate(Path(tmp) / "standard", list(STANDARD_SET), load_truth(), periods=3, rate_hz=2000.0,
                                 seed=1, date="261122"))]
        folders += [Path(make_session(Path(tmp) / f"unit-{i:03d}", i)) for i in range(sessions)]
        for folder in folders:
            experiments = [e for e in read_dataset(folder, columns).experiments if e.kind == "periodic"]
            fits[folder.name] = record(fit_experiments(model, experiments, params, ESTIMATE))
    out.write_text(json.dumps(fits, indent=1) + "\n")
    print(f"{len(fits)} fits written to {out}")


def compare(before: Path, after: Path, digits: int) -> int:
    a, b = (json.loads(p.read_text()) for p in (before, after))
    if a.keys() != b.keys():
        print(f"different sessions: {sorted(a.keys() ^ b.keys())}")
        return 1
    worst = dict.fromkeys(FIGURES, 0.0)
    for name in a:
        for key in FIGURES:
            x, y = a[name][key], b[name][key]
            if (x is None) != (y is None):
                print(f"{name}: {key} given by one only")
                return 1
            for u, v in zip(x or [], y or [], strict=True):
                worst[key] = max(worst[key], abs(u - v) / abs(u))
        if (a[name]["iterations"], a[name]["newton"]) != (b[name]["iterations"], b[name]["newton"]):
            print(f"{name}: iterations {a[name]['iterations']} -> {b[name]['iterations']}, Newton "
                  f"{a[name]['newton']} -> {b[name]['newton']}")
    shared = {k: (17 if v == 0 else min(17, int(math.floor(-math.log10(2 * v))))) for k, v in worst.items()}
    for key in FIGURES:
        print(f"  {key:13s} largest relative difference {worst[key]:.2e}  ({shared[key]} significant digits agree)")
    ok = min(shared.values()) >= digits
    print(f"{len(a)} fits: {'equal' if ok else 'NOT equal'} to {digits} significant digits")
    return 0 if ok else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    d = sub.add_parser("dump", help="fit the benchmark sessions, write estimates and sigmas")
    d.add_argument("out", type=Path)
    d.add_argument("--sessions", type=int, default=12, help="bench_batch sessions beside the standard set")
    c = sub.add_parser("compare", help="compare two dumps")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    c.add_argument("--digits", type=int, default=8)
    args = parser.parse_args()
    if args.command == "dump":
        dump(args.out, args.sessions)
        return 0
    return compare(args.before, args.after, args.digits)


if __name__ == "__main__":
    sys.exit(main())
