"""`linalg.lapack`: one LAPACK call per matrix where jaxlib's batched calls can hang, with the
same results as ``jnp.linalg``'s batched calls."""

import re

import jax
import jax.numpy as jnp
import jaxlib.version
import numpy as np
import pytest

from evojax_motion.linalg import lapack


@pytest.fixture
def one_at_a_time(monkeypatch):
    """The path of the affected jaxlib releases, on any jaxlib (read at trace time)."""
    monkeypatch.setattr(lapack, "one_matrix_at_a_time", lambda: True)


def _matrices(*shape):
    return jax.random.normal(jax.random.PRNGKey(0), shape, jnp.float32)


def _lapack_batches(hlo: str) -> list[str]:
    """The operand shapes of the LAPACK custom calls in a lowered program's text."""
    calls = [line for line in hlo.splitlines() if "lapack_" in line and "custom_call" in line]
    return [m.group(1) for m in (re.search(r"\} : \((tensor<[^>]*>)", c) for c in calls) if m]


def _batched_svd(a):
    """The SVD of a ``(2, 3, 6, 4)`` stack as callers write it: vmap over vmap, one matrix each."""
    return jax.vmap(jax.vmap(lambda m: lapack.svd(m, full_matrices=False)))(a)


def _batched_eigh(a):
    sym = a @ jnp.swapaxes(a, -1, -2)
    return jax.vmap(lapack.eigh)(sym.reshape(-1, *sym.shape[-2:])), lapack.eigh(sym)


def test_one_matrix_at_a_time_equals_the_batched_call(one_at_a_time):
    """Each matrix goes through the same LAPACK routine: the results are bit-identical to
    ``jnp.linalg``'s batched call, under nested vmap and with leading batch axes."""
    a = _matrices(2, 3, 6, 4)
    u, s, vt = jax.jit(_batched_svd)(a)
    ref = jnp.linalg.svd(a, full_matrices=False)
    for got, want in zip((u, s, vt), ref, strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    (w1, v1), (w2, v2) = jax.jit(_batched_eigh)(a)
    sym = a @ jnp.swapaxes(a, -1, -2)
    w_ref, v_ref = jnp.linalg.eigh(sym)
    np.testing.assert_array_equal(np.asarray(w2), np.asarray(w_ref))
    np.testing.assert_array_equal(np.asarray(v2), np.asarray(v_ref))
    np.testing.assert_array_equal(np.asarray(w1).reshape(w_ref.shape), np.asarray(w_ref))
    np.testing.assert_array_equal(np.asarray(v1).reshape(v_ref.shape), np.asarray(v_ref))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="LAPACK custom calls are CPU's")
def test_one_matrix_at_a_time_leaves_no_batched_lapack_call(one_at_a_time):
    """The lowered program calls LAPACK on single matrices only (a batch is a loop around the
    call): the property that keeps those jaxlibs from waiting on their own thread pool. The
    batched path, for contrast, has a batched call (so the check can fail)."""
    a = _matrices(2, 3, 6, 4)
    shapes = _lapack_batches(jax.jit(_batched_svd).lower(a).as_text())
    shapes += _lapack_batches(jax.jit(_batched_eigh).lower(a).as_text())
    assert shapes, "no LAPACK custom call found in the lowered text: the scan is broken"
    assert all(s.count("x") == 2 for s in shapes), shapes  # tensor<6x4xf32>: one matrix
    batched = _lapack_batches(jax.jit(jnp.linalg.svd).lower(a).as_text())
    assert any(s.count("x") > 2 for s in batched), batched


def test_affected_releases_are_the_ones_with_split_batches(monkeypatch):
    """The switch follows the jaxlib release on CPU and nothing else."""
    monkeypatch.setattr(jaxlib.version, "__version_info__", (0, 10, 2))
    assert lapack.one_matrix_at_a_time() == (jax.default_backend() == "cpu")
    for other in ((0, 9, 2), (0, 11, 2)):
        monkeypatch.setattr(jaxlib.version, "__version_info__", other)
        assert not lapack.one_matrix_at_a_time()


@pytest.fixture
def chunks_of_four(monkeypatch):
    """The GPU's chunked path (`lapack.batch_limit`) with a limit of 4 matrices, on any backend."""
    monkeypatch.setattr(lapack, "one_matrix_at_a_time", lambda: False)
    monkeypatch.setattr(lapack, "batch_limit", lambda: 4)


def test_chunked_calls_equal_the_batched_call(chunks_of_four):
    """Batches past the limit, from leading axes and from nested vmap (2 x 3 = 6 matrices, and
    5): every batch axis is folded into one and solved in chunks, bit-identical to the batched
    call (the same routine per matrix), the padding dropped."""
    a = _matrices(2, 3, 6, 4)
    u, s, vt = jax.jit(lambda m: _batched_svd(m))(a)  # a new function: traced anew
    for got, want in zip((u, s, vt), jnp.linalg.svd(a, full_matrices=False), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    five = _matrices(5, 6, 4)
    (w1, v1), (w2, v2) = jax.jit(lambda m: _batched_eigh(m))(five)
    w_ref, v_ref = jnp.linalg.eigh(five @ jnp.swapaxes(five, -1, -2))
    for got in ((w1, v1), (w2, v2)):
        np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(w_ref))
        np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(v_ref))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="LAPACK custom calls are CPU's")
def test_chunked_calls_take_at_most_the_limit(chunks_of_four):
    """The 6 matrices go in two equal chunks of 3 (the limit is 4), while the
    plain batched call gets all 6: the check can fail."""
    a = _matrices(2, 3, 6, 4)
    chunked = _lapack_batches(jax.jit(lambda m: _batched_svd(m)).lower(a).as_text())
    plain = _lapack_batches(
        jax.jit(lambda m: jnp.linalg.svd(m, full_matrices=False)).lower(a).as_text()
    )
    assert chunked and all(t.startswith("tensor<3x6x4") for t in chunked), chunked  # 2 x 3
    assert any(t.startswith("tensor<2x3x6x4") or t.startswith("tensor<6x6x4") for t in plain), plain
