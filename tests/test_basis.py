"""Neighbour selection (eq. 6) and the masked per-joint PCA basis against numpy references."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import subspace_angles
from scipy.spatial.transform import Rotation

import evojax_motion.basis as basis_module
from evojax_motion.basis import (
    BasisSettings,
    gram_svd,
    jacobi_eigh,
    jacobi_svd,
    neighbour_candidates,
    pca_basis,
    rotation_distance,
    select_neighbours,
    select_neighbours_among,
    small_eigh,
    small_right_svd,
    small_svd,
    validate_neighbour_database,
    validate_targets,
)
from evojax_motion.errors import UserError

TOL_ANGLE = 1e-3  # rad: largest principal angle between our and numpy's component subspaces
TOL_PCA = 1e-5  # rad: masked mean vs numpy (float32 sums of ~10 values of ~1 rad)
TOL_VAR_REL = 1e-4  # relative: component variances vs numpy's singular values
TOL_DIST = 1e-6  # m: distances vs numpy
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
# coordinates (`compile_interp._joint_system`, leak rule; built on an H100): graded over
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

N, T, J, K, C = 40, 20, 3, 4, 6


def smooth_trajectories(rng, n, t, j):
    """Random smooth trajectories ``(n, t, j)`` with a few independent modes per joint."""
    s = np.linspace(0.0, 1.0, t)
    modes = np.stack([np.ones_like(s), s, np.sin(np.pi * s), np.sin(2 * np.pi * s), s**3])
    weights = rng.standard_normal((n, j, len(modes))) * np.array([0.3, 1.0, 0.5, 0.2, 0.1])
    return np.einsum("njm,mt->ntj", weights, modes).astype(np.float32)


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    q = smooth_trajectories(rng, N, T, J)
    cond = rng.uniform(-0.3, 0.3, (N, 3)).astype(np.float32)
    valid = rng.random(N) < 0.7
    valid[:5] = True
    dur = rng.uniform(0.5, 1.5, N).astype(np.float32)
    targets = (cond[:C] + rng.normal(0, 0.02, (C, 3))).astype(np.float32)
    return q, cond, valid, dur, targets


def test_settings_validation():
    assert BasisSettings().radius == 0.15
    for field, value in [("radius", 0.0), ("neighbours", 1), ("w_pos", -1.0), ("w_rot", -0.5)]:
        with pytest.raises(ValueError, match=f"^{field}: expected"):
            BasisSettings(**{field: value})


def test_neighbours_match_numpy_and_skip_invalid(data):
    _, cond, valid, _, targets = data
    k, radius = 10, 0.15
    nb = jax.jit(select_neighbours, static_argnums=(3,))(
        jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(targets), k, radius
    )
    d = np.linalg.norm(targets[:, None] - cond[None], axis=-1)
    d[:, ~valid] = np.inf
    expect = np.argsort(d, axis=1, kind="stable")[:, :k]
    np.testing.assert_allclose(
        np.asarray(nb.distance), np.take_along_axis(d, expect, 1), atol=TOL_DIST
    )
    assert np.asarray(nb.mask).all()  # enough valid entries: every slot used
    assert valid[np.asarray(nb.index)].all()  # never an invalid entry
    inside = (d <= radius).sum(axis=1)
    np.testing.assert_array_equal(np.asarray(nb.n_inside), inside)
    np.testing.assert_array_equal(np.asarray(nb.short), inside < k)


def test_neighbours_with_few_valid_entries_are_masked(data):
    _, cond, _, _, targets = data
    few = np.zeros(N, bool)
    few[[3, 7, 11]] = True
    nb = select_neighbours(jnp.asarray(cond), jnp.asarray(few), jnp.asarray(targets), 5, 0.15)
    mask = np.asarray(nb.mask)
    assert (mask.sum(axis=1) == 3).all()
    assert set(np.asarray(nb.index)[mask].tolist()) <= {3, 7, 11}
    assert np.asarray(nb.short).all()
    # A database smaller than k pads with masked slots; a NaN target selects nothing.
    nb = select_neighbours(
        jnp.asarray(cond[:4]), jnp.ones(4, bool), jnp.asarray(targets).at[0, 1].set(jnp.nan), 6, 0.1
    )
    assert nb.index.shape == (C, 6)
    assert not np.asarray(nb.mask)[0].any()
    assert (np.asarray(nb.mask)[1:].sum(axis=1) == 4).all()
    # ... under jit too, among enough targets for XLA to vectorise the distances
    many = np.concatenate([targets] * 50)
    many[-1] = np.nan
    jitted = jax.jit(select_neighbours, static_argnums=(3,))
    nb = jitted(jnp.asarray(cond), jnp.ones(N, bool), jnp.asarray(many), 5, 0.1)
    assert not np.asarray(nb.mask)[-1].any() and int(nb.n_inside[-1]) == 0
    # A NaN condition in the database is never selected.
    bad = cond.copy()
    bad[0] = np.nan
    nb = select_neighbours(jnp.asarray(bad), jnp.ones(N, bool), jnp.asarray(cond[:1]), 5, 0.1)
    assert 0 not in np.asarray(nb.index)[np.asarray(nb.mask)]


def test_blocked_neighbour_search_equals_one_block(data, monkeypatch):
    """Many targets are searched in blocks of `NEIGHBOUR_BLOCK_ENTRIES` // N (memory); the
    result is the same, a last partial block included."""
    _, cond, valid, _, targets = data
    many = np.concatenate([targets] * 3)
    many[5, 0] = np.nan
    whole = select_neighbours(jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(many), 5, 0.15)
    # blocks of 4 targets: len(many) is not a multiple of 4
    monkeypatch.setattr(basis_module, "NEIGHBOUR_BLOCK_ENTRIES", 4 * len(cond) + 1)
    blocks = select_neighbours(jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(many), 5, 0.15)
    for name in ("index", "mask", "n_inside", "short"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(blocks, name))
    np.testing.assert_allclose(whole.distance, blocks.distance, rtol=1e-6)  # vectorised sums


def _run_like_database(rng, n_fixed, m, filled):
    """Conditions of a run's database: ``n_fixed`` human rows (valid), then one slot per target
    condition (a fraction ``filled`` valid); the targets are the slots' conditions and a NaN."""
    cond = rng.uniform(-0.3, 0.3, (n_fixed + m, 3)).astype(np.float32)
    valid = np.concatenate([np.ones(n_fixed, bool), rng.random(m) < filled])
    targets = np.concatenate([cond[n_fixed:], np.full((1, 3), np.nan, np.float32)])
    return jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(targets)


