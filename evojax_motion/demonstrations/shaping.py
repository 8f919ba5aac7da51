"""The shapes the synthetic demonstrations are built from (`demonstrations.synthetic`): catch
points spread over the catch region (`halton`, `region_points`), the shoulder-centred arc of a
hand path (`shoulder_arc`), and the C2 cubic spline through the IK's nodes (`spline_matrix`,
`spline_eval`); their minimum-jerk progress is `motion.profiles.minimum_jerk`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.demonstrations import CatchRegion

HALTON_BASES = (2, 3, 5)


def halton(index: np.ndarray, bases=HALTON_BASES) -> np.ndarray:
    """Halton points ``(n, len(bases))`` in [0, 1) for integer ``index (n,)`` (radical inverse)."""
    out = np.zeros((len(index), len(bases)))
    for d, base in enumerate(bases):
        i = np.asarray(index, np.int64).copy()
        f, r = 1.0, np.zeros(len(index))
        while np.any(i > 0):
            f /= base
            r += f * (i % base)
            i //= base
        out[:, d] = r
    return out


def region_points(region: CatchRegion, centre, u) -> np.ndarray:
    """Map ``u (n, 3)`` in [0, 1)^3 to points of the sector with uniform volume density."""
    r0, r1 = region.radius
    r = np.cbrt(r0**3 + u[:, 0] * (r1**3 - r0**3))
    az = np.deg2rad(region.azimuth_deg[0] + u[:, 1] * np.diff(region.azimuth_deg)[0])
    s0, s1 = np.sin(np.deg2rad(region.elevation_deg))
    el = np.arcsin(s0 + u[:, 2] * (s1 - s0))
    direction = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return np.asarray(centre)[None] + r[:, None] * direction


def spline_matrix(k: int, dtype) -> np.ndarray:
    """``(K, K)``: node values -> second derivatives of the clamped cubic spline on K even nodes
    of [0, 1], with end slopes from the 4th-order finite differences of `make_time_grid`."""
    h = 1.0 / (k - 1)
    d1 = make_time_grid(k, dtype=np.float64).d1
    a, rhs = np.zeros((k, k)), np.zeros((k, k))
    for i in range(1, k - 1):  # M[i-1] + 4 M[i] + M[i+1] = 6 (Q[i-1] - 2 Q[i] + Q[i+1]) / h^2
        a[i, i - 1 : i + 2] = (1.0, 4.0, 1.0)
        rhs[i, i - 1 : i + 2] = np.array([1.0, -2.0, 1.0]) * 6.0 / h**2
    a[0, :2], a[-1, -2:] = (2.0, 1.0), (1.0, 2.0)
    rhs[0, :2] = np.array([-1.0, 1.0]) * 6.0 / h**2  # 6/h ((Q1 - Q0)/h - Q'(0))
    rhs[0] -= 6.0 / h * d1[0]
    rhs[-1, -2:] = np.array([1.0, -1.0]) * 6.0 / h**2  # 6/h (Q'(1) - (Q[-1] - Q[-2])/h)
    rhs[-1] += 6.0 / h * d1[-1]
    return np.linalg.solve(a, rhs).astype(dtype)


def spline_eval(second, values, u, u_rest):
    """Cubic spline through ``values (K, J)`` at even nodes of [0, 1], at ``u (T,)`` -> (T, J).

    ``u_rest = 1 - u``, computed accurately by the caller: near u = 1 (the slow end of a motion)
    float32 ``u`` has lost the digits that tell neighbouring samples apart.
    """
    k = values.shape[0]
    m = jnp.asarray(second) @ values  # (K, J) second derivatives
    upper = u > 0.5
    x, y = u * (k - 1), u_rest * (k - 1)
    i = jnp.where(upper, k - 2 - jnp.floor(y), jnp.floor(x))
    i = jnp.clip(i, 0, k - 2).astype(jnp.int32)
    # local coordinate t in the interval and 1 - t, each from the end it is accurate at
    t = jnp.where(upper, 1.0 - (y - (k - 2 - i)), x - i)[:, None]
    omt = jnp.where(upper, y - (k - 2 - i), 1.0 - (x - i))[:, None]
    h2 = 1.0 / (k - 1) ** 2
    curve = h2 / 6.0 * ((omt**3 - omt) * m[i] + (t**3 - t) * m[i + 1])
    step = values[i + 1] - values[i]
    # offsets from the nearer node: a sample near a node is the node plus a small correction
    near = jnp.where(t < 0.5, values[i] + t * step, values[i + 1] - omt * step)
    return near + curve


def shoulder_arc(centre, p0, target, u):
    """Hand positions ``(P, T, 3)`` around ``centre`` (the shoulder): the direction turns along a
    great circle (slerp) and the distance changes linearly with progress ``u (P, T, 1)``."""
    a, b = p0 - centre, target - centre  # (3,), (P, 3)
    ra, rb = jnp.linalg.norm(a), jnp.linalg.norm(b, axis=-1, keepdims=True)
    da, db = a / ra, b / rb
    omega = jnp.arccos(jnp.clip(jnp.sum(da * db, -1, keepdims=True), -1.0, 1.0))
    omega = jnp.maximum(omega, 1e-6)[:, None]  # (P, 1, 1)
    direction = (jnp.sin((1.0 - u) * omega) * da + jnp.sin(u * omega) * db[:, None]) / jnp.sin(
        omega
    )
    return centre + (ra + u * (rb[:, None] - ra)) * direction
