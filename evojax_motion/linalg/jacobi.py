"""Small symmetric eigenproblems and SVDs as elementwise code: parallel cyclic Jacobi.

Used by the PCA basis (`compiler.basis.pca_basis`), the boundary-condition solves
(`compile_interp`) and
the Newton method's trust-region models (`solvers.steps`). On GPUs a batch of small SVD / eigen
problems is a cuSOLVER call per matrix, far slower than its arithmetic; these kernels are
straight-line elementwise code that vmap batches and XLA fuses. On CPU LAPACK is faster (and these
long programs compile slowly): the dispatching functions `small_svd`, `small_eigh` and
`small_right_svd` take the choice as an argument (`jacobi_backend`: on accelerators).

- `jacobi_eigh`: parallel two-sided Jacobi of a symmetric ``(n, n)``;
- `jacobi_svd`: one-sided (Hestenes) Jacobi of an ``(m, n)``, as accurate as a backward stable
  SVD;
- `gram_svd`, `gram_two_pass`: SVDs through the Gram matrix (one pass: a ``sqrt(eps)`` floor on
  the small singular values; two passes: none).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.linalg import lapack

# Symmetric eigenproblems up to this size are solved by `jacobi_eigh` (elementwise code, batched
# by vmap and fused by XLA); larger ones by `jnp.linalg.eigh` (a solver call per matrix on GPUs).
JACOBI_MAX_N = 12
# Parallel Jacobi sweeps, starting from the matrix itself (quadratic convergence; float32 random
# symmetric matrices reach rounding level after 3 sweeps at n <= 5 and 5 at n = 10): up to n = 6,
# and above.
JACOBI_SWEEPS_SMALL = 4
JACOBI_SWEEPS = 6
# One-sided Jacobi (`jacobi_svd`) up to n = 6: one sweep more. On the paper's BC solves (100
# conditions x 7 joints, T = 100, K = 4), compared with a float64 solve, 4 sweeps left start
# trajectories up to 8.4e-3 rad off the float64 ones, 5 as close as LAPACK (1.5e-4 rad): the BC
# rows in q-orthonormal coordinates are graded over four orders (the slope rows near `BC_LEAK`),
# and after 4 sweeps their left singular vectors were orthonormal only to 2.1e-6
# (`tests/compiler/test_basis.py`, ``PAPER_BC_ROWS``).
JACOBI_SVD_SWEEPS_SMALL = 5


def dot(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """``a @ b`` at full float32 precision (no reduced-precision passes on accelerators)."""
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
        return lapack.eigh(a)
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


def jacobi_backend() -> bool:
    """Whether small decompositions should use the Jacobi kernels (accelerators) or LAPACK (CPU).

    On GPUs a batch of small SVD/eigen problems is a cuSOLVER call per matrix or a batched Jacobi
    call, both far slower than the arithmetic (an online query has ~70 such problems per target);
    on CPU, LAPACK is fast and `jacobi_eigh`'s long elementwise program compiles slowly (the same
    split as ``model.rnea.default_form``). Read at trace time.
    """
    return jax.default_backend() != "cpu"


def small_svd(
    a: jnp.ndarray, full_matrices: bool = True, *, jacobi: bool
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """``jnp.linalg.svd`` of a small ``a (m, n)``: by LAPACK, or with ``jacobi`` (accelerators,
    `jacobi_backend`) by `jacobi_svd` up to ``n = JACOBI_MAX_N``. ``full_matrices=False`` trims
    ``vt`` to ``(min(m, n), n)``."""
    if jacobi and a.shape[-1] <= JACOBI_MAX_N:
        u, s, vt = jacobi_svd(a)
        return u, s, vt if full_matrices else vt[: s.shape[0]]
    u, s, vt = lapack.svd(a, full_matrices=full_matrices)
    return u, s, vt


def small_eigh(a: jnp.ndarray, *, jacobi: bool) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``jnp.linalg.eigh`` (ascending eigenvalues ``(..., n)``, eigenvectors ``(..., n, n)``) of a
    batch of small symmetric ``a (..., n, n)``: LAPACK/cuSOLVER, or with ``jacobi``
    (accelerators, `jacobi_backend`) `jacobi_eigh` up to ``n = JACOBI_MAX_N``."""
    n = a.shape[-1]
    if not (jacobi and n <= JACOBI_MAX_N):
        return lapack.eigh(a)
    batch = a.shape[:-2]
    w, v = jax.vmap(jacobi_eigh)(a.reshape(-1, n, n))
    order = jnp.argsort(w, axis=-1)
    w = jnp.take_along_axis(w, order, axis=-1)
    v = jnp.take_along_axis(v, order[:, None, :], axis=-1)
    return w.reshape(*batch, n), v.reshape(*batch, n, n)


