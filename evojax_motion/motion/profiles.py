"""Rest-to-rest progress profiles on normalised time ``w`` in [0, 1]: 0 -> 1, at rest at both
ends. The synthetic demonstrations' progress (`minimum_jerk`) and the online limits' paths
(`online.limits.minimum_jerk`, `online.limits.plateau_path`) share them."""

from __future__ import annotations

import jax.numpy as jnp


def minimum_jerk(w):
    """Flash & Hogan (1985) position profile ``10 w^3 - 15 w^4 + 6 w^5`` on [0, 1]: peak speed
    1.875, peak acceleration 5.77 (times the mean)."""
    return w**3 * (10.0 - 15.0 * w + 6.0 * w**2)


def quintic_hermite(w):
    """The four quintic polynomials on [0, 1] that each set one boundary value and leave the
    others zero, with zero acceleration at both ends: a tuple (value 1 at the start, ``1 -
    minimum_jerk``; value 1 at the end, `minimum_jerk`; slope 1 at the start; slope 1 at the
    end; slopes per unit of ``w``), each shaped as ``w`` (NumPy in, NumPy out)."""
    end = minimum_jerk(w)
    return (
        1.0 - end,
        end,
        w * (1.0 + w**2 * (-6.0 + w * (8.0 - 3.0 * w))),
        w**3 * (-4.0 + w * (7.0 - 3.0 * w)),
    )


def plateau(w, ramp: float):
    """A speed plateau: the speed rises as ``3x^2 - 2x^3`` (x = w / ramp: zero acceleration at
    the start, continuous acceleration) over the first ``ramp`` of the time, holds ``1 / (1 -
    ramp)`` of the mean speed, and falls symmetrically. Peak acceleration ``1.5 / (ramp (1 -
    ramp))`` times the mean. ``0 < ramp <= 0.5``."""
    v = 1.0 / (1.0 - ramp)

    def rise(u):  # progress while speeding up, for normalised time u in [0, ramp]
        x = u / ramp
        return v * ramp * (x**3 - 0.5 * x**4)

    head = rise(jnp.minimum(w, ramp)) + v * jnp.clip(w - ramp, 0.0, 1.0 - 2.0 * ramp)
    return jnp.where(w <= 1.0 - ramp, head, 1.0 - rise(jnp.clip(1.0 - w, 0.0, ramp)))


def rest_to_rest(profile, q0, qf):
    """Paths ``q0 (C, J) -> qf (C, J)`` along ``profile (T,)``: ``(C, T, J)``; monotone between
    q0 and qf where the profile is, so inside any box that holds both ends."""
    return q0[:, None, :] + (qf - q0)[:, None, :] * profile[None, :, None]
