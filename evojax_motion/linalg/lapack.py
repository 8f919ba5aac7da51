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
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jaxlib.version

# jaxlib releases whose CPU LAPACK kernels wait on pool threads for pieces of a batch
SPLIT_BATCH_JAXLIBS = frozenset({(0, 10, 0), (0, 10, 1), (0, 10, 2)})


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


@functools.cache
def _serial_svd(full_matrices: bool):
    return _serial(functools.partial(jnp.linalg.svd, full_matrices=full_matrices))


_serial_eigh = _serial(jnp.linalg.eigh)


def svd(a: jnp.ndarray, full_matrices: bool = True):
    """``jnp.linalg.svd(a (..., m, n), full_matrices) -> (u, s, vt)`` (module docstring)."""
    if one_matrix_at_a_time():
        return _serial_svd(full_matrices)(a)
    return jnp.linalg.svd(a, full_matrices=full_matrices)


def eigh(a: jnp.ndarray):
    """``jnp.linalg.eigh(a (..., n, n)) -> (w (..., n) ascending, v (..., n, n))`` (module
    docstring)."""
    if one_matrix_at_a_time():
        return _serial_eigh(a)
    return jnp.linalg.eigh(a)
