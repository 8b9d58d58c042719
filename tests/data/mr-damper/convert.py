"""How the CSV files beside this script were made from the source repository's MAT files
(kept for provenance; the tests read the CSV files only).

    python tests/data/mr-damper/convert.py PATH/TO/mr-damper/data tests/data/mr-damper

Each record ensaioK.1.mat (K = 1..10) holds Tout (s), dist (mm) and forc (N) at 100 Hz
for 30 s.  The table stands still for about a second and then starts; the first
START_S seconds are dropped so that only the steady state remains.  The frequency is
the least-squares sine frequency of the displacement over what is kept (a sine plus a
linear drift).  Nothing else is changed: the samples are the measured ones."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.io import loadmat
from scipy.optimize import least_squares

START_S = 6.0


def frequency(t: np.ndarray, x: np.ndarray) -> float:
    spectrum = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(x.size)))
    f0 = np.fft.rfftfreq(x.size, t[1] - t[0])[np.argmax(spectrum)]

    def residual(p: np.ndarray) -> np.ndarray:
        f, a, b, c, s = p
        w = 2 * np.pi * f * t
        return a * np.sin(w) + b * np.cos(w) + c + s * t - x

    fits = [least_squares(residual, [f0 + df, np.ptp(x) / 2, 0.0, x.mean(), 0.0]) for df in (-0.01, 0.0, 0.01)]
    return float(min(fits, key=lambda r: r.cost).x[0])


def main(source: Path, target: Path) -> None:
    experiments = []
    for k in range(1, 11):
        mat = loadmat(source / f"ensaio{k}.1.mat")
        t, x, force = (mat[c].ravel() for c in ("Tout", "dist", "forc"))
        keep = t >= START_S
        t, x, force = t[keep] - t[keep][0], x[keep], force[keep]
        f = frequency(t, x)
        label = f"e{k:02d}"
        rows = zip(t, x, force, strict=True)
        lines = ["time_s,displacement_mm,force_N"] + [f"{a:.2f},{b:.6g},{c:.6g}" for a, b, c in rows]
        (target / f"{label}.csv").write_text("\n".join(lines) + "\n")
        experiments.append({"label": label, "kind": "periodic", "file": f"{label}.csv", "frequency_Hz": round(f, 6),
                            "sample_rate_Hz": 100.0, "source": f"data/ensaio{k}.1.mat",
                            "excitation": f"crank-driven sine, {np.ptp(x):.1f} mm peak to peak, 0 V"})
    manifest = {"format": "damper-dataset/1",
                "name": "Labcontrol (UTFPR) shaking table with MR damper: sinusoidal tests at 0 V",
                "unit": {"type": "small magnetorheological damper on a crank-driven shaking table"},
                "experiments": experiments}
    (target / "dataset.json").write_text(json.dumps(manifest, indent=2) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
