"""Normalised time: samples, derivative operators and quadrature (DESIGN.md, conventions).

A primitive is sampled at ``s_i = i / (T - 1)``, ``i = 0..T-1``, over normalised time
``s in [0, 1]`` and carries its duration ``D``. Derivatives are fixed linear operators on the
samples, ``qd = (d1 @ q) / D`` and ``qdd = (d2 @ q) / D**2``; integrals over time are
``int f dt = D * sum_i w_i f(s_i)`` with trapezoid weights ``w`` (they sum to 1).

The operators are 4th-order finite differences (Fornberg weights; centred inside, one-sided near the
ends). High order matters at the ends: a rest-to-rest motion (minimum jerk, ``q'(0) = q''(0) = 0``)
then has end velocities that vanish to O(h^4), so the velocity rows of the boundary-condition system
are recognisably degenerate (see ``compile_interp``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

STENCIL_POINTS = 5  # d1: 4th order everywhere; d2: 4th order inside, 3rd at the ends


class TimeGrid(NamedTuple):
    """Fixed operators for T samples. ``s (T,)``, ``d1 (T, T)``, ``d2 (T, T)``, ``w (T,)``."""

    s: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    w: np.ndarray


def fornberg_weights(x0: float, x: np.ndarray, order: int) -> np.ndarray:
    """Finite-difference weights of derivatives 0..order at ``x0`` from nodes ``x`` (Fornberg 1988).

    Returns ``(order + 1, len(x))``: row m approximates the m-th derivative.
    """
    n = len(x)
    c = np.zeros((order + 1, n))
    c1, c4 = 1.0, x[0] - x0
    c[0, 0] = 1.0
    for i in range(1, n):
        mn = min(i, order)
        c2, c5, c4 = 1.0, c4, x[i] - x0
        for j in range(i):
            c3 = x[i] - x[j]
            c2 *= c3
            if j == i - 1:
                for k in range(mn, 0, -1):
                    c[k, i] = c1 * (k * c[k - 1, i - 1] - c5 * c[k, i - 1]) / c2
                c[0, i] = -c1 * c5 * c[0, i - 1] / c2
            for k in range(mn, 0, -1):
                c[k, j] = (c4 * c[k, j] - k * c[k - 1, j]) / c3
            c[0, j] = c4 * c[0, j] / c3
        c1 = c2
    return c


def _derivative_matrix(s: np.ndarray, order: int, points: int) -> np.ndarray:
    """(T, T) operator of the ``order``-th derivative with ``points``-point stencils."""
    t = len(s)
    mat = np.zeros((t, t))
    half = points // 2
    for i in range(t):
        lo = min(max(i - half, 0), t - points)
        idx = np.arange(lo, lo + points)
        mat[i, idx] = fornberg_weights(s[i], s[idx], order)[order]
    return mat


def make_time_grid(num_samples: int, dtype=np.float32) -> TimeGrid:
    """Operators for ``num_samples`` (T >= ``STENCIL_POINTS + 1``) samples over s in [0, 1]."""
    if num_samples < STENCIL_POINTS + 1:
        raise ValueError(f"T must be >= {STENCIL_POINTS + 1}, got {num_samples}")
    s = np.linspace(0.0, 1.0, num_samples)
    d1 = _derivative_matrix(s, 1, STENCIL_POINTS)
    d2 = _derivative_matrix(s, 2, STENCIL_POINTS)
    w = np.full(num_samples, 1.0 / (num_samples - 1))
    w[[0, -1]] *= 0.5
    return TimeGrid(*(a.astype(dtype) for a in (s, d1, d2, w)))


def derivatives(grid: TimeGrid, q: jnp.ndarray, duration: jnp.ndarray):
    """Velocities and accelerations of ``q (..., T, J)`` with ``duration (...)`` [s].

    Returns ``qd, qdd`` with the shape of ``q``.
    """
    q = jnp.asarray(q)
    d = jnp.asarray(duration, q.dtype)[..., None, None]
    d1 = jnp.asarray(grid.d1, q.dtype)
    d2 = jnp.asarray(grid.d2, q.dtype)
    # HIGHEST: on GPUs float32 matmuls default to TF32 (10-bit mantissa), which ruins the
    # cancellations of finite differences (end velocities, accelerations).
    hi = jax.lax.Precision.HIGHEST
    qd = jnp.einsum("ts,...sj->...tj", d1, q, precision=hi) / d
    qdd = jnp.einsum("ts,...sj->...tj", d2, q, precision=hi) / d**2
    return qd, qdd
