"""Continuous joints on one branch: same poses (whole turns), no jumps, means near rest."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evojax_motion.motion.angles import on_rest_branch, posture_on_rest_branch, wrap_difference

TURN_TOL = 1e-9  # float64 round-off of a subtraction of whole turns


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_on_rest_branch_keeps_poses_and_lands_near_rest(seed):
    rng = np.random.default_rng(seed)
    t, j = 20, 3
    smooth = np.cumsum(rng.normal(0.0, 0.3, (4, t, j)), axis=1)
    continuous = np.array([True, True, False])
    # the same poses stored up to 3 turns apart, on the continuous joints
    turns = rng.integers(-3, 4, (4, t, j)) * continuous
    q = smooth + 2 * np.pi * turns
    rest = rng.uniform(-np.pi, np.pi, j)
    out = on_rest_branch(q, rest, continuous)
    k = (out - q) / (2 * np.pi)
    assert np.allclose(k, np.round(k), atol=TURN_TOL)  # whole turns only
    np.testing.assert_array_equal(out[..., 2], q[..., 2])  # a limited joint is untouched
    assert np.all(np.abs(np.diff(out[..., :2], axis=1)) <= np.pi + TURN_TOL)
    mean = out[..., :2].mean(axis=1)
    assert np.all(mean >= rest[:2] - np.pi - TURN_TOL) and np.all(mean < rest[:2] + np.pi)
    # the branch is a property of the poses, not of how they were stored
    np.testing.assert_allclose(out, on_rest_branch(smooth, rest, continuous), atol=1e-9)


def test_wrap_difference_and_posture():
    cont = np.array([True, False])
    d = wrap_difference(np.array([3 * np.pi / 2, 3 * np.pi / 2]), cont)
    np.testing.assert_allclose(d, [-np.pi / 2, 3 * np.pi / 2])
    p = posture_on_rest_branch(np.array([7.0, 7.0]), np.zeros(2), cont)
    np.testing.assert_allclose(p, [7.0 - 2 * np.pi, 7.0])
