"""The statistics of one generation of the evolution (`GenerationStats`), without JAX: the
training run names its metrics after them (`run.training.METRIC_FIELDS`) before JAX is loaded."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    import jax.numpy as jnp


class GenerationStats(NamedTuple):
    """Scalars of one generation (``metrics.jsonl``; their meaning:
    `evolution.step.make_generation_step`)."""

    offspring_cost_mean: jnp.ndarray
    db_cost_mean: jnp.ndarray
    torque_sum_mean: jnp.ndarray
    human_deviation_deg: jnp.ndarray
    n_replaced: jnp.ndarray
    n_rejected_nonfinite: jnp.ndarray
    n_rejected_limits: jnp.ndarray
    n_rejected_torque: jnp.ndarray
    n_rejected_velocity: jnp.ndarray
    n_rejected_bc: jnp.ndarray
    n_valid: jnp.ndarray
    n_short: jnp.ndarray
    bc_residual_max: jnp.ndarray
    bc_velocity_residual_max: jnp.ndarray
    converged_fraction: jnp.ndarray
