"""The small-matrix kernels of `evojax_motion.linalg` against NumPy (float64 references): Jacobi
eigen- and singular value decompositions (both dispatch paths), the unrolled Cholesky, the
closed-form 2 x 2 eigensolver and the fusable reductions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from evojax_motion.linalg.cholesky import cholesky, cholesky_solve, spd_solve
from evojax_motion.linalg.eigh2 import eigh_2x2
from evojax_motion.linalg.jacobi import (
    gram_svd,
    jacobi_eigh,
    jacobi_svd,
    small_eigh,
    small_right_svd,
    small_svd,
)
from evojax_motion.linalg.reductions import dot_rows, matvec, row_norms, row_reduce, sum_together

TOL_EIG = 2e-6  # relative to the largest |eigenvalue|: float32 Jacobi vs numpy (float64)
TOL_ORTHO = 3e-6  # Jacobi eigenvectors' deviation from orthonormality (float32)
TOL_GRAM_SVD = 1e-4  # relative: Gram-based singular values (squared conditioning) vs numpy
# One-sided Jacobi: every singular value (the smallest of a 1e-4 graded spectrum too) relative to
# itself vs numpy; a Gram-based SVD misses those by O(1) (eps * cond^2).
TOL_JACOBI_SVD_REL = 1e-3
TOL_JACOBI_SVD = 2e-6  # relative to s[0]: singular values and the rebuilt matrix (float32)
# Left singular vectors' deviation from orthonormality on `PAPER_BC_ROWS` (float32): 1.0e-7 with
# the default sweeps; 2.1e-6 with one sweep fewer (they build the BC solve's binding rows).
TOL_U_ORTHO = 5e-7
# The BC rows (q, q at the end, end slopes) of one joint of a paper problem in q-orthonormal
# coordinates (`compiler.interpolation._joint_system`, leak rule; built on an H100): graded over
# four orders with slope rows near `BC_LEAK`; one-sided Jacobi needed 5 sweeps here.
PAPER_BC_ROWS = np.array(
    [
        [9.9150902e-01, 8.6972788e-05, 3.9750159e-07, -1.4079719e-04, -2.4273682e00],
        [1.0006860e00, -1.3771796e00, -1.4659084e00, 9.1515005e-01, 1.9347692e-01],
        [-3.0556896e-06, 8.4528880e-04, -8.8380672e-05, 6.2640343e-04, -8.7294471e-04],
        [-3.2271785e-06, 1.9684207e-04, 1.8224504e-04, 1.3259037e-03, -9.2237513e-04],
    ],
    np.float32,
)

TOL_F64 = 1e-10  # float64: closed forms and unrolled factorisations vs numpy (relative)
TOL_F32 = 2e-5  # float32: a well-conditioned solve vs numpy's float64 one (relative)


@pytest.mark.parametrize("n", [3, 4, 5, 10])
def test_jacobi_eigh_matches_numpy(n):
    rng = np.random.default_rng(n)
    x = rng.standard_normal((20, n, 30)) * np.logspace(0, -3, n)[:, None]  # spread spectrum
    a = np.einsum("bit,bjt->bij", x, x).astype(np.float32)
    w, v = jax.jit(jax.vmap(jacobi_eigh))(jnp.asarray(a))
    w, v = np.asarray(w, np.float64), np.asarray(v, np.float64)
    ref = np.linalg.eigvalsh(a.astype(np.float64))
    scale = np.abs(ref).max(axis=1, keepdims=True)
    np.testing.assert_allclose(np.sort(w, axis=1) / scale, ref / scale, atol=TOL_EIG)
    assert np.abs(np.einsum("bki,bkj->bij", v, v) - np.eye(n)).max() < TOL_ORTHO
    rebuilt = np.einsum("bik,bk,bjk->bij", v, w, v)
    assert (np.abs(rebuilt - a).max(axis=(1, 2)) / scale[:, 0]).max() < TOL_EIG * n


def test_gram_svd_matches_numpy():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((30, 4, 5)).astype(np.float32)
    u, s, vt = jax.jit(jax.vmap(gram_svd))(jnp.asarray(a))
    _, s_ref, vt_ref = np.linalg.svd(a.astype(np.float64), full_matrices=True)
    np.testing.assert_allclose(np.asarray(s), s_ref, rtol=TOL_GRAM_SVD)
    vt = np.asarray(vt, np.float64)
    for i in range(4):  # each right singular vector up to its sign; the 5th spans the null space
        np.testing.assert_allclose(np.abs(np.sum(vt[:, i] * vt_ref[:, i], axis=1)), 1.0, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(vt[:, 4] * vt_ref[:, 4], axis=1)), 1.0, atol=1e-4)
    rebuilt = np.einsum("bik,bk,bkj->bij", np.asarray(u), np.asarray(s), vt[:, :4])
    np.testing.assert_allclose(rebuilt, a, atol=1e-5)


@pytest.mark.parametrize("shape", [(4, 5), (100, 5), (30, 3), (6, 6), (3, 7), (50, 1)])
def test_jacobi_svd_matches_numpy(shape):
    """One-sided Jacobi vs numpy (float64) on random, rank-deficient and graded matrices."""
    m, n = shape
    k = min(m, n)
    rng = np.random.default_rng(m * n)
    a = rng.standard_normal((30, m, n))
    a[:10, :, -1] = a[:10, :, 0]  # a repeated column: rank-deficient
    # graded: singular values 1 .. 1e-4 (random orthogonal factors)
    uu = np.linalg.qr(rng.standard_normal((10, m, m)))[0][..., :k]
    vv = np.linalg.qr(rng.standard_normal((10, n, n)))[0][..., :k]
    a[10:20] = np.einsum("bik,k,bjk->bij", uu, np.logspace(0, -4, k), vv)
    a = a.astype(np.float32)
    u, s, vt = (np.asarray(x, np.float64) for x in jax.jit(jax.vmap(jacobi_svd))(jnp.asarray(a)))
    s_ref = np.linalg.svd(a.astype(np.float64), compute_uv=False)
    assert u.shape == (30, m, k) and s.shape == (30, k) and vt.shape == (30, n, n)
    np.testing.assert_allclose(s / s_ref[:, :1], s_ref / s_ref[:, :1], atol=TOL_JACOBI_SVD)
    graded = s_ref[10:20] > 0
    rel = np.abs(s[10:20] - s_ref[10:20])[graded] / s_ref[10:20][graded]
    assert rel.max() < TOL_JACOBI_SVD_REL
    assert np.abs(np.einsum("bki,bkj->bij", vt, vt) - np.eye(n)).max() < TOL_ORTHO * n
    rebuilt = np.einsum("bik,bk,bkj->bij", u, s, vt[:, :k])
    err = np.abs(rebuilt - a).max(axis=(1, 2)) / s_ref[:, 0]
    assert err.max() < TOL_JACOBI_SVD * n


@pytest.mark.parametrize("jacobi", [False, True], ids=["lapack", "gram"])
@pytest.mark.parametrize("shape", [(100, 5), (30, 3), (6, 6), (50, 1)])
def test_small_right_svd_matches_numpy(shape, jacobi):
    """`small_right_svd` on both paths (the two-pass Gram one of accelerators, and LAPACK) on
    random, rank-deficient and graded (1 .. 1e-4) matrices: every singular value relative to
    itself within `TOL_JACOBI_SVD_REL` (what the one-sided Jacobi SVD meets, which this path
    replaces in the BC solve), right singular vectors orthonormal, ``a V = U S`` with orthogonal
    ``U``, each vector of a distinct singular value numpy's up to its sign."""
    m, n = shape
    rng = np.random.default_rng(m + n)
    a = rng.standard_normal((30, m, n))
    if n > 1:
        a[:10, :, -1] = a[:10, :, 0]  # a repeated column: rank-deficient
    uu = np.linalg.qr(rng.standard_normal((10, m, m)))[0][..., :n]
    vv = np.linalg.qr(rng.standard_normal((10, n, n)))[0]
    a[10:20] = np.einsum("bik,k,bjk->bij", uu, np.logspace(0, -4, n), vv)  # graded
    a = a.astype(np.float32)
    svd = jax.vmap(lambda x: small_right_svd(x, two_pass_gram=True, jacobi=jacobi))
    s, vt = (np.asarray(x, np.float64) for x in jax.jit(svd)(a))
    _, s_ref, vt_ref = np.linalg.svd(a.astype(np.float64), full_matrices=False)
    assert s.shape == (30, n) and vt.shape == (30, n, n)
    np.testing.assert_allclose(s / s_ref[:, :1], s_ref / s_ref[:, :1], atol=TOL_JACOBI_SVD)
    rel = np.abs(s[10:20] - s_ref[10:20]) / s_ref[10:20]
    assert rel.max() < TOL_JACOBI_SVD_REL
    assert np.abs(np.einsum("bki,bkj->bij", vt, vt) - np.eye(n)).max() < TOL_ORTHO * n
    av = np.einsum("bij,bkj->bik", a.astype(np.float64), vt)  # columns s_i u_i
    np.testing.assert_allclose(np.linalg.norm(av, axis=1) / s_ref[:, :1], s / s_ref[:, :1],
                               atol=TOL_JACOBI_SVD)  # fmt: skip
    graded = np.abs(np.sum(vt[10:20] * vt_ref[10:20], axis=2))  # distinct values: vector by vector
    np.testing.assert_allclose(graded, 1.0, atol=TOL_JACOBI_SVD_REL)