@pytest.mark.parametrize("filled", [0.7, 0.05])
def test_neighbours_among_candidates_equal_the_whole_search_where_exact(filled):
    """Candidate lists (the k nearest human rows and 4 k nearest slots, made once) give the
    whole database's neighbours wherever they report ``exact``: nearly everywhere with most
    slots filled (a run's later generations), not everywhere with few (its first)."""
    from evojax_motion.evolution import search_neighbours

    k, n_fixed, m, radius = 5, 30, 300, 0.1
    cond, valid, targets = _run_like_database(np.random.default_rng(1), n_fixed, m, filled)
    cand = jax.jit(neighbour_candidates, static_argnums=(2, 4, 5))(
        cond, valid, n_fixed, targets, k, 4 * k
    )
    whole = select_neighbours(cond, valid, targets, k, radius)
    among, exact = select_neighbours_among(cond, valid, targets, cand, k, radius)
    exact = np.asarray(exact)
    assert exact[-1]  # the NaN target: no neighbour either way
    if filled > 0.5:
        assert exact.mean() > 0.95, exact.mean()
    else:
        assert 0.05 < exact.mean() < 0.95, exact.mean()  # both branches are checked below
    mask = np.asarray(whole.mask)
    np.testing.assert_array_equal(np.asarray(among.mask)[exact], mask[exact])
    np.testing.assert_array_equal(
        np.where(mask, np.asarray(among.index), -1)[exact], np.where(mask, whole.index, -1)[exact]
    )
    np.testing.assert_array_equal(
        np.asarray(among.distance)[exact], np.asarray(whole.distance)[exact]
    )
    np.testing.assert_array_equal(np.asarray(among.short)[exact], np.asarray(whole.short)[exact])
    assert (np.asarray(among.n_inside) <= np.asarray(whole.n_inside)).all()
    # what the generation step uses: the lists where every one is exact, else the whole search
    db = SimpleNamespace(condition=cond, valid=valid)
    conditions = SimpleNamespace(target=targets, candidates=cand)
    used = search_neighbours(db, conditions, BasisSettings(radius=radius, neighbours=k))
    for name in ("index", "mask", "distance"):
        got, want = np.asarray(getattr(used, name)), np.asarray(getattr(whole, name))
        np.testing.assert_array_equal(np.where(mask, got, 0), np.where(mask, want, 0), name)
    np.testing.assert_array_equal(np.asarray(used.short), np.asarray(whole.short))


