"""Cholesky factorisation and solve of small symmetric positive definite systems, unrolled.

``n`` is small (the optimiser's quasi-Newton models: 14; the online query's projections: 2-4), so
the factorisation is unrolled in Python into elementwise operations on ``n``-vectors: no solver
call per system (on GPUs a cuSOLVER launch per iteration; batched LU calls for 4 x 4 systems once
dominated the online query), and XLA fuses the whole solve. Any leading batch axes ``...``.

Used by the BFGS method's Newton step (`solvers.steps.SubspaceStep`) and the online query's
limit projection (`online`, `spd_solve`).
"""

from __future__ import annotations

import jax.numpy as jnp


def _columns(a: jnp.ndarray) -> tuple[list[jnp.ndarray], jnp.ndarray]:
    """The columns ``(..., n)`` of the Cholesky factor L of ``a (..., n, n)`` (zero above the
    diagonal), and ``ok (...)``: every pivot was positive."""
    n = a.shape[-1]
    rows = jnp.arange(n)
    cols: list[jnp.ndarray] = []
    ok = jnp.ones(a.shape[:-2], bool)
    for k in range(n):
        c = a[..., :, k]
        for i in range(k):
            c = c - cols[i] * cols[i][..., k : k + 1]
        d = c[..., k]
        ok = ok & (d > 0)
        root = jnp.sqrt(jnp.where(d > 0, d, 1.0))
        cols.append(jnp.where(rows >= k, c / root[..., None], 0.0))
    return cols, ok


def cholesky(a: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(L (..., n, n), ok (...))``: the lower triangular ``L`` with ``a = L L^T`` of symmetric
    positive definite ``a (..., n, n)`` (only its lower triangle is read), as
    ``numpy.linalg.cholesky``; ``ok`` False where a pivot was not positive (``a`` not numerically
    positive definite; ``L`` is then meaningless)."""
    cols, ok = _columns(a)
    return jnp.stack(cols, axis=-1), ok


def cholesky_solve(a: jnp.ndarray, b: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(x, ok)``: ``x = a^-1 b (..., n)`` for symmetric positive definite ``a (..., n, n)`` and
    ``b (..., n)``, by `cholesky` and two triangular solves; ``ok (...)`` False where ``a`` was
    not numerically positive definite or ``x`` is not finite (``x`` is then meaningless)."""
    n = a.shape[-1]
    cols, ok = _columns(a)
    y: list[jnp.ndarray] = []  # L y = b
    for k in range(n):
        t = b[..., k]
        for i in range(k):
            t = t - cols[i][..., k] * y[i]
        y.append(t / cols[k][..., k])
    x: list[jnp.ndarray] = [jnp.zeros(())] * n  # L^T x = y
    for k in reversed(range(n)):
        t = y[k]
        for i in range(k + 1, n):
            t = t - cols[k][..., i] * x[i]
        x[k] = t / cols[k][..., k]
    sol = jnp.stack(x, axis=-1)
    return sol, ok & jnp.all(jnp.isfinite(sol), axis=-1)


def spd_solve(h: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """``x (n,)`` with ``h x = b`` for a small ``h (n, n)`` known to be symmetric positive
    definite (`cholesky_solve` without its flag), ``b (n,)``."""
    return cholesky_solve(h, b)[0]
