"""User models with hysteresis and broadband excitation: the Bouc-Wen oscillator of
identify/models/bouc_wen.py on data made by tests/hysteresis_data.py."""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from tests import hysteresis_data as bw


def test_reference_data_agree_with_an_adaptive_integrator():
    """The fixed-step generator against DOP853 at tight tolerances, the force summed line
    by line (not from the generator's table): the first 0.4 s from rest."""
    spectrum = bw.multisine(1)
    count = 300
    y = bw.integrate(bw.TRUTH, spectrum, count)
    period = bw.SAMPLES / bw.RATE_HZ
    lines = np.flatnonzero(spectrum)
    amp, omega = 2 * np.abs(spectrum[lines]), 2 * np.pi * lines / period
    phase = np.angle(spectrum[lines])
    m, c, k, alpha, bg, bd = bw.TRUTH.values()

    def rhs(t, s):
        y, v, z = s
        u = float(amp @ np.cos(omega * t + phase))
        return [v, (u - c * v - k * y - z) / m, alpha * v - bg * abs(v) * z - bd * v * abs(z)]

    t = np.arange(count) / bw.RATE_HZ
    ref = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0, 0.0], method="DOP853", t_eval=t, rtol=1e-11,
                    atol=[1e-14, 1e-12, 1e-9]).y[0]
    assert np.max(np.abs(y - ref)) < 3e-6 * np.max(np.abs(ref))  # 3e-7 found; 4 substeps give 4e-5
