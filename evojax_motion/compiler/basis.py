"""Neighbour selection (paper eq. 6) and the per-joint PCA basis of the movement compilers (sec. 2).

For a target condition the compilers build their trajectories from the primitives of the database
whose conditions are closest to it (paper sec. 4.2: within a 15 cm radius, hand position only):

    d(c_i, c_j) = w_pos * |p_i - p_j| + w_rot * ||R_i^T R_j - I||_F            (eq. 6, see below)

Shapes must stay static under jit, so instead of "all primitives within r" we take a fixed-size
top-k (k = `settings.compiler.BasisSettings`' ``neighbours``) of the valid entries by distance,
with a mask. When fewer than k valid primitives lie within r, the nearest ones outside r fill the
set and the condition is flagged ``short``; invalid entries (and entries with a non-finite
condition) are never selected, so with fewer than k valid primitives in total the surplus slots
are masked out.

Orientation: the paper writes ``w2 |R_i^T R_j|``, but any norm of a rotation matrix is constant
(the Frobenius norm of a rotation is sqrt(3)), so taken literally the term adds nothing. We use its
deviation from the identity, ``||R_i^T R_j - I||_F = 2 sqrt(2) |sin(theta / 2)|`` for the relative
angle theta, which is 0 for equal orientations. The paper (and our default, ``w_rot = 0``) uses
position only.

`pca_basis` runs, per condition and per joint, a PCA of the masked neighbours' trajectories
(the paper's Fig. 4): the masked mean ``(T,)`` and the leading right singular vectors of the centred
``(k, T)`` matrix (masked rows zero) as unit-norm components, with their variances. On CPU by
LAPACK's SVD; on accelerators (`jacobi_backend`) through the ``k x k`` Gram matrix and one
batched symmetric eigensolver call, in two passes that keep the SVD's accuracy
(`_pca_rows_gram`): a batched SVD is one solver call per small matrix, which made the online
query ~260 targets/s on an H100.

Example (a batch of C target hand positions)::

    settings = BasisSettings()                          # r = 0.15 m, k = 10, position only
    nb = select_neighbours(db.condition, db.valid, targets, settings.neighbours,
                           settings.radius, settings.w_pos)
    basis = pca_basis(db.q, db.duration, nb, n_components=4)
    basis.mean        # (C, T, J)
    basis.components  # (C, 4, T, J)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.linalg import jacobi, lapack
from evojax_motion.linalg.jacobi import gram_two_pass, jacobi_backend

# A component whose singular value is below this fraction of the largest one spans only rounding
# noise (e.g. a joint that no neighbour moves); it is set to zero rather than to a random direction.
PCA_RTOL = 1e-5


class Neighbours(NamedTuple):
    """The k primitives chosen per condition, nearest first.

    index: (C, k) int32 rows of the database; mask: (C, k) bool, the slot holds a valid primitive;
    distance: (C, k) eq. 6 distance (+inf where masked); n_inside: (C,) int32 valid primitives
    within the radius (all of them, not only the k); short: (C,) bool, fewer than k inside.
    """

    index: jnp.ndarray  # type: ignore[assignment]  # (a field, shadowing tuple.index)
    mask: jnp.ndarray
    distance: jnp.ndarray
    n_inside: jnp.ndarray
    short: jnp.ndarray


class Basis(NamedTuple):
    """Per-condition, per-joint PCA basis of the neighbours (paper eq. 1 and 3).

    mean: (C, T, J) masked mean trajectory; components: (C, K, T, J), unit norm over T per joint,
    zero where the neighbours span fewer than K directions; variance: (C, K, J) variance of the
    neighbours' coefficients along each component [rad^2] (sum over the T samples);
    duration: (C,) masked mean duration [s]; n_neighbours: (C,) int32 neighbours used.
    Where a condition has no valid neighbour, ``mean`` and ``duration`` are NaN so everything
    compiled from it is flagged non-finite.
    """

    mean: jnp.ndarray
    components: jnp.ndarray
    variance: jnp.ndarray
    duration: jnp.ndarray
    n_neighbours: jnp.ndarray


def rotation_distance(rot_a: jnp.ndarray, rot_b: jnp.ndarray) -> jnp.ndarray:
    """``||R_a^T R_b - I||_F`` for ``rot_a (..., 3, 3)``, ``rot_b (..., 3, 3)`` -> ``(...)``."""
    rel = jnp.einsum("...ji,...jk->...ik", rot_a, rot_b, precision=jax.lax.Precision.HIGHEST)
    return jnp.linalg.norm(rel - jnp.eye(3, dtype=rel.dtype), axis=(-2, -1))


def condition_distance(
    condition: jnp.ndarray,
    targets: jnp.ndarray,
    w_pos: float = 1.0,
    rotation: jnp.ndarray | None = None,
    target_rotation: jnp.ndarray | None = None,
    w_rot: float = 0.0,
) -> jnp.ndarray:
    """Eq. 6 between every target and every database entry: ``(C, N)``.

    ``condition: (N, 3)``, ``targets: (C, 3)``; ``rotation: (N, 3, 3)`` and
    ``target_rotation: (C, 3, 3)`` are used when both are given and ``w_rot > 0``.
    """
    diff = targets[:, None, :] - condition[None, :, :]
    # No floor on the sum of squares (it is >= 0): jnp.maximum(NaN, 0.0) is 0.0 in XLA's
    # vectorised CPU code, which gave a NaN target distance 0 to every entry under jit.
    d = w_pos * jnp.sqrt(jnp.sum(diff**2, axis=-1))
    if rotation is not None and target_rotation is not None and w_rot > 0:
        d = d + w_rot * rotation_distance(target_rotation[:, None], rotation[None, :])
    return d


# Distances held at once by the neighbour search (1 GiB in float32): the (C, N) distance matrix
# of 1e5 conditions against a database of 1e5 entries would take 40 GB, so the targets are
# searched in ``lax.map`` blocks of ``NEIGHBOUR_BLOCK_ENTRIES // N`` (2,676 at N = 100,311). A
# small database (online queries: N = 611) is searched in one block: blocks run one after the
# other, each far too small to fill a GPU.
NEIGHBOUR_BLOCK_ENTRIES = 2**28


def select_neighbours(
    condition: jnp.ndarray,
    valid: jnp.ndarray,
    targets: jnp.ndarray,
    k: int,
    radius: float,
    w_pos: float = 1.0,
    rotation: jnp.ndarray | None = None,
    target_rotation: jnp.ndarray | None = None,
    w_rot: float = 0.0,
) -> Neighbours:
    """The k nearest valid primitives of each target by eq. 6 (fixed-size top-k with a mask).

    ``condition: (N, 3)`` and ``valid: (N,)`` from the database, ``targets: (C, 3)``; optional
    orientations ``rotation: (N, 3, 3)``, ``target_rotation: (C, 3, 3)`` weighted by ``w_rot``.
    ``k`` and the weights are static; ``radius`` [m, or distance units when ``w_pos != 1``] only
    decides ``n_inside``/``short``. Pure and jittable; a NaN target gets an all-False mask.
    The targets are searched in blocks of ``NEIGHBOUR_BLOCK_ENTRIES // N`` (memory bounded by
    `NEIGHBOUR_BLOCK_ENTRIES` distances, not ``C x N``).
    """
    n = condition.shape[0]
    k_eff = min(k, n)  # a database smaller than k: the surplus slots are padding
    use_rot = rotation is not None and target_rotation is not None and w_rot > 0

    def one(xs):
        tgt, tgt_rot = xs  # (3,), (3, 3) or None
        d = condition_distance(
            condition, tgt[None], w_pos, rotation, None if tgt_rot is None else tgt_rot[None],
            w_rot,
        )[0]  # fmt: skip
        usable = valid & jnp.isfinite(d)
        d = jnp.where(usable, d, jnp.inf)
        neg, index = jax.lax.top_k(-d, k_eff)
        n_inside = jnp.sum(usable & (d <= radius)).astype(jnp.int32)
        return -neg, index, n_inside

    xs = (targets, target_rotation if use_rot else None)
    block = max(1, NEIGHBOUR_BLOCK_ENTRIES // max(n, 1))
    if targets.shape[0] > block:
        dist, index, n_inside = jax.lax.map(one, xs, batch_size=block)
    else:
        dist, index, n_inside = jax.vmap(one)(xs)
    if k_eff < k:
        pad = k - k_eff
        dist = jnp.concatenate([dist, jnp.full((dist.shape[0], pad), jnp.inf, dist.dtype)], 1)
        index = jnp.concatenate([index, jnp.zeros((index.shape[0], pad), index.dtype)], 1)
    mask = jnp.isfinite(dist)
    return Neighbours(
        index=index.astype(jnp.int32),
        mask=mask,
        distance=dist,
        n_inside=n_inside,
        short=n_inside < k,
    )


def neighbour_candidates(
    condition: jnp.ndarray,
    valid: jnp.ndarray,
    n_fixed: int,
    targets: jnp.ndarray,
    k: int,
    extra: int,
    w_pos: float = 1.0,
) -> jnp.ndarray:
    """Candidate lists for `select_neighbours_among`: ``(C, k + extra)`` int32 database rows.

    Per target: its k nearest valid rows among the first ``n_fixed`` (rows whose validity never
    changes: the human originals), nearest first; then its ``extra`` nearest rows with a finite
    condition after them (the evolved slots, filled or not), nearest first. Where there are fewer,
    the list is filled with ``N`` (one past the last row). ``condition: (N, 3)``, ``valid: (N,)``,
    ``targets: (C, 3)``; ``n_fixed``, ``k``, ``extra`` static. The search is `select_neighbours`'
    (position only): quadratic in the conditions, so it is made once, not per generation.
    """
    n = condition.shape[0]
    fixed = select_neighbours(condition[:n_fixed], valid[:n_fixed], targets, k, jnp.inf, w_pos)
    rest = select_neighbours(
        condition[n_fixed:], jnp.ones(n - n_fixed, bool), targets, extra, jnp.inf, w_pos
    )
    return jnp.concatenate(
        [jnp.where(fixed.mask, fixed.index, n), jnp.where(rest.mask, rest.index + n_fixed, n)],
        axis=1,
    ).astype(jnp.int32)


def select_neighbours_among(
    condition: jnp.ndarray,
    valid: jnp.ndarray,
    targets: jnp.ndarray,
    candidates: jnp.ndarray,
    k: int,
    radius: float,
    w_pos: float = 1.0,
) -> tuple[Neighbours, jnp.ndarray]:
    """`select_neighbours` (position only) searching only each target's candidate list: linear,
    not quadratic, in the conditions. Returns ``(neighbours, exact (C,) bool)``.

    ``candidates: (C, k + L)`` from `neighbour_candidates` over the same rows, whose fixed rows
    have not changed validity since. Rows outside a list are fixed rows farther than the list's k
    nearest (``valid`` at this call: the k nearest valid fixed rows are in the list) or other rows
    at least as far as the list's last one, so the k nearest valid rows of the list are those of
    the whole database (``exact``) when the k-th is nearer than that last row, when the list holds
    every other finite row, or for a non-finite target (no neighbour either way). Where ``exact``,
    ``index`` (where ``mask``), ``mask``, ``distance`` and ``short`` equal `select_neighbours`';
    ``n_inside`` counts the list's rows only (which decides ``short`` exactly); masked ``index``
    entries are 0.
    """
    n = condition.shape[0]
    pts = jnp.take(condition, candidates, axis=0, mode="fill", fill_value=jnp.nan)  # (C, L, 3)
    ok = jnp.take(valid, candidates, axis=0, mode="fill", fill_value=False)

    def one(p, tgt):
        return condition_distance(p, tgt[None], w_pos)[0]

    raw = jax.vmap(one)(pts, targets)  # (C, L), NaN at the fillers
    usable = ok & jnp.isfinite(raw)
    d = jnp.where(usable, raw, jnp.inf)
    neg, pos = jax.lax.top_k(-d, k)
    dist = -neg
    mask = jnp.isfinite(dist)
    index = jnp.where(mask, jnp.take_along_axis(candidates, pos, axis=1), 0)
    everything = candidates[:, -1] >= n  # a filler: the list holds every other finite row
    no_target = ~jnp.all(jnp.isfinite(targets), axis=-1)
    exact = (dist[:, k - 1] < raw[:, -1]) | everything | no_target
    n_inside = jnp.sum(usable & (d <= radius), axis=1).astype(jnp.int32)
    nb = Neighbours(
        index=index.astype(jnp.int32), mask=mask, distance=dist, n_inside=n_inside,
        short=n_inside < k,
    )  # fmt: skip
    return nb, exact


def small_svd(a: jnp.ndarray, full_matrices: bool = True):
    """`linalg.jacobi.small_svd` of ``a (m, n)`` with this backend's kernel (`jacobi_backend`,
    looked up here at trace time: LAPACK on CPU, one-sided Jacobi on accelerators)."""
    return jacobi.small_svd(a, full_matrices, jacobi=jacobi_backend())


def small_eigh(a: jnp.ndarray):
    """`linalg.jacobi.small_eigh` of symmetric ``a (..., n, n)`` with this backend's kernel
    (`jacobi_backend`, looked up here at trace time): ``(e (..., n) ascending, v (..., n, n))``."""
    return jacobi.small_eigh(a, jacobi=jacobi_backend())


def small_right_svd(a: jnp.ndarray, two_pass_gram: bool = False):
    """`linalg.jacobi.small_right_svd` of ``a (m, n)`` with this backend's kernel
    (`jacobi_backend`, looked up here at trace time): ``(s (n,), vt (n, n))``."""
    return jacobi.small_right_svd(a, two_pass_gram, jacobi=jacobi_backend())


def _pca_rows_svd(centred: jnp.ndarray, n_components: int):
    """Leading singular values ``(K',)`` and right singular vectors ``(K', T)``, ``K' = min(k,
    K)``, of ``centred (k, T)`` by LAPACK (CPU): the left singular vectors of its transpose,
    since LAPACK's path for a tall matrix is the faster one (a paper-scale generation's 2,100
    matrices of 10 x 100 on 2 CPU cores: 43 against 59 ms, CHANGELOG.md)."""
    u, sv, _ = lapack.svd(centred.T, full_matrices=False)  # u: (T, min(k, T))
    avail = min(u.shape[1], n_components)
    return sv[:avail], u[:, :avail].T


def _pca_rows_gram(centred: jnp.ndarray, n_components: int):
    """As `_pca_rows_svd`, through the ``k x k`` Gram matrix (k ~ 10 rows) in two passes
    (`linalg.jacobi.gram_two_pass`: as accurate as a backward stable SVD of X).

    For accelerators: under vmap each pass is one batched symmetric eigensolver call (cuSOLVER's
    batched Jacobi on GPUs). For 700,000 Gram matrices of 10 x 100 trajectories (100,000 online
    targets) on an H100 this takes 48 ms, the same two passes with `jacobi_eigh` 137 ms
    (``benchmarks/small_eigh.py``, ``benchmarks/results/small_eigh_gpu.json``)."""
    _, z = gram_two_pass(centred, lapack.eigh)  # (k, T) rows s_i v_i, unordered
    sv, order = jax.lax.top_k(jnp.sqrt(jnp.sum(z * z, axis=1)), min(z.shape[0], n_components))
    return sv, z[order] / jnp.where(sv > 0, sv, 1.0)[:, None]


def _joint_pca(x: jnp.ndarray, mask: jnp.ndarray, n_components: int, gram: bool):
    """PCA of one joint's neighbour trajectories ``x (k, T)`` with row ``mask (k,)``.

    Returns ``mean (T,)``, ``components (K, T)``, ``variance (K,)``: the leading right singular
    vectors of the centred matrix, and its squared singular values / (count - 1). ``gram``:
    `_pca_rows_gram` (accelerators), else `_pca_rows_svd`.
    """
    w = mask.astype(x.dtype)
    count = jnp.sum(w)
    # where, not a product: a masked slot may hold anything (an empty database row, NaN).
    mean = jnp.sum(jnp.where(mask[:, None], x, 0.0), axis=0) / jnp.maximum(count, 1.0)
    mean = jnp.where(count > 0, mean, jnp.nan)
    centred = jnp.where(mask[:, None], x - mean, 0.0)
    sv, vt = (_pca_rows_gram if gram else _pca_rows_svd)(centred, n_components)
    avail = vt.shape[0]
    if avail < n_components:  # fewer rows than requested components: pad with zeros
        vt = jnp.concatenate([vt, jnp.zeros((n_components - avail, vt.shape[1]), vt.dtype)])
        sv = jnp.concatenate([sv, jnp.zeros(n_components - avail, sv.dtype)])
    # Centred data of n rows span at most n - 1 directions; below PCA_RTOL it is rounding noise.
    rank_ok = jnp.arange(n_components) < count - 1
    keep = rank_ok & (sv > PCA_RTOL * sv[0]) & (sv[0] > 0)
    # Sign convention: the entry of largest magnitude is positive (SVD signs are arbitrary).
    peak = jnp.take_along_axis(vt, jnp.argmax(jnp.abs(vt), axis=1)[:, None], axis=1)
    vt = vt * jnp.where(peak < 0, -1.0, 1.0).astype(vt.dtype)
    components = jnp.where(keep[:, None], vt, 0.0)
    variance = jnp.where(keep, sv**2 / jnp.maximum(count - 1.0, 1.0), 0.0)
    return mean, components, variance


def pca_basis(
    q: jnp.ndarray, duration: jnp.ndarray, neighbours: Neighbours, n_components: int
) -> Basis:
    """Masked per-joint PCA of each condition's neighbours (paper sec. 2, Fig. 4).

    ``q: (N, T, J)``, ``duration: (N,)`` from the database, ``neighbours`` from
    `select_neighbours` (``C`` conditions, ``k`` slots); ``n_components`` (K) is static.
    Returns a `Basis` (``mean (C, T, J)``, ``components (C, K, T, J)``, ``variance (C, K, J)``,
    ``duration (C,)``, ``n_neighbours (C,)``). Pure and jittable.
    """
    x = q[neighbours.index]  # (C, k, T, J)
    # joint axis last in every output: mean (T, J), components (K, T, J), variance (K, J)
    per_joint = jax.vmap(_joint_pca, in_axes=(2, None, None, None), out_axes=(1, 2, 1))
    per_condition = jax.vmap(per_joint, in_axes=(0, 0, None, None))
    mean, comps, var = per_condition(x, neighbours.mask, n_components, jacobi_backend())
    w = neighbours.mask.astype(q.dtype)
    count = jnp.sum(w, axis=1)
    dur = jnp.where(neighbours.mask, duration[neighbours.index], 0.0)
    dur = jnp.sum(dur, axis=1) / jnp.maximum(count, 1.0)
    return Basis(
        mean=mean,
        components=comps,
        variance=var,
        duration=jnp.where(count > 0, dur, jnp.nan),
        n_neighbours=count.astype(jnp.int32),
    )


def validate_targets(targets, where: str = "targets") -> np.ndarray:
    """A user's target hand positions as a finite ``(C, 3)`` float32 array, else `UserError`.

    A single ``(3,)`` target becomes ``(1, 3)``.
    """
    arr = np.asarray(targets, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise UserError(f"{where}: expected shape (C, 3) hand positions [m], got {arr.shape}")
    if not np.isfinite(arr).all():
        raise UserError(f"{where}: expected finite positions [m], got NaN/inf")
    return arr.astype(np.float32)


def validate_neighbour_database(valid, where: str = "database") -> None:
    """Refuse a database with no valid primitive (no basis can be built). Raises `UserError`."""
    if not np.asarray(valid).any():
        raise UserError(f"{where}: expected at least one valid primitive, got none")
