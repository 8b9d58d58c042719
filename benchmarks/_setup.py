"""What the identification benchmarks share: one BLAS thread, the repository on the
import path, and the fit they time (2-dof, θ4, θ6, θ16 from examples/start-2dof.json).

Import it before numpy: the BLAS thread count is read when numpy loads OpenBLAS.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# One BLAS thread: what `python -m identify` and Dask's workers use, so that the
# in-process figures measure the same code the same way.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

ESTIMATE = ["theta4", "theta6", "theta16"]
START = ROOT / "examples" / "start-2dof.json"


def fit_env() -> dict[str, str]:
    """The environment of an `identify fit` child process: this checkout importable."""
    return dict(os.environ, PYTHONPATH=str(ROOT))


def fit_command(folder: str | Path, output: str | Path) -> list[str]:
    """The `python -m identify fit` command line of the benchmarked fit of one dataset folder."""
    return [sys.executable, "-m", "identify", "fit", str(folder), "--params", str(START), "--estimate",
            ",".join(ESTIMATE), "--output", str(output), "--quiet"]
