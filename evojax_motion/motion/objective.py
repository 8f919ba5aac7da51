"""The torque objective of the optimisation compiler (paper eq. 5) and the paper's Fig. 5 quantity.

``cost = 0.5 * int_0^D |tau(t)|^2 dt = 0.5 * D * sum_i w_i |tau(s_i)|^2`` with the trapezoid
weights of ``TimeGrid`` and ``tau = M(q) qdd + C(q, qd) qd + g(q)`` from ``Dynamics.inverse``.

``torque_sum`` is the quantity plotted per generation (the paper's "sum of required torque", in
N m): the time average of ``|tau_j|`` summed over the joints, ``sum_j (1/D) int |tau_j| dt``.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import one_shot
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.motion.timegrid import TimeGrid, derivatives


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


def trajectory_measures(dyn: Dynamics, grid: TimeGrid, q: jnp.ndarray, duration) -> tuple:
    """One primitive's eq. 5 cost, Fig. 5 torque sum and peak ``|qd|``, ``|tau|`` over its
    samples, from one inverse dynamics pass: ``q: (T, J)``, ``duration: ()`` -> ``((), (), (J,),
    (J,))`` (`TrajectoryCosts`' fields)."""
    qd, qdd = derivatives(grid, q, duration)
    tau = jax.vmap(dyn.inverse)(q, qd, qdd)
    peaks = jnp.max(jnp.abs(qd), axis=0), jnp.max(jnp.abs(tau), axis=0)
    return cost_from_torques(grid, tau, duration), torque_sum(grid, tau), *peaks


class TrajectoryCosts(NamedTuple):
    """Per trajectory: eq. 5 ``cost`` (n,) [N^2 m^2 s], Fig. 5 ``torque_sum`` (n,) [N m], and the
    peaks over the T samples of ``|qd|`` (``peak_velocity`` (n, J) [rad/s]) and of ``|tau|``
    (``peak_torque`` (n, J) [N m]), from the same torques."""

    cost: np.ndarray
    torque_sum: np.ndarray
    peak_velocity: np.ndarray
    peak_torque: np.ndarray


class CostProgram:
    """``costs(q (n, T, J), duration (n,)) -> TrajectoryCosts`` for any n <= ``rows``: one
    compiled program of ``rows`` trajectories (padded with resting ones) that serves a run's
    synthesised demonstrations, its human costs and limit check (`motion.feasibility`) and its
    human-only baseline.
    ``cache``: `run.cache.traced_program`'s ``parts`` (e.g. `run.workflow.cache_parts` of a
    run), to keep the traced program across processes; None: in this process only.
    `precompile` compiles it for trajectories of ``samples`` x ``joints`` before the data exist.
    """

    def __init__(self, dyn, grid, rows: int, cache: Any = None):
        from evojax_motion.run.cache import traced_program

        def one(q, d):
            return trajectory_measures(dyn, grid, q, d)

        options = one_shot()  # run a few times a run

        @functools.partial(jax.jit, compiler_options=options)
        @exact_matmuls
        def trajectory_costs(q, d):
            return jax.vmap(one)(q, d)

        self.rows = rows
        self._batch = traced_program(trajectory_costs, cache, options)

    def precompile(self, samples: int, joints: int) -> None:
        f32 = np.dtype(np.float32)
        shapes = ((self.rows, samples, joints), (self.rows,))
        self._batch.precompile(*(jax.ShapeDtypeStruct(s, f32) for s in shapes))

    def __call__(self, q, duration):
        n = q.shape[0]
        if n > self.rows:
            raise ValueError(f"CostProgram of {self.rows} rows: got {n} trajectories")
        q_pad = np.zeros((self.rows, *q.shape[1:]), np.float32)
        q_pad[:n] = q
        d_pad = np.ones(self.rows, np.float32)
        d_pad[:n] = duration
        return TrajectoryCosts(*(np.asarray(a)[:n] for a in self._batch(q_pad, d_pad)))
