"""The estimator's covariance keeps every parameter's direction whatever the scales."""

from __future__ import annotations

import numpy as np

from identify.estimator import scaled_pinv


def test_parameters_many_decades_apart_keep_their_sigma():
    rng = np.random.default_rng(0)
    J = rng.standard_normal((200, 4)) * np.array([1e-4, 1e3, 1e8, 1e-9])   # as theta3 beside theta9
    A = J.T @ J
    exact = np.sqrt(np.diag(np.linalg.inv(A)))
    assert np.allclose(np.sqrt(np.diag(scaled_pinv(A))), exact, rtol=1e-6)
    # plain pinv loses the large-scale directions: the reason for scaled_pinv
    assert np.sqrt(np.diag(np.linalg.pinv(A)))[0] < 1e-6 * exact[0]


def test_a_direction_the_data_do_not_hold_stays_out():
    A = np.diag([4.0, 0.0, 1e-30])
    assert np.allclose(scaled_pinv(A), np.diag([0.25, 0.0, 1e30]))
