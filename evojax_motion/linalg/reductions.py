"""Batched row reductions and matrix-vector products written so that XLA fuses them.

The optimiser works on batches of small vectors ``(B, n)`` and matrices ``(B, n, n)``: a
reduction or GEMM of its own there is a GPU kernel launch (and on the CPU a loop) per use, which
costs far more than the arithmetic. These forms keep the work elementwise where they can
(`row_reduce`) or share one reduction among several sums (`sum_together`). Also the masked
means of the evolution and the online generation (`masked_mean`, `masked_row_mean`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

COLUMN_REDUCE_MAX_N = 2  # `row_reduce`: rows up to this length are summed column by column


def row_reduce(x: jnp.ndarray, op: Callable[..., jnp.ndarray] = jnp.add) -> jnp.ndarray:
    """``x (..., n)`` reduced over its last axis by ``op`` (`jnp.add` or `jnp.maximum`):
    ``(..., 1)``.

    Up to ``n = COLUMN_REDUCE_MAX_N`` as ``op`` over the columns, elementwise: XLA fuses that
    with what comes before and after, where a reduction starts a new GPU kernel (the 2 x 2
    subspace model's secular iterations: 434 kernels a generation at 1,000 conditions on an H100
    as reductions, 186 this way; CHANGELOG.md).
    """
    n = x.shape[-1]
    if n > COLUMN_REDUCE_MAX_N:
        whole: dict[Callable, Callable[..., jnp.ndarray]] = {jnp.add: jnp.sum, jnp.maximum: jnp.max}
        return whole[op](x, axis=-1, keepdims=True)
    return functools.reduce(op, [x[..., i : i + 1] for i in range(n)])


def dot_rows(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """``sum(a * b, -1)``: row-wise dot products of batched vectors ``(..., n)`` -> ``(...)``
    (elementwise, fusable)."""
    return row_reduce(a * b)[..., 0]


def matvec(m: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
    """``m (B, n, n) @ x (B, n)`` -> ``(B, n)`` as elementwise products and a sum (fused by XLA,
    no GEMM)."""
    return row_reduce(m * x[:, None, :])[..., 0]


def row_norms(v: jnp.ndarray) -> jnp.ndarray:
    """``|v_i|`` of ``v (B, n)`` -> ``(B,)``, at least the dtype's ``tiny`` (a divisor)."""
    return jnp.maximum(jnp.linalg.norm(v, axis=1), jnp.finfo(v.dtype).tiny)


def sum_together(terms: Sequence[jnp.ndarray], axis: int = 0) -> tuple[jnp.ndarray, ...]:
    """Sums over ``axis`` of ``terms``, arrays of one shape, as one variadic reduction: one loop
    on the CPU, the terms' shared producers computed once (XLA's CPU compiler emits one loop per
    output array otherwise and recomputes in each what they share; its GPU compiler splits the
    reduction into a few kernels). At least two terms: a single sum is XLA:CPU's YNNPACK
    reduction, whose input XLA materialises first."""
    assert len(terms) >= 2
    zeros = tuple(jnp.zeros((), t.dtype) for t in terms)
    return jax.lax.reduce(
        tuple(terms), zeros, lambda xs, ys: tuple(x + y for x, y in zip(xs, ys, strict=True)),
        (axis,),
    )  # fmt: skip


def masked_mean(x: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Mean of the entries of ``x`` where ``mask`` (same shape): a scalar, NaN where ``mask``
    holds none. Entries outside ``mask`` are never read (a rejected offspring's ``inf`` cost)."""
    n = jnp.sum(mask)
    return jnp.where(n > 0, jnp.sum(jnp.where(mask, x, 0.0)) / jnp.maximum(n, 1), jnp.nan)


def masked_row_mean(x: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Mean of ``x (C, k, ...)`` over the k rows where ``mask (C, k)``: ``(C, ...)`` (e.g. over
    each condition's neighbours); 0 for a finite ``x`` where ``mask`` holds none."""
    w = mask.astype(x.dtype).reshape(mask.shape + (1,) * (x.ndim - 2))
    return jnp.sum(w * x, axis=1) / jnp.maximum(jnp.sum(w, axis=1), 1.0)
