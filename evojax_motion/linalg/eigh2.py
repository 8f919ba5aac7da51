"""Closed-form eigendecomposition of symmetric 2 x 2 matrices, elementwise.

For the BFGS method's two-dimensional subspace step (`solvers.steps.subspace_step`): its 2 x 2
trust-region model is decomposed once per iteration for every problem of the batch, with no
solver call and no loop.
"""

from __future__ import annotations

import jax.numpy as jnp


def eigh_2x2(a: jnp.ndarray, b: jnp.ndarray, c: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Eigenvalues ``(..., 2)`` (ascending) and eigenvectors ``(..., 2, 2)`` (columns) of the
    symmetric ``[[a, b], [b, c]]``, each ``(...)``, in closed form (elementwise: no solver call,
    no loop). The smaller eigenvalue is ``det / larger`` where the larger is positive: unlike
    ``mean - radius`` it keeps its relative accuracy when the diagonal entries differ by orders
    of magnitude (as the curvatures of a BFGS model do)."""
    mean, half = 0.5 * (a + c), 0.5 * (a - c)
    rad = jnp.hypot(half, b)
    hi = mean + rad
    lo = jnp.where(hi > 0, (a * c - b * b) / jnp.where(hi > 0, hi, 1.0), mean - rad)
    phi = 0.5 * jnp.arctan2(b, half)  # (cos phi, sin phi) belongs to the larger eigenvalue
    cs, sn = jnp.cos(phi), jnp.sin(phi)
    v = jnp.stack([jnp.stack([-sn, cs], -1), jnp.stack([cs, sn], -1)], -1)
    return jnp.stack([lo, hi], -1), v
