"""Derivative operators and quadrature against analytic references."""

import numpy as np
import pytest

from evojax_motion.motion.timegrid import derivatives, fornberg_weights, make_time_grid

TOL_D1_MINJERK = 1e-5  # rel. error of d1 on a quintic (4th-order FD, T=100)
TOL_D2_MINJERK = 1e-3  # rel. error of d2 (3rd order at the ends)
TOL_QUAD = 1e-4


def minimum_jerk(s):
    return 10 * s**3 - 15 * s**4 + 6 * s**5, 30 * s**2 - 60 * s**3 + 30 * s**4


def test_fornberg_matches_textbook_central_stencil():
    w = fornberg_weights(0.0, np.array([-2.0, -1.0, 0.0, 1.0, 2.0]), 2)
    np.testing.assert_allclose(w[1], [1 / 12, -2 / 3, 0, 2 / 3, -1 / 12], atol=1e-14)
    np.testing.assert_allclose(w[2], [-1 / 12, 4 / 3, -5 / 2, 4 / 3, -1 / 12], atol=1e-14)


def test_derivatives_of_minimum_jerk_profile():
    grid = make_time_grid(100, np.float64)
    s = grid.s
    f, df = minimum_jerk(s)
    ddf = 60 * s - 180 * s**2 + 120 * s**3
    assert np.abs(grid.d1 @ f - df).max() <= TOL_D1_MINJERK * np.abs(df).max()
    assert np.abs(grid.d2 @ f - ddf).max() <= TOL_D2_MINJERK * np.abs(ddf).max()
    # Rest-to-rest: the end velocities vanish to O(h^4), far below the interior values.
    assert np.abs((grid.d1 @ f)[[0, -1]]).max() < 1e-5


def test_operators_are_exact_on_quartics():
    grid = make_time_grid(12, np.float64)
    s = grid.s
    np.testing.assert_allclose(grid.d1 @ s**4, 4 * s**3, atol=1e-10)
    np.testing.assert_allclose(grid.d2 @ s**3, 6 * s, atol=1e-9)


def test_trapezoid_weights_integrate():
    grid = make_time_grid(200, np.float64)
    assert grid.w.sum() == pytest.approx(1.0, abs=1e-14)
    assert grid.w @ np.sin(np.pi * grid.s) == pytest.approx(2 / np.pi, abs=TOL_QUAD)


def test_derivatives_scale_with_duration(x64):
    grid = make_time_grid(50, np.float64)
    f, _ = minimum_jerk(grid.s)
    q = np.stack([f, 2 * f], axis=-1)[None]  # (1, T, 2)
    qd, qdd = derivatives(grid, q, np.array([0.5]))
    np.testing.assert_allclose(qd[0, :, 1], 2 * (grid.d1 @ f) / 0.5, rtol=1e-10)
    np.testing.assert_allclose(qdd[0, :, 0], (grid.d2 @ f) / 0.25, rtol=1e-10, atol=1e-9)


def test_too_few_samples_rejected():
    with pytest.raises(ValueError, match="T must be"):
        make_time_grid(4)
