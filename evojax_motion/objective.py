"""The torque objective of the optimisation compiler (paper eq. 5) and the paper's Fig. 5 quantity.

``cost = 0.5 * int_0^D |tau(t)|^2 dt = 0.5 * D * sum_i w_i |tau(s_i)|^2`` with the trapezoid
weights of ``TimeGrid`` and ``tau = M(q) qdd + C(q, qd) qd + g(q)`` from ``Dynamics.inverse``.

``torque_sum`` is the quantity plotted per generation (the paper's "sum of required torque", in
N m): the time average of ``|tau_j|`` summed over the joints, ``sum_j (1/D) int |tau_j| dt``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from evojax_motion.dynamics import Dynamics
from evojax_motion.timegrid import TimeGrid, derivatives


def trajectory_torques(dyn: Dynamics, grid: TimeGrid, q: jnp.ndarray, duration) -> jnp.ndarray:
    """Joint torques along one primitive. ``q: (T, J)``, ``duration: ()`` -> ``tau: (T, J)``."""
    qd, qdd = derivatives(grid, q, duration)
    return jax.vmap(dyn.inverse)(q, qd, qdd)


def cost_from_torques(grid: TimeGrid, tau: jnp.ndarray, duration) -> jnp.ndarray:
    """``0.5 * int |tau|^2 dt`` from ``tau: (T, J)`` -> scalar [N^2 m^2 s]."""
    w = jnp.asarray(grid.w, tau.dtype)
    return 0.5 * duration * jnp.sum(w * jnp.sum(tau**2, axis=-1))


def torque_cost(dyn: Dynamics, grid: TimeGrid, q: jnp.ndarray, duration) -> jnp.ndarray:
    """Eq. 5 for one primitive. ``q: (T, J)``, ``duration: ()`` -> scalar."""
    return cost_from_torques(grid, trajectory_torques(dyn, grid, q, duration), duration)


def torque_sum(grid: TimeGrid, tau: jnp.ndarray) -> jnp.ndarray:
    """Time-averaged absolute torque summed over joints [N m]. ``tau: (T, J)`` -> scalar."""
    w = jnp.asarray(grid.w, tau.dtype)
    return jnp.sum(w[:, None] * jnp.abs(tau))
