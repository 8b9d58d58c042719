"""What ``identify batch --db`` costs beside the batch alone, on QC production units.

Units: generated on the default QC spec's plan (seeded production scatter, every fourth
one a gas leak), all but the last judged once by ``qc judge`` into a fresh records
database (its first records).  Then, as ``python -m identify batch`` processes against
one LocalCluster of single-threaded workers (started here, so that the client's CPU time
is the child process's alone):

  * the batch without --db (the baseline), fresh RESULTS_DIR;
  * the batch with --db, fresh RESULTS_DIR: fits plus one re-judgement per recorded unit;
  * the same with --db again: every fit skipped, every re-judgement found (nothing added);

each with its wall time and the client process's CPU time.  Also: the CPU time of one
re-judgement's judging (the characteristics from a stored result, in this process),
which the client would spend per unit if it judged by itself instead of sending the
judging to the workers.  The machine may be shared: the load average is printed.

    python benchmarks/bench_batch_db.py [--units 8] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _setup import fit_env  # first: one BLAS thread, set before numpy loads

# isort: split
from identify import batch
from rig.qc.batch_sink import identified_from_result
from rig.qc.characteristics import check_model
from rig.qc.evaluate import evaluate_identified
from rig.qc.records import Records
from rig.qc.run import qc_judge
from rig.qc.spec import load_spec
from simulator.generate import generate
from simulator.truth import load_truth

SPEC = load_spec("default")


def make_unit(folder: Path, i: int) -> Path:
    unit = "gas-leak" if i % 4 == 3 else "good"
    return generate(folder, list(SPEC.plan.experiments), load_truth(None, "2dof", unit, 100 + i), periods=None,
                    seed=100 + i, date="261122", serial=f"SN-{100 + i:04d}")


def run(cmd: list[str]) -> tuple[float, float, str]:
    """Wall time, the child's CPU time (user + system) and its stdout."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=fit_env())
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 1):
        sys.exit(f"{' '.join(cmd)}: exit {proc.returncode}\n{out}")
    return wall, usage.ru_utime + usage.ru_stime, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp, batch.connect(workers=args.workers) as client:
        root = Path(tmp)
        folders = [root / "station" / f"SN-{100 + i:04d}" for i in range(args.units)]
        client.gather(client.map(make_unit, folders, range(args.units), pure=False))
        db = root / "station" / "qc-records.sqlite"
        Records.open(str(db), create=True).close()
        recorded = folders[:-1]
        client.gather(client.map(lambda f: qc_judge(f, "default", str(db), "bench"), recorded, pure=False))
        base = [sys.executable, "-m", "identify", "batch", *map(str, folders), "--estimate", ",".join(SPEC.estimate),
                "--n", str(SPEC.grid_points), "--scheduler", client.scheduler.address]
        rows = []
        for label, out, db_args in (("batch alone", "a", []), ("batch --db", "b", ["--db", str(db)]),
                                    ("batch --db, rerun", "b", ["--db", str(db)])):
            wall, cpu, stdout = run([*base, "--out", str(root / out), *db_args])
            summary = next((ln for ln in stdout.splitlines() if ln.startswith("QC records in")), "")
            rows.append((label, wall, cpu, summary.split(": ", 1)[-1]))
        doc = json.loads((root / "b" / f"{folders[0].name}.json").read_text())
        model = check_model(SPEC)
        identified = identified_from_result(model, doc)
        evaluate_identified(SPEC, folders[0], identified, [])          # warm: imports, model code
        t0 = time.process_time()
        evaluate_identified(SPEC, folders[0], identified, [])
        judging = time.process_time() - t0
        records = len(Records.open(str(db)).find())

    print(f"{args.units} units ({len(recorded)} with a QC record), {args.workers} workers, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'run':<20} {'wall [s]':>9} {'client CPU [s]':>15}  records")
    for label, wall, cpu, summary in rows:
        print(f"{label:<20} {wall:9.1f} {cpu:15.2f}  {summary}")
    extra = (rows[1][2] - rows[0][2]) / len(recorded)
    print(f"client CPU per re-judged unit with --db: {extra:.3f} s (judging on the workers); judging one unit "
          f"in the client instead would cost {judging:.2f} s CPU")
    print(f"records in the database: {records} (first {len(recorded)} + {records - len(recorded)} re-judgements)")


if __name__ == "__main__":
    main()
