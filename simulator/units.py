"""Simulated production units: the nominal damper with a seeded production scatter, or
with one of the faults a damper line sees.

Each fault changes the parameters the physics says it changes:

``gas-leak``      less gas: θ5 = n0·R/V0 falls, and the gas's heat capacity θ15 = m·c_v
                  with it (the same amount of gas holds both); the pre-charge drops;
``worn-seal``     the seal's friction amplitude θ8 + θ9·p grows (both parts alike);
``worn-orifice``  a wider orifice: less quadratic damping θ3.

A good unit's scatter is a truncated normal per parameter, small enough that every
characteristic of the default QC spec stays well inside its tolerance; a faulty unit
gets the same scatter plus a seeded severity that takes its characteristic clearly out.
"""

from __future__ import annotations

import numpy as np

from simulator.errors import UsageError

UNITS = ("good", "gas-leak", "worn-seal", "worn-orifice")

# Relative standard deviation of each parameter over a production batch; cut at CLIP sd.
SCATTER = {"theta3": 0.012, "theta5": 0.006, "theta6": 0.004, "theta8": 0.04, "theta9": 0.04}
CLIP = 2.5
# Fault severity: a factor drawn uniformly from this range.
SEVERITY = {"gas-leak": (0.75, 0.88), "worn-seal": (1.6, 2.2), "worn-orifice": (0.65, 0.82)}


def unit_parameters(kind: str, seed: int, base: dict[str, float]) -> dict[str, float]:
    """``base`` (SI, theta1…theta17) changed as production unit ``kind`` number ``seed``."""
    if kind not in UNITS:
        raise UsageError(f"--unit {kind!r}: expected one of {', '.join(UNITS)}")
    rng = np.random.default_rng([seed, UNITS.index(kind)])
    theta = dict(base)
    for name, sd in SCATTER.items():
        theta[name] *= 1.0 + sd * float(np.clip(rng.standard_normal(), -CLIP, CLIP))
    theta["theta15"] *= theta["theta5"] / base["theta5"]
    if kind == "good":
        return theta
    factor = float(rng.uniform(*SEVERITY[kind]))
    if kind == "gas-leak":
        theta["theta5"] *= factor
        theta["theta15"] *= factor
    elif kind == "worn-seal":
        theta["theta8"] *= factor
        theta["theta9"] *= factor
    else:
        theta["theta3"] *= factor
    return theta