def test_orientation_term():
    rots = Rotation.from_euler("z", [[0.0], [0.3], [1.0], [0.0]]).as_matrix().astype(np.float32)
    angle = 0.3
    np.testing.assert_allclose(
        float(rotation_distance(jnp.asarray(rots[0]), jnp.asarray(rots[1]))),
        2 * np.sqrt(2) * abs(np.sin(angle / 2)),
        rtol=1e-5,
    )
    assert float(rotation_distance(jnp.asarray(rots[0]), jnp.asarray(rots[3]))) < 1e-6
    # Equal positions: only the orientation term orders them.
    cond = np.zeros((4, 3), np.float32)
    cond[:, 0] = [0.0, 0.001, 0.002, 0.003]
    target = np.zeros((1, 3), np.float32)
    nb = select_neighbours(
        jnp.asarray(cond), jnp.ones(4, bool), jnp.asarray(target), 4, 0.15,
        rotation=jnp.asarray(rots), target_rotation=jnp.asarray(rots[3:4]), w_rot=1.0,
    )  # fmt: skip
    assert np.asarray(nb.index)[0].tolist() == [0, 3, 1, 2]
    nb = select_neighbours(jnp.asarray(cond), jnp.ones(4, bool), jnp.asarray(target), 4, 0.15)
    assert np.asarray(nb.index)[0].tolist() == [0, 1, 2, 3]  # default: position only


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
def test_small_right_svd_matches_numpy(shape, jacobi, monkeypatch):
    """`small_right_svd` on both paths (the two-pass Gram one of accelerators, and LAPACK) on
    random, rank-deficient and graded (1 .. 1e-4) matrices: every singular value relative to
    itself within `TOL_JACOBI_SVD_REL` (what the one-sided Jacobi SVD meets, which this path
    replaces in the BC solve), right singular vectors orthonormal, ``a V = U S`` with orthogonal
    ``U``, each vector of a distinct singular value numpy's up to its sign."""
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: jacobi)
    m, n = shape
    rng = np.random.default_rng(m + n)
    a = rng.standard_normal((30, m, n))
    if n > 1:
        a[:10, :, -1] = a[:10, :, 0]  # a repeated column: rank-deficient
    uu = np.linalg.qr(rng.standard_normal((10, m, m)))[0][..., :n]
    vv = np.linalg.qr(rng.standard_normal((10, n, n)))[0]
    a[10:20] = np.einsum("bik,k,bjk->bij", uu, np.logspace(0, -4, n), vv)  # graded
    a = a.astype(np.float32)
    svd = jax.vmap(lambda x: small_right_svd(x, two_pass_gram=True))
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
def test_small_svd_and_eigh_agree_with_numpy(jacobi, monkeypatch):
    """The dispatchers give numpy's conventions on both paths: descending singular values,
    ``full_matrices`` shapes, ascending eigenvalues with matching eigenvectors."""
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: jacobi)
    rng = np.random.default_rng(7)
    a = rng.standard_normal((8, 4, 5)).astype(np.float32)
    for full in (True, False):
        u, s, vt = jax.vmap(lambda x, f=full: small_svd(x, f))(jnp.asarray(a))
        assert vt.shape == ((8, 5, 5) if full else (8, 4, 5))
        np.testing.assert_allclose(s, np.linalg.svd(a, compute_uv=False), rtol=1e-5)
        rebuilt = np.einsum("bik,bk,bkj->bij", u, s, np.asarray(vt)[:, :4])
        np.testing.assert_allclose(rebuilt, a, atol=1e-5)
    x = rng.standard_normal((3, 2, 7, 9)).astype(np.float32)
    sym = np.einsum("...it,...jt->...ij", x, x) - 2.0 * np.eye(7, dtype=np.float32)
    w, v = small_eigh(jnp.asarray(sym))
    np.testing.assert_allclose(w, np.linalg.eigvalsh(sym.astype(np.float64)), atol=2e-5 * 20)
    rebuilt = np.einsum("...ik,...k,...jk->...ij", v, w, v)
    np.testing.assert_allclose(rebuilt, sym, atol=1e-4)


