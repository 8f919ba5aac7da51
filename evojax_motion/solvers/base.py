"""What the optimisation compiler's solvers share: the batch of problems they solve, their result,
and the two strategies a trust-region solver is assembled from.

Split as in optimistix: a *Hessian model* learns the curvature of the objective (`HessianModel`:
the exact Hessian, BFGS...; `solvers.quasi_newton`), a *descent* turns the model into a step for
a trust-region radius (`Descent`: the exact trust-region step, the two-dimensional subspace
step; `solvers.steps`), and the trust region (`solvers.trust_region`) decides which steps to take
and how the radius changes. Each strategy is a small frozen dataclass of static settings with
pure ``init`` / ``update`` (or ``query`` / ``step``) functions on NamedTuple state.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax.numpy as jnp


class SolverResult(NamedTuple):
    """A solver's result for B problems.

    z: (B, n) the last accepted point; f: (B,) its objective; iterations: (B,) int32 iterations
    used; converged: (B,) bool, the stopping test was met within the budget.
    """

    z: jnp.ndarray
    f: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray


class Batch(NamedTuple):
    """B problems ``fun(z (n,), i) -> scalar`` (problem ``i`` of the batch) and what is derived
    once from their free coordinates (`make_batch`).

    free: (B, n) bool, the coordinates that move (the others stay at their start); idx: (B,)
    int32 problem indices; pair: (B, n, n) bool, both coordinates free; eye: (n, n) identity.
    """

    fun: Callable
    free: jnp.ndarray
    idx: jnp.ndarray
    pair: jnp.ndarray
    eye: jnp.ndarray

    def on_free(self, h: jnp.ndarray, diagonal) -> jnp.ndarray:
        """``h (B, n, n)`` symmetrised on the free coordinates, plus ``diagonal`` (``(B, n)`` or a
        scalar) there; unit curvature (and, by the solvers, zero gradient) on the others keeps
        them still."""
        h = 0.5 * (h + jnp.swapaxes(h, 1, 2))
        return (
            jnp.where(self.pair, h, 0.0)
            + jnp.where(self.free, diagonal, 1.0)[:, :, None] * self.eye
        )


def make_batch(fun: Callable, free: jnp.ndarray, dtype) -> Batch:
    """`Batch` of ``fun`` with free coordinates ``free (B, n)``; ``dtype``: the iterates'."""
    b, n = free.shape
    return Batch(
        fun=fun,
        free=free,
        idx=jnp.arange(b),
        pair=free[:, :, None] & free[:, None, :],
        eye=jnp.eye(n, dtype=dtype),
    )


class ModelInputs(NamedTuple):
    """What a Hessian model learns from once per iteration, at the point the iteration ended on.

    z_old, z: (B, n) the previous and the current point (equal where the step was rejected);
    g_old, g: (B, n) their gradients; bm: (B, n, n) the model's Hessian at ``z_old``; accept:
    (B,) bool, the step was taken; first: () bool, ``z`` is the start (no model yet); it: ()
    int32, the iteration counter.
    """

    z_old: jnp.ndarray
    z: jnp.ndarray
    g_old: jnp.ndarray
    g: jnp.ndarray
    bm: jnp.ndarray
    accept: jnp.ndarray
    first: jnp.ndarray
    it: jnp.ndarray


class HessianModel(Protocol):
    """A model of the objective's Hessian: ``init(batch, z0) -> state`` once, then
    ``update(batch, state, inputs) -> (bm (B, n, n), state)`` at every point the solver reaches
    (`ModelInputs`). ``bm`` must be symmetric with unit diagonal on the masked coordinates."""

    def init(self, batch: Batch, z0: jnp.ndarray) -> Any: ...

    def update(self, batch: Batch, state: Any, inputs: ModelInputs) -> tuple[jnp.ndarray, Any]: ...


class Descent(Protocol):
    """A step of the quadratic model ``g.p + p.B.p / 2`` within a radius: ``init(z0) -> state``,
    ``query(bm, g) -> state`` once per point (what does not depend on the radius), then
    ``step(bm, g, radius, state) -> (p (B, n), predicted decrease (B,), Newton decrement (B,))``
    (the decrement ``g.B^-1.g / 2``, inf where the model is not positive definite)."""

    def init(self, z0: jnp.ndarray) -> Any: ...

    def query(self, bm: jnp.ndarray, g: jnp.ndarray) -> Any: ...

    def step(
        self, bm: jnp.ndarray, g: jnp.ndarray, radius: jnp.ndarray, state: Any
    ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]: ...
