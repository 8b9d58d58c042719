"""Several QC stations on one PostgreSQL at once: four stations (four served simulators,
four loops of ``python -m rig qc run``, each station with its own folder and
station.toml), ≥ 100 units in total, good and faulty, against a throwaway PostgreSQL
server (initdb + pg_ctl in a temporary folder, loopback port, password authentication;
the password only in each station's owner-only station.toml).

Prints the records that arrived per station (none lost, none twice: serials and uids
unique), the verdicts, wall time per unit and in total, and that ``qc history`` reads
every station's records by station.

    python benchmarks/bench_stations.py [--units 25] [--speed 50]

The QC spec is the default one with loose settling thresholds (tests/test_qc_run.py's
short_spec): the figures are about the records, not the plan.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig.virtual import VirtualRig  # noqa: E402
from tests.pgserver import STATION_PASSWORD, PgServer  # noqa: E402
from tests.stations import StationLoop, commission, make_station, run_stations  # noqa: E402
from tests.test_qc_run import short_spec  # noqa: E402

UNITS = ("good", "gas-leak", "worn-seal", "worn-orifice")
EXIT_VERDICT = {0: "PASS", 1: "FAIL", 4: "INCONCLUSIVE"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--units", type=int, default=25, help="units per station (default 25: 100 in total)")
    ap.add_argument("--speed", type=float, default=50.0, help="simulator speed (default 50x)")
    args = ap.parse_args()

    root = Path(tempfile.mkdtemp(prefix="bench-stations-"))
    os.chmod(root, 0o755)
    server = PgServer(root / "pg", "qc", "Pg-bench-7c1d")
    (root / "pg").mkdir()
    os.chmod(root / "pg", 0o755)
    sims: list[VirtualRig] = []
    try:
        server.start()
        spec = str(short_spec(root))
        url = server.records_database("bench")     # the administrator's schema; the stations' role writes
        loops = []
        for i, unit in enumerate(UNITS):
            sim = VirtualRig(unit=unit, unit_seed=i, seed=i + 1, speed=args.speed)
            sims.append(sim)
            folder = make_station(root / f"station-{i}", f"line1-{'ABCD'[i]}", url, STATION_PASSWORD)
            checked = commission(folder, sim.modbus_url, sim.daq_url, spec)
            if checked.returncode != 0:
                raise SystemExit(f"station {i} not commissioned:\n{checked.stdout}{checked.stderr}")
            loops.append(StationLoop(folder, f"S{'ABCD'[i]}", sim.modbus_url, sim.daq_url, args.units, spec,
                                     progress=True))
        t0 = time.monotonic()
        run_stations(loops)
        wall = time.monotonic() - t0
        env = {**os.environ, "PGPASSWORD": STATION_PASSWORD}
        r = subprocess.run([sys.executable, "-m", "rig", "qc", "history", "--db", url, "--json", "--all"],
                           capture_output=True, text=True, env=env, check=True)
        docs = json.loads(r.stdout)
        per_station = []
        for i, loop in enumerate(loops):
            name = f"line1-{'ABCD'[i]}"
            r = subprocess.run([sys.executable, "-m", "rig", "qc", "history", "--out", str(loop.folder), "--station",
                                name, "--include-simulated", "--chart", str(root / f"charts-{i}")],
                               capture_output=True, text=True, check=True)
            per_station.append((name, UNITS[i], sum(d["station"] == name for d in docs),
                                len(list((root / f"charts-{i}").glob("*.png"))), "warning" in r.stderr))
    finally:
        for sim in sims:
            sim.stop()
        server.stop()
    expected = sorted(loop.serial(i) for loop in loops for i in range(loop.units))
    serials = Counter(d["serial"] for d in docs)
    uids = Counter(d["uid"] for d in docs)
    lost = sorted(set(expected) - set(serials))
    twice = sorted(s for s, n in serials.items() if n > 1) + sorted(u for u, n in uids.items() if n > 1)
    units = sum(loop.units for loop in loops)
    per_unit = [w for loop in loops for w in loop.wall_s]
    print(f"four stations on one PostgreSQL, {units} units, simulators at {args.speed:g}x, {os.cpu_count()} cores")
    print(f"{'station':10} {'unit':13} {'records':>8} {'charts':>7} {'verdicts (exit status)':<40}")
    for (name, unit, n, charts, warned), loop in zip(per_station, loops, strict=True):
        verdicts = Counter(EXIT_VERDICT.get(e, f"exit {e}") for e in loop.exits)
        print(f"{name:10} {unit:13} {n:>8} {charts:>7} {', '.join(f'{v} {k}' for k, v in sorted(verdicts.items())):<40}"
              + ("  (history warned of a queue)" if warned else ""))
    print(f"records {len(docs)} of {units} units: lost {len(lost)}, twice {len(twice)}; "
          f"unique serials {len(serials)}, unique uids {len(uids)}")
    print(f"wall: {wall:.0f} s in total, per unit median {statistics.median(per_unit):.1f} s "
          f"(min {min(per_unit):.1f}, max {max(per_unit):.1f}); {units / wall * 60:.1f} units per minute, "
          "four stations together")
    errors = [e for loop in loops for e in loop.errors]
    for e in errors[:5]:
        print(f"run that ended without a verdict: {e}")
    ok = not lost and not twice and len(docs) == units and not errors
    print(f"acceptance (≥ 100 records, none lost, none twice): {'met' if ok and units >= 100 else 'NOT met'}")
    shutil.rmtree(root, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