def test_jacobi_svd_converges_on_a_paper_bc_matrix():
    u, s, vt = (np.asarray(x, np.float64) for x in jax.jit(jacobi_svd)(PAPER_BC_ROWS))
    a = PAPER_BC_ROWS.astype(np.float64)
    s_ref = np.linalg.svd(a, compute_uv=False)
    np.testing.assert_allclose(s / s_ref[0], s_ref / s_ref[0], atol=TOL_JACOBI_SVD)
    assert np.abs(u.T @ u - np.eye(4)).max() < TOL_U_ORTHO
    assert np.abs((u * s) @ vt[:4] - a).max() / s_ref[0] < TOL_JACOBI_SVD


@pytest.mark.parametrize("jacobi", [False, True], ids=["lapack", "jacobi"])
def test_small_svd_and_eigh_agree_with_numpy(jacobi):
    """The dispatchers give numpy's conventions on both paths: descending singular values,
    ``full_matrices`` shapes, ascending eigenvalues with matching eigenvectors."""
    rng = np.random.default_rng(7)
    a = rng.standard_normal((8, 4, 5)).astype(np.float32)
    for full in (True, False):
        u, s, vt = jax.vmap(lambda x, f=full: small_svd(x, f, jacobi=jacobi))(jnp.asarray(a))
        assert vt.shape == ((8, 5, 5) if full else (8, 4, 5))
        np.testing.assert_allclose(s, np.linalg.svd(a, compute_uv=False), rtol=1e-5)
        rebuilt = np.einsum("bik,bk,bkj->bij", u, s, np.asarray(vt)[:, :4])
        np.testing.assert_allclose(rebuilt, a, atol=1e-5)
    x = rng.standard_normal((3, 2, 7, 9)).astype(np.float32)
    sym = np.einsum("...it,...jt->...ij", x, x) - 2.0 * np.eye(7, dtype=np.float32)
    w, v = small_eigh(jnp.asarray(sym), jacobi=jacobi)
    np.testing.assert_allclose(w, np.linalg.eigvalsh(sym.astype(np.float64)), atol=2e-5 * 20)
    rebuilt = np.einsum("...ik,...k,...jk->...ij", v, w, v)
    np.testing.assert_allclose(rebuilt, sym, atol=1e-4)


