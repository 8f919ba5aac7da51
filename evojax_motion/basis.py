"""Neighbour selection (paper eq. 6) and the per-joint PCA basis of the movement compilers (sec. 2).

For a target condition the compilers build their trajectories from the primitives of the database
whose conditions are closest to it (paper sec. 4.2: within a 15 cm radius, hand position only):

    d(c_i, c_j) = w_pos * |p_i - p_j| + w_rot * ||R_i^T R_j - I||_F            (eq. 6, see below)

Shapes must stay static under jit, so instead of "all primitives within r" we take a fixed-size
top-k (k = ``BasisSettings.neighbours``) of the valid entries by distance, with a mask. When fewer
than k valid primitives lie within r, the nearest ones outside r fill the set and the condition is
flagged ``short``; invalid entries (and entries with a non-finite condition) are never selected,
so with fewer than k valid primitives in total the surplus slots are masked out.

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

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.errors import UserError

# A component whose singular value is below this fraction of the largest one spans only rounding
# noise (e.g. a joint that no neighbour moves); it is set to zero rather than to a random direction.
PCA_RTOL = 1e-5


def _check(ok: bool, name: str, expected: str, value) -> None:
    if not ok:
        raise ValueError(f"{name}: expected {expected}, got {value!r}")


@dataclass(frozen=True)
class BasisSettings:
    """Neighbour selection of eq. 6; defaults are the paper's (sec. 4.2).

    - ``radius`` [m]: primitives whose condition lies within it are "inside" (paper: 15 cm).
    - ``neighbours``: fixed number k of primitives per basis (top-k by distance).
    - ``w_pos`` [1/m], ``w_rot``: weights of the position and orientation terms of eq. 6.
    """

    radius: float = 0.15
    neighbours: int = 10
    w_pos: float = 1.0
    w_rot: float = 0.0

    def __post_init__(self):
        _check(
            isinstance(self.radius, int | float) and self.radius > 0,
            "radius",
            "a number > 0 [m]",
            self.radius,
        )
        _check(
            isinstance(self.neighbours, int) and self.neighbours >= 2,
            "neighbours",
            "an integer >= 2",
            self.neighbours,
        )
        _check(
            isinstance(self.w_pos, int | float) and self.w_pos > 0,
            "w_pos",
            "a number > 0",
            self.w_pos,
        )
        _check(
            isinstance(self.w_rot, int | float) and self.w_rot >= 0,
            "w_rot",
            "a number >= 0",
            self.w_rot,
        )


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


# Symmetric eigenproblems up to this size are solved by `jacobi_eigh` (elementwise code, batched
# by vmap and fused by XLA); larger ones by `jnp.linalg.eigh` (a solver call per matrix on GPUs).
JACOBI_MAX_N = 12
# Parallel Jacobi sweeps from the identity (quadratic convergence; float32 random symmetric matrices
# reach rounding level after 3 sweeps at n <= 5 and 5 at n = 10): up to n = 6, and above.
JACOBI_SWEEPS_SMALL = 4
JACOBI_SWEEPS = 6
# One-sided Jacobi (`jacobi_svd`) up to n = 6: one sweep more. On the paper's BC solves (100
# conditions x 7 joints, T = 100, K = 4; compared with a float64 solve)
# 4 sweeps left start trajectories up to 8.4e-3 rad off the float64 ones, 5 as close as LAPACK
# (1.5e-4 rad): the BC rows in q-orthonormal coordinates are graded over four orders (the slope
# rows near `BC_LEAK`), and after 4 sweeps their left singular vectors were orthonormal only to
# 2.1e-6 (`tests/test_basis.py`, ``PAPER_BC_ROWS``).
JACOBI_SVD_SWEEPS_SMALL = 5


def _dot(a, b):
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _round_robin(n: int) -> list[np.ndarray]:
    """Static schedule of parallel Jacobi rounds for an even ``n``: every round rotates the pairs
    of adjacent positions ``(2i, 2i + 1)``, then the matrix is permuted by the round's index
    array so that the next round's pairs are adjacent. Circle method (one index fixed, the others
    rotating): the ``n - 1`` rounds of a sweep meet every pair once and end in the start order."""
    half = n // 2
    slot = [2 * i if i < half else 2 * (n - 1 - i) + 1 for i in range(n)]  # list index -> position

    def order(players):
        out = [0] * n
        for i, p in enumerate(players):
            out[slot[i]] = p
        return out

    players = list(range(n))
    perms = []
    for _ in range(n - 1):
        nxt = [players[0], players[-1], *players[1:-1]]
        now, new = order(players), order(nxt)
        perms.append(np.asarray([now.index(p) for p in new]))
        players = nxt
    return perms


def _pair_rotation(app, aqq, apq):
    """Cosines and sines ``(c, s)`` of the Jacobi rotations that zero ``apq`` in the symmetric 2x2
    blocks ``[[app, apq], [apq, aqq]]`` (Numerical Recipes' stable angle; no rotation where
    ``apq == 0``). All arguments ``(h,)``."""
    one = jnp.ones((), app.dtype)
    nz = apq != 0
    theta = (aqq - app) / jnp.where(nz, 2.0 * apq, one)
    t = jnp.where(theta >= 0, one, -one) / (jnp.abs(theta) + jnp.hypot(theta, one))
    t = jnp.where(nz, t, 0.0)
    c = jax.lax.rsqrt(t * t + 1.0)
    return c, t * c


def _rotate_pairs(x, c, s):
    """Columns ``(2i, 2i + 1)`` of ``x (r, m)`` rotated by ``(c_i, s_i)``: ``x J``."""
    r, m = x.shape
    x = x.reshape(r, m // 2, 2)
    x0, x1 = x[..., 0], x[..., 1]
    return jnp.stack([c * x0 - s * x1, s * x0 + c * x1], axis=-1).reshape(r, m)


def _default_sweeps(n: int) -> int:
    return JACOBI_SWEEPS_SMALL if n <= 6 else JACOBI_SWEEPS


def jacobi_eigh(a: jnp.ndarray, sweeps: int | None = None):
    """Eigenvalues ``w (n,)`` (unsorted) and eigenvectors ``v (n, n)`` (columns) of a small
    symmetric ``a (n, n)``, ``a = v diag(w) v^T``, by ``sweeps`` sweeps of parallel cyclic Jacobi
    (default `JACOBI_SWEEPS_SMALL` up to n = 6, else `JACOBI_SWEEPS`).

    Each round rotates ``n / 2`` disjoint pairs at once (`_pair_rotation`) with
    elementwise arithmetic on the whole matrix, then permutes it (`_round_robin`): a short program
    (fast to compile) with no solver call per matrix, so under vmap a batch runs as a few fused
    elementwise kernels per round (batched cuSOLVER/LAPACK calls for small matrices cost far more
    than their arithmetic on GPUs). An odd ``n`` is padded with a decoupled zero row. Sizes above
    `JACOBI_MAX_N` use ``jnp.linalg.eigh``.
    """
    n = a.shape[-1]
    if n > JACOBI_MAX_N:
        return jnp.linalg.eigh(a)
    m = n + n % 2
    a = jnp.pad(a, ((0, m - n), (0, m - n)))
    perms = _round_robin(m)

    def sweep(_, carry):
        x, v = carry
        for perm in perms:
            d = jnp.diagonal(x)
            c, s = _pair_rotation(d[0::2], d[1::2], jnp.diagonal(x, offset=1)[0::2])
            x = _rotate_pairs(_rotate_pairs(x, c, s).T, c, s)  # J^T x J (x symmetric)
            v = _rotate_pairs(v, c, s)
            x, v = x[perm][:, perm], v[:, perm]
        return x, v

    sweeps = _default_sweeps(n) if sweeps is None else sweeps
    x, v = jax.lax.fori_loop(0, sweeps, sweep, (a, jnp.eye(m, dtype=a.dtype)))
    return jnp.diagonal(x)[:n], v[:n, :n]


def jacobi_svd(a: jnp.ndarray, sweeps: int | None = None):
    """``(u (m, k), s (k,), vt (n, n))`` of a small ``a (m, n)``, ``k = min(m, n)``, singular
    values descending, like ``jnp.linalg.svd(a, full_matrices=True)`` for ``vt`` (columns of
    ``u`` are zero where ``s == 0``), by one-sided (Hestenes) Jacobi.

    The columns of ``a`` are rotated pairwise until they are orthogonal, ``a V = U diag(s)``: each
    round takes the pairs' norms and dot product from the current columns and rotates them like
    `jacobi_eigh` rotates a symmetric matrix. No Gram matrix is formed, so small singular values
    keep the accuracy of a backward-stable SVD (relative to ``s[0]``, not ``sqrt(eps)``), and
    there is no solver call: under vmap a batch is a few elementwise kernels per round, for
    accelerators (`small_svd`). ``n`` up to `JACOBI_MAX_N`; an odd ``n`` gets a zero column.
    """
    m, n = a.shape
    if n > JACOBI_MAX_N:
        raise ValueError(f"jacobi_svd: expected at most {JACOBI_MAX_N} columns, got {n}")
    n2 = n + n % 2
    x = jnp.pad(a, ((0, 0), (0, n2 - n)))
    perms = _round_robin(n2)

    def sweep(_, carry):
        x, v = carry
        for perm in perms:
            pairs = x.reshape(m, n2 // 2, 2)
            p, q = pairs[..., 0], pairs[..., 1]
            c, s = _pair_rotation(
                jnp.sum(p * p, axis=0), jnp.sum(q * q, axis=0), jnp.sum(p * q, axis=0)
            )
            x, v = _rotate_pairs(x, c, s)[:, perm], _rotate_pairs(v, c, s)[:, perm]
        return x, v

    if sweeps is None:
        sweeps = JACOBI_SVD_SWEEPS_SMALL if n <= 6 else JACOBI_SWEEPS
    x, v = jax.lax.fori_loop(0, sweeps, sweep, (x, jnp.eye(n2, dtype=a.dtype)))
    norms = jnp.sqrt(jnp.sum(x * x, axis=0))
    sv, order = jax.lax.top_k(norms, n2)
    k = min(m, n)
    u = x[:, order[:k]] / jnp.where(sv[:k] > 0, sv[:k], 1.0)[None, :]
    # The padding column stays zero and sorts last among equals; drop its row and column of V.
    vt = v[:n, order[:n]].T
    return jnp.where(sv[None, :k] > 0, u, 0.0), sv[:k], vt


def small_svd(a: jnp.ndarray, full_matrices: bool = True):
    """``jnp.linalg.svd`` of a small ``a (m, n)`` on CPU (LAPACK), `jacobi_svd` on accelerators
    (`jacobi_backend`); ``full_matrices=False`` trims ``vt`` to ``(min(m, n), n)``."""
    if jacobi_backend() and a.shape[-1] <= JACOBI_MAX_N:
        u, s, vt = jacobi_svd(a)
        return u, s, vt if full_matrices else vt[: s.shape[0]]
    return jnp.linalg.svd(a, full_matrices=full_matrices)


def small_eigh(a: jnp.ndarray):
    """``jnp.linalg.eigh`` (ascending eigenvalues ``(..., n)``, eigenvectors ``(..., n, n)``) of a
    batch of small symmetric ``a (..., n, n)``: LAPACK/cuSOLVER, or `jacobi_eigh` on
    accelerators (`jacobi_backend`) up to ``n = JACOBI_MAX_N``."""
    n = a.shape[-1]
    if not (jacobi_backend() and n <= JACOBI_MAX_N):
        return jnp.linalg.eigh(a)
    batch = a.shape[:-2]
    w, v = jax.vmap(jacobi_eigh)(a.reshape(-1, n, n))
    order = jnp.argsort(w, axis=-1)
    w = jnp.take_along_axis(w, order, axis=-1)
    v = jnp.take_along_axis(v, order[:, None, :], axis=-1)
    return w.reshape(*batch, n), v.reshape(*batch, n, n)


def jacobi_backend() -> bool:
    """Whether small decompositions use `jacobi_eigh` (accelerators) or LAPACK (CPU).

    On GPUs a batch of small SVD/eigen problems is a cuSOLVER call per matrix or a batched Jacobi
    call, both far slower than the arithmetic (an online query has ~70 such problems per target);
    on CPU, LAPACK is fast and `jacobi_eigh`'s long elementwise program compiles slowly (the same
    split as ``dynamics_rnea.default_form``). Read at trace time.
    """
    return jax.default_backend() != "cpu"


def gram_svd(a: jnp.ndarray):
    """``(u (m, k), s (k,), vt (n, n))`` of a small ``a (m, n)``, ``k = min(m, n)``, singular
    values descending, from the eigen-decomposition of ``a^T a`` (`jacobi_eigh`).

    Like ``jnp.linalg.svd(a, full_matrices=True)`` for ``vt``, but singular values below
    ~``sqrt(eps) * s[0]`` are rounding noise (the Gram squares the conditioning): for rank
    decisions at coarser tolerances and pseudo-inverses followed by a refinement step. Columns of
    ``u`` are zero where ``s == 0``.
    """
    m, n = a.shape
    lam, v = jacobi_eigh(_dot(a.T, a))
    order = jnp.argsort(-lam)
    lam, v = lam[order], v[:, order]
    k = min(m, n)
    s = jnp.sqrt(jnp.maximum(lam[:k], 0.0))
    u = _dot(a, v[:, :k]) / jnp.where(s > 0, s, 1.0)[None, :]
    return jnp.where(s[None, :] > 0, u, 0.0), s, v.T


def _pca_rows_svd(centred: jnp.ndarray, n_components: int):
    """Leading singular values ``(K',)`` and right singular vectors ``(K', T)``, ``K' = min(k,
    K)``, of ``centred (k, T)`` by LAPACK (CPU): the left singular vectors of its transpose,
    since LAPACK's path for a tall matrix is the faster one (a paper-scale generation's 2,100
    matrices of 10 x 100 on 2 CPU cores: 43 against 59 ms, CHANGELOG.md)."""
    u, sv, _ = jnp.linalg.svd(centred.T, full_matrices=False)  # u: (T, min(k, T))
    avail = min(u.shape[1], n_components)
    return sv[:avail], u[:, :avail].T


def _gram_two_pass(x: jnp.ndarray, eigh):
    """``(left (r, r), z (r, c))`` for ``x (r, c)``: its left singular vectors (columns) and the
    rows ``s_i v_i`` (singular value times right singular vector), both unordered, from two
    passes of its ``r x r`` row Gram: ``x x^T = U diag(s^2) U^T`` rotates the rows, ``y = U^T
    x``; the Gram of ``y`` (nearly diagonal) rotates them again, ``z = W^T y``, and ``left = U
    W``. The second Gram is formed from the rotated rows, so its entries err by rounding relative
    to ``s_i s_j`` rather than to ``s_0^2``: as accurate as a (backward stable) SVD of x, with no
    ``sqrt(eps)`` floor on the small singular values. ``eigh``: a symmetric eigensolver
    returning ``(values, vectors)`` (`jnp.linalg.eigh` or `jacobi_eigh`)."""
    _, u = eigh(_dot(x, x.T))
    y = _dot(u.T, x)
    _, w = eigh(_dot(y, y.T))
    return _dot(u, w), _dot(w.T, y)


def small_right_svd(a: jnp.ndarray, two_pass_gram: bool = False):
    """``(s (n,), vt (n, n))`` of a small ``a (m, n)`` with ``m >= n``: singular values
    (descending) and right singular vectors (rows), as ``jnp.linalg.svd(a,
    full_matrices=False)[1:]``.

    `small_svd`'s (LAPACK on CPU, one-sided Jacobi on accelerators), or with ``two_pass_gram``
    on accelerators (`jacobi_backend`, ``n <= JACOBI_MAX_N``) the two Gram passes of
    `_gram_two_pass` on the columns' ``n x n`` Gram with `jacobi_eigh`: as accurate, with no
    reduction over the m rows per Jacobi round, but more rounds. For the optimiser's BC solve
    (100 x 5 matrices per condition and joint, `compile_interp.GRAM_SVD_MIN_MATRICES`).
    """
    m, n = a.shape
    if not (two_pass_gram and jacobi_backend() and m >= n and n <= JACOBI_MAX_N):
        _, s, vt = small_svd(a, full_matrices=False)
        return s, vt
    left, z = _gram_two_pass(a.T, jacobi_eigh)
    s, order = jax.lax.top_k(jnp.sqrt(jnp.sum(z * z, axis=1)), n)
    return s, left[:, order].T


def _pca_rows_gram(centred: jnp.ndarray, n_components: int):
    """As `_pca_rows_svd`, through the ``k x k`` Gram matrix (k ~ 10 rows) in two passes
    (`_gram_two_pass`: as accurate as a backward stable SVD of X).

    For accelerators: under vmap each pass is one batched symmetric eigensolver call (cuSOLVER's
    batched Jacobi on GPUs). For 700,000 Gram matrices of 10 x 100 trajectories (100,000 online
    targets) on an H100 this takes 48 ms, the same two passes with `jacobi_eigh` 137 ms
    (``benchmarks/small_eigh.py``, ``benchmarks/results/small_eigh_gpu.json``)."""
    _, z = _gram_two_pass(centred, jnp.linalg.eigh)  # (k, T) rows s_i v_i, unordered
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
