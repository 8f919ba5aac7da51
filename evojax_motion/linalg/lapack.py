"""LAPACK's SVD and symmetric eigensolver (``jnp.linalg.svd`` / ``eigh``), safe on every jaxlib.

jaxlib 0.10.0-0.10.2 split a batched LAPACK call on CPU into pieces for XLA's intra-op thread
pool and wait for them on the thread that made the call. When XLA runs as many such calls at
once as the pool has threads (two on a 2-core machine), each of them waits on a pool thread for
pieces that no free thread is left to run, and the program never returns: the optimisation
compiler on the paper's problems hung on its second or third call (both pool threads in
``jax::ParallelBatchMap`` under ``lapack_sgesdd_ffi``). A call of one matrix runs on the calling
thread. On those versions `svd` and `eigh` therefore solve a batch one matrix at a time
(``lax.map``, also under ``vmap``); elsewhere they are ``jnp.linalg``'s own. Each matrix goes
through the same LAPACK routine either way.

On GPUs the batched solvers (cuSOLVER's batched Jacobi ``syevjBatched`` and ``gesvdjBatched``)
refuse a batch past a size of their own: on an H200 (jax 0.11.2) ``eigh`` of 2^20 matrices of
5 x 5 or 8 x 8 ran and of 2^21 failed with "cuSolver invalid value error" in
``syevjBatched_bufferSize`` (400,000 conditions of the sharded step died there). There `svd` and
`eigh` gather every batch axis, ``vmap``'s included, into one and solve it in equal chunks of
at most `GPU_BATCH_LIMIT` matrices (``lax.map`` over the chunks), so that any batch that fits in
memory runs: there 2.1 and 4.2 million 5 x 5 matrices took 32 and 65 ms, and 700,000 in two
chunks 11.2 ms against 11.1 in one call.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jaxlib.version

# jaxlib releases whose CPU LAPACK kernels wait on pool threads for pieces of a batch
SPLIT_BATCH_JAXLIBS = frozenset({(0, 10, 0), (0, 10, 1), (0, 10, 2)})
GPU_BATCH_LIMIT = 1 << 19  # matrices per batched GPU solver call (2^20 ran, 2^21 failed)


def batch_limit() -> int | None:
    """The most matrices one batched solver call may take here (None: no limit): the GPU's
    `GPU_BATCH_LIMIT`. Read at trace time."""
    return GPU_BATCH_LIMIT if jax.default_backend() == "gpu" else None


def one_matrix_at_a_time() -> bool:
    """Whether batched LAPACK calls must run one matrix at a time here (see the module
    docstring): the CPU backend of a jaxlib in `SPLIT_BATCH_JAXLIBS`. Read at trace time."""
    release = tuple(jaxlib.version.__version_info__[:3])
    return jax.default_backend() == "cpu" and release in SPLIT_BATCH_JAXLIBS


def _serial(fn):
    """``fn`` of one matrix ``(m, n)``, mapped over any leading batch axes, and over ``vmap``'s
    batch axis, by ``lax.map``: one LAPACK call per matrix."""

    @jax.custom_batching.custom_vmap
    def one(a):
        return fn(a)

    @one.def_vmap
    def _batched(axis_size, in_batched, a):
        (batched,) = in_batched
        out = jax.lax.map(one, a) if batched else one(a)
        return out, jax.tree_util.tree_map(lambda _: batched, out)

    def call(a):
        if a.ndim == 2:
            return one(a)
        out = jax.lax.map(one, a.reshape(-1, *a.shape[-2:]))
        return jax.tree_util.tree_map(lambda x: x.reshape(a.shape[:-2] + x.shape[1:]), out)

    return call


def _chunked(fn):
    """``fn`` of a batch ``(b, m, n)``, over any leading batch axes and ``vmap``'s: every batch
    axis folded into one (a ``vmap`` of it folds its axis in and calls it again), then solved
    at most ``batch_limit()`` matrices at a time, in equal chunks. Like `_serial`, not
    differentiable (``custom_vmap``): the package differentiates through neither."""

    @jax.custom_batching.custom_vmap
    def flat(a):  # (b, m, n)
        limit = batch_limit()
        b = a.shape[0]
        if limit is None or b <= limit:
            return fn(a)
        chunks = -(-b // limit)
        size = -(-b // chunks)  # equal chunks: fewer than ``chunks`` padding matrices
        pad = jnp.concatenate([a, jnp.broadcast_to(a[:1], (chunks * size - b, *a.shape[1:]))])
        out = jax.lax.map(fn, pad.reshape(chunks, size, *a.shape[1:]))
        return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[2:])[:b], out)

    @flat.def_vmap
    def _folded(axis_size, in_batched, a):  # a: (axis_size, b, m, n)
        (batched,) = in_batched
        if not batched:
            out = flat(a)
        else:
            out = flat(a.reshape(-1, *a.shape[2:]))
            out = jax.tree_util.tree_map(lambda x: x.reshape(axis_size, -1, *x.shape[1:]), out)
        return out, jax.tree_util.tree_map(lambda _: batched, out)

    def call(a):
        out = flat(a.reshape(-1, *a.shape[-2:]))
        return jax.tree_util.tree_map(lambda x: x.reshape(a.shape[:-2] + x.shape[1:]), out)

    return call


def _one_matrix(op: str, full_matrices: bool):
    """``jnp.linalg``'s solver ``op`` ("svd" or "eigh")."""
    if op == "eigh":
        return jnp.linalg.eigh
    return functools.partial(jnp.linalg.svd, full_matrices=full_matrices)


@functools.cache
def _wrapped(wrap, op: str, full_matrices: bool = True):
    """``wrap`` (`_serial` or `_chunked`) of a solver, made once (``custom_vmap`` functions
    keep their identity across traces)."""
    return wrap(_one_matrix(op, full_matrices))


def _solve(op: str, a, full_matrices: bool = True):
    """``op`` of ``a (..., m, n)`` on the path this jaxlib and backend need (module docstring)."""
    if one_matrix_at_a_time():
        return _wrapped(_serial, op, full_matrices)(a)
    if batch_limit() is not None:
        return _wrapped(_chunked, op, full_matrices)(a)
    return _one_matrix(op, full_matrices)(a)


def svd(a: jnp.ndarray, full_matrices: bool = True):
    """``jnp.linalg.svd(a (..., m, n), full_matrices) -> (u, s, vt)`` (module docstring)."""
    return _solve("svd", a, full_matrices)


def eigh(a: jnp.ndarray):
    """``jnp.linalg.eigh(a (..., n, n)) -> (w (..., n) ascending, v (..., n, n))`` (module
    docstring)."""
    return _solve("eigh", a)