def _spd_batch(rng, shape, n):
    """Random symmetric positive definite matrices ``shape + (n, n)`` (float64)."""
    a = rng.standard_normal((*shape, n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


def test_cholesky_matches_numpy(x64):
    """`cholesky` against ``numpy.linalg.cholesky`` on a (2, 3) batch of 6 x 6 SPD matrices (only
    the lower triangle is read: junk above it changes nothing); an indefinite one is flagged."""
    rng = np.random.default_rng(5)
    a = _spd_batch(rng, (2, 3), 6)
    ref = np.linalg.cholesky(a)
    junk = a + np.triu(rng.standard_normal((6, 6)), k=1)  # upper triangle not symmetric
    low, ok = (np.asarray(x) for x in jax.jit(cholesky)(jnp.asarray(junk)))
    assert ok.all()
    np.testing.assert_allclose(low, ref, rtol=TOL_F64, atol=TOL_F64 * np.abs(ref).max())
    bad = a[0, 0].copy()
    bad[2, 2] = -1.0
    assert not bool(cholesky(jnp.asarray(bad))[1])


def test_cholesky_solve_matches_numpy(x64):
    """`cholesky_solve` against ``np.linalg.solve`` on positive definite matrices, one of them
    ill-conditioned (1e8): errors within `TOL_F64` times the condition number; an indefinite
    matrix is flagged, not solved."""
    rng = np.random.default_rng(4)
    a, b = _spd_batch(rng, (5,), 7), rng.standard_normal((5, 7))
    a[3] = a[3] @ np.diag(np.logspace(0, 4, 7)) @ a[3].T / 7 + 1e-4 * np.eye(7)
    a[4] = np.diag([1.0, 2.0, -1.0, 3.0, 1.0, 1.0, 1.0])
    x, ok = (np.asarray(v) for v in jax.jit(cholesky_solve)(jnp.asarray(a), jnp.asarray(b)))
    np.testing.assert_array_equal(ok, [True, True, True, True, False])
    expect = np.linalg.solve(a[:4], b[:4, :, None])[..., 0]
    cond = np.linalg.cond(a[:4])
    assert cond.max() > 1e6  # the ill-conditioned case is one
    err = np.abs(x[:4] - expect).max(axis=1) / np.abs(expect).max(axis=1)
    assert (err <= TOL_F64 * cond).all(), err


def test_spd_solve_of_one_system_under_vmap():
    """`spd_solve` on one ``(n, n)`` system, vmapped as the online query does, in float32 on the
    online projection's systems (``I + rho G^T G``): numpy's float64 solution within `TOL_F32`."""
    rng = np.random.default_rng(6)
    g = rng.standard_normal((40, 30, 4))
    h = np.eye(4) + 3.0 * np.swapaxes(g, 1, 2) @ g
    b = rng.standard_normal((40, 4))
    x = jax.jit(jax.vmap(spd_solve))(jnp.asarray(h, jnp.float32), jnp.asarray(b, jnp.float32))
    ref = np.linalg.solve(h, b[..., None])[..., 0]
    np.testing.assert_allclose(np.asarray(x), ref, rtol=TOL_F32, atol=TOL_F32 * np.abs(ref).max())


def test_closed_form_2x2_eigh_matches_numpy(x64):
    """`eigh_2x2` against ``np.linalg.eigh``: random symmetric matrices, a multiple of the
    identity (any basis), diagonal ones in either order, and an ill-conditioned positive
    definite one, whose small eigenvalue must keep its relative accuracy (``mean - radius``
    errs by ~3e-5 there); eigenvectors orthonormal with ``A v = v e``."""
    rng = np.random.default_rng(3)
    a, b, c = rng.standard_normal((3, 50))
    a[:3], b[:3], c[:3] = [2.0, 1.0, 3.0], [0.0, 0.0, 0.0], [2.0, 3.0, 1.0]
    a[3], b[3], c[3] = 1e12, 1e5, 1.0  # eigenvalues ~1e12 and ~0.99
    m = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)
    e, v = (np.asarray(x) for x in eigh_2x2(*map(jnp.asarray, (a, b, c))))
    ref, ref_v = np.linalg.eigh(m)
    np.testing.assert_allclose(e[3], ref[3], rtol=1e-8)
    np.testing.assert_allclose(e, ref, atol=TOL_F64 * np.abs(ref).max())
    np.testing.assert_allclose(m @ v, v * e[:, None, :], atol=TOL_F64)
    np.testing.assert_allclose(np.swapaxes(v, 1, 2) @ v, np.broadcast_to(np.eye(2), m.shape),
                               atol=TOL_F64)  # fmt: skip
    distinct = np.abs(ref[:, 1] - ref[:, 0]) > 1e-3 * np.abs(ref).max(axis=1)
    overlap = np.abs(np.sum(v * ref_v, axis=1))  # (50, 2): each vector numpy's up to its sign
    np.testing.assert_allclose(overlap[distinct], 1.0, atol=TOL_F64 * 1e3)


@pytest.mark.parametrize("n", [1, 2, 5])
def test_row_reductions_match_numpy(n, x64):
    """`row_reduce` (column by column up to `COLUMN_REDUCE_MAX_N`, a reduction above),
    `dot_rows`, `matvec`, `row_norms` and `sum_together` against numpy."""
    rng = np.random.default_rng(n)
    m, x, y = (
        rng.standard_normal((4, n, n)),
        rng.standard_normal((4, n)),
        rng.standard_normal((4, n)),
    )
    np.testing.assert_allclose(row_reduce(jnp.asarray(x)), x.sum(-1, keepdims=True), rtol=TOL_F64)
    np.testing.assert_allclose(row_reduce(jnp.asarray(x), jnp.maximum), x.max(-1, keepdims=True))
    np.testing.assert_allclose(dot_rows(jnp.asarray(x), jnp.asarray(y)), (x * y).sum(-1),
                               rtol=TOL_F64, atol=TOL_F64)  # fmt: skip
    mx = np.einsum("bij,bj->bi", m, x)
    np.testing.assert_allclose(matvec(jnp.asarray(m), jnp.asarray(x)), mx, rtol=TOL_F64,
                               atol=TOL_F64)  # fmt: skip
    np.testing.assert_allclose(row_norms(jnp.asarray(x)), np.linalg.norm(x, axis=1), rtol=TOL_F64)
    assert float(row_norms(jnp.zeros((1, n)))[0]) > 0  # a divisor: never zero
    sums = sum_together([jnp.asarray(x), jnp.asarray(y), jnp.asarray(x * y)], axis=0)
    for got, want in zip(sums, (x.sum(0), y.sum(0), (x * y).sum(0)), strict=True):
        np.testing.assert_allclose(got, want, rtol=TOL_F64, atol=TOL_F64)