def gram_svd(a: jnp.ndarray):
    """``(u (m, k), s (k,), vt (n, n))`` of a small ``a (m, n)``, ``k = min(m, n)``, singular
    values descending, from the eigen-decomposition of ``a^T a`` (`jacobi_eigh`).

    Like ``jnp.linalg.svd(a, full_matrices=True)`` for ``vt``, but singular values below
    ~``sqrt(eps) * s[0]`` are rounding noise (the Gram squares the conditioning): for rank
    decisions at coarser tolerances and pseudo-inverses followed by a refinement step. Columns of
    ``u`` are zero where ``s == 0``.
    """
    m, n = a.shape
    lam, v = jacobi_eigh(dot(a.T, a))
    order = jnp.argsort(-lam)
    lam, v = lam[order], v[:, order]
    k = min(m, n)
    s = jnp.sqrt(jnp.maximum(lam[:k], 0.0))
    u = dot(a, v[:, :k]) / jnp.where(s > 0, s, 1.0)[None, :]
    return jnp.where(s[None, :] > 0, u, 0.0), s, v.T


def gram_two_pass(x: jnp.ndarray, eigh):
    """``(left (r, r), z (r, c))`` for ``x (r, c)``: its left singular vectors (columns) and the
    rows ``s_i v_i`` (singular value times right singular vector), both unordered, from two
    passes of its ``r x r`` row Gram: ``x x^T = U diag(s^2) U^T`` rotates the rows, ``y = U^T
    x``; the Gram of ``y`` (nearly diagonal) rotates them again, ``z = W^T y``, and ``left = U
    W``. The second Gram is formed from the rotated rows, so its entries err by rounding relative
    to ``s_i s_j`` rather than to ``s_0^2``: as accurate as a (backward stable) SVD of x, with no
    ``sqrt(eps)`` floor on the small singular values. ``eigh``: a symmetric eigensolver
    returning ``(values, vectors)`` (`jnp.linalg.eigh` or `jacobi_eigh`)."""
    _, u = eigh(dot(x, x.T))
    y = dot(u.T, x)
    _, w = eigh(dot(y, y.T))
    return dot(u, w), dot(w.T, y)


def small_right_svd(
    a: jnp.ndarray, two_pass_gram: bool = False, *, jacobi: bool
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``(s (n,), vt (n, n))`` of a small ``a (m, n)`` with ``m >= n``: singular values
    (descending) and right singular vectors (rows), as ``jnp.linalg.svd(a,
    full_matrices=False)[1:]``.

    `small_svd`'s (LAPACK, or one-sided Jacobi with ``jacobi``), or with ``two_pass_gram`` and
    ``jacobi`` (``n <= JACOBI_MAX_N``) the two Gram passes of `gram_two_pass` on the columns'
    ``n x n`` Gram with `jacobi_eigh`: as accurate, with no reduction over the m rows per Jacobi
    round, but more rounds. For the optimiser's BC solve (100 x 5 matrices per condition and
    joint, `compiler.interpolation.GRAM_SVD_MIN_MATRICES`).
    """
    m, n = a.shape
    if not (two_pass_gram and jacobi and m >= n and n <= JACOBI_MAX_N):
        _, s, vt = small_svd(a, full_matrices=False, jacobi=jacobi)
        return s, vt
    left, z = gram_two_pass(a.T, jacobi_eigh)
    s, order = jax.lax.top_k(jnp.sqrt(jnp.sum(z * z, axis=1)), n)
    return s, left[:, order].T