@pytest.mark.parametrize("jacobi", [False, True], ids=["lapack", "jacobi"])
def test_pca_matches_numpy_svd(data, jacobi, monkeypatch):
    """Both PCA paths: LAPACK's SVD (CPU) and the Gram + Jacobi one (accelerators)."""
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: jacobi)
    q, cond, valid, dur, targets = data
    k = 10
    nb = select_neighbours(jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(targets), k, 0.15)
    mask = np.asarray(nb.mask).copy()
    mask[0, 7:] = False  # some masked slots inside the top-k
    nb = nb._replace(mask=jnp.asarray(mask))
    basis = jax.jit(lambda q, d, nb: pca_basis(q, d, nb, K))(jnp.asarray(q), jnp.asarray(dur), nb)
    idx = np.asarray(nb.index)
    for c in range(C):
        rows = idx[c][mask[c]]
        np.testing.assert_allclose(float(basis.duration[c]), dur[rows].mean(), rtol=1e-6)
        assert int(basis.n_neighbours[c]) == len(rows)
        for j in range(J):
            x = q[rows, :, j].astype(np.float64)
            mean = x.mean(axis=0)
            np.testing.assert_allclose(np.asarray(basis.mean[c, :, j]), mean, atol=TOL_PCA)
            _, sv, vt = np.linalg.svd(x - mean, full_matrices=False)
            comps = np.asarray(basis.components[c, :, :, j], np.float64)  # (K, T)
            np.testing.assert_allclose(np.linalg.norm(comps, axis=1), 1.0, atol=1e-5)
            assert subspace_angles(comps.T, vt[:K].T).max() < TOL_ANGLE
            # Each component individually (distinct singular values here), up to the sign rule.
            for i in range(K):
                assert abs(abs(comps[i] @ vt[i]) - 1.0) < 1e-5
                assert comps[i][np.argmax(np.abs(comps[i]))] > 0
            np.testing.assert_allclose(
                np.asarray(basis.variance[c, :, j]), sv[:K] ** 2 / (len(rows) - 1), rtol=TOL_VAR_REL
            )


@pytest.mark.parametrize("jacobi", [False, True], ids=["lapack", "jacobi"])
def test_pca_with_fewer_neighbours_than_components(data, jacobi, monkeypatch):
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: jacobi)
    q, cond, valid, dur, targets = data
    nb = select_neighbours(jnp.asarray(cond), jnp.asarray(valid), jnp.asarray(targets), 10, 0.15)
    mask = np.zeros((C, 10), bool)
    mask[0, :3] = True  # 3 neighbours: 2 directions
    mask[1, :1] = True  # 1 neighbour: the mean, no direction
    basis = pca_basis(jnp.asarray(q), jnp.asarray(dur), nb._replace(mask=jnp.asarray(mask)), K)
    norms = np.linalg.norm(np.asarray(basis.components), axis=2)  # (C, K, J)
    np.testing.assert_allclose(norms[0, :2], 1.0, atol=1e-5)
    assert (norms[0, 2:] == 0).all() and (np.asarray(basis.variance)[0, 2:] == 0).all()
    assert (norms[1] == 0).all()
    np.testing.assert_allclose(np.asarray(basis.mean[1]), q[np.asarray(nb.index)[1, 0]], atol=0)
    # No neighbour at all: NaN mean and duration, so whatever is compiled from it is flagged.
    assert np.isnan(np.asarray(basis.mean[2])).all() and np.isnan(float(basis.duration[2]))
    assert int(basis.n_neighbours[2]) == 0


def test_validators():
    assert validate_targets([0.1, 0.2, 0.3]).shape == (1, 3)
    with pytest.raises(UserError, match="targets: expected shape"):
        validate_targets(np.zeros((2, 2)))
    with pytest.raises(UserError, match="targets: expected finite"):
        validate_targets([[0.0, np.nan, 0.0]])
    with pytest.raises(UserError, match="database: expected at least one valid"):
        validate_neighbour_database(np.zeros(4, bool))
