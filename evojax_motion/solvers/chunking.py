"""Batches of problems run in equal chunks, one after another (``lax.map``).

On accelerators a batch's time per problem rises once its working set leaves the cache, so the
optimisation compiler optimises at most ``OptimSettings.max_batch`` problems at once
(`settings.compiler.MAX_BATCH`, `docs/scaling.md`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from evojax_motion.solvers.base import SolverResult


def in_chunks(fn: Callable, args: tuple, max_batch: int | None):
    """``fn(*args)`` over a batch of B rows, in equal chunks of at most ``max_batch`` rows run one
    after another (``lax.map``), or at once where ``B <= max_batch`` (or it is None).

    ``args``: pytrees of ``(B, ...)`` arrays (None for an absent one); ``fn`` returns a pytree
    of ``(rows, ...)`` arrays whose rows depend on their own input rows only (up to rounding),
    so the chunks' results, concatenated, are the batch's. The last chunk is filled up with
    copies of the last row, whose results are dropped.
    """
    b = jax.tree_util.tree_leaves(args)[0].shape[0]
    if max_batch is None or b <= max_batch:
        return fn(*args)
    n_chunks = -(-b // max_batch)
    size = -(-b // n_chunks)
    pad = n_chunks * size - b

    def split(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a
        return a.reshape(n_chunks, size, *a.shape[1:])

    out = jax.lax.map(lambda chunk: fn(*chunk), jax.tree_util.tree_map(split, args))
    return jax.tree_util.tree_map(lambda a: a.reshape(n_chunks * size, *a.shape[2:])[:b], out)


def optimise_in_chunks(
    solve: Callable, problems, z0: jnp.ndarray, free: jnp.ndarray, max_batch: int | None,
    initial: jnp.ndarray | None = None,
) -> SolverResult:  # fmt: skip
    """``solve(problems, z0, free, initial) -> SolverResult`` over a batch of B problems in
    chunks (`in_chunks`): ``problems`` a pytree of ``(B, ...)`` arrays, ``z0, free: (B, n)``,
    ``initial``: ``(B, n, n)`` or None. A problem's result does not depend on the others in its
    batch (the solvers stop a converged problem where it is; only rounding may differ between
    batch sizes)."""
    return in_chunks(solve, (problems, z0, free, initial), max_batch)
