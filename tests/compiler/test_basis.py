"""Neighbour selection (eq. 6) and the masked per-joint PCA basis against numpy references."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import subspace_angles
from scipy.spatial.transform import Rotation

import evojax_motion.compiler.basis as basis_module
import evojax_motion.linalg.jacobi as linalg_jacobi
from evojax_motion.compiler.basis import (
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
from evojax_motion.settings.compiler import BasisSettings

TOL_ANGLE = 1e-3  # rad: largest principal angle between our and numpy's component subspaces
TOL_PCA = 1e-5  # rad: masked mean vs numpy (float32 sums of ~10 values of ~1 rad)
TOL_VAR_REL = 1e-4  # relative: component variances vs numpy's singular values
TOL_DIST = 1e-6  # m: distances vs numpy
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
    from evojax_motion.evolution.step import search_neighbours

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


@pytest.mark.parametrize("jacobi", [False, True], ids=["lapack", "jacobi"])
def test_small_decompositions_follow_the_backend_switch(jacobi, monkeypatch):
    """`small_svd`, `small_eigh` and `small_right_svd` take this module's `jacobi_backend` at
    trace time (the switch the compilers' accelerator-path tests patch): each gives exactly what
    its `linalg.jacobi` kernel gives with that choice (the kernels:
    `tests/linalg/test_linalg.py`)."""
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: jacobi)
    rng = np.random.default_rng(8)
    a = jnp.asarray(rng.standard_normal((6, 5)), jnp.float32)
    sym = a.T @ a
    pairs = [
        (small_svd(a, False), linalg_jacobi.small_svd(a, False, jacobi=jacobi)),
        (small_eigh(sym), linalg_jacobi.small_eigh(sym, jacobi=jacobi)),
        (small_right_svd(a, True), linalg_jacobi.small_right_svd(a, True, jacobi=jacobi)),
    ]
    for got, want in pairs:
        for x, y in zip(got, want, strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    other = linalg_jacobi.small_eigh(sym, jacobi=not jacobi)[1]
    assert not np.array_equal(np.asarray(small_eigh(sym)[1]), np.asarray(other))


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
