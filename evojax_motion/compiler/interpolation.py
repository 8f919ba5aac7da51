"""Movement compiler via interpolation (paper sec. 2.1, eq. 1-2) and the boundary-condition algebra
shared with the optimisation compiler (sec. 2.2, eq. 3).

Per joint, a trajectory is the basis mean plus K weighted principal components plus a constant:

    q(s) = q_mean(s) + sum_{i=1..K} x_i q_pc_i(s) + x_{K+1}          (eq. 1: K = 3; eq. 3: K = 4)

and the boundary conditions (eq. 2) ``q(0) = q0, q(1) = qf, qd(0) = qd0, qd(1) = qdf`` are four
linear equations ``A x = b`` in the K + 1 unknowns. The velocity rows use the time grid's derivative
operator, ``qd = (d1 @ q) / D``; they are multiplied by the duration D so that every row is in
radians and the rows are comparable.

Solving. The unknowns are scaled to prior units before solving: component i by the standard
deviation of the neighbours' coefficients along it (``sqrt(Basis.variance)``), the constant by the
neighbours' RMS spread per sample. The minimum-norm solution in these units is then the most likely
trajectory under the basis' Gaussian model (the conditional mean given the BCs), which stays closest
to the demonstrations. ``A`` is solved by an SVD pseudo-inverse with the relative rank tolerance
`RANK_RTOL`: exact when the system is solvable, least squares of minimum norm when it is degenerate,
with the position rows before the velocity rows (the end postures hold whenever the basis can
reach them). Degenerate is common: primitives that all start and end at rest have components with
nearly vanishing end velocities, so the two velocity rows carry little more than finite-difference
noise (O(h^4), see ``timegrid``) and are dropped rather than fitted with huge coefficients.

Outside the demonstrations. Where a condition's end posture lies beyond its neighbours' ends
and they hardly vary there (a few trials of one person that start alike and end in a cluster),
meeting the BCs exactly takes weights of hundreds of prior standard deviations and the path
overshoots by several times the joint's move. A joint whose weights exceed `MAX_PRIOR_SIGMA`
follows its neighbours' mean motion instead, moved onto the BCs by quintic offsets
(`mean_onto_boundary`; ``Interpolated.mean_path`` says which). The paper configuration never
comes near the threshold, so its results are eq. 1-2's.

The same algebra yields the null space: ``x = x_ls + N z`` meets the BCs for every z, so the
optimisation compiler moves in z (static shapes: N always has K columns, masked by ``null_mask``;
the constant's column makes the rank at least 1). For it, which BC directions bind is decided in
q units (``solve_boundary(..., leak=BC_LEAK)``): a direction binds when 1 rad RMS of motion
changes it by more than `settings.compiler.BC_LEAK`; the solution is still the prior minimum-norm
one.

Example::

    basis = pca_basis(db.q, db.duration, neighbours, n_components=3)
    out = compile_interpolation(basis, Boundary(q0, qf, qd0, qdf, duration), make_time_grid(T))
    out.q            # (C, T, J) trajectories meeting the BCs; out.bc_residual (C,) says how well
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.basis import Basis, jacobi_backend, small_right_svd, small_svd
from evojax_motion.errors import UserError
from evojax_motion.linalg import lapack
from evojax_motion.linalg.jacobi import gram_svd
from evojax_motion.motion import profiles
from evojax_motion.motion.timegrid import TimeGrid

# Singular values of the scaled BC matrix below RANK_RTOL * (largest) count as zero (interpolation
# default). Bases of rest-to-rest primitives have velocity rows at ~1e-6 (minimum jerk, T = 100) ..
# 1e-2 (T = 16, or demonstrations whose ends are only nearly at rest) of the position rows; fitting
# them exactly takes large coefficients far from the demonstrations. On the synthetic catching
# demonstrations (leave-one-out, 100 held out, T = 100, K = 3) 1e-2 reproduced held-out motions with
# 0.78 deg median RMS error against 0.81 deg at 1e-3 and 1.5 deg at 1e-4, leaving end-velocity
# errors below 1e-3 rad/s. The optimisation compiler decides in q units instead
# (`settings.compiler.BC_LEAK`): in prior units a direction can look degenerate and still move the
# end velocities by 0.2 .. 0.6 rad/s per rad of motion.
RANK_RTOL = 1e-2
# Relative tolerance at float32 noise level (SVD error ~1e-7 relative): systems solvable at this
# level are solved exactly.
STRICT_RANK_RTOL = 1e-5
# From this many BC systems (conditions x joints) in one solve, the optimisation compiler's rule
# finds each basis' q-orthonormal coordinates by `compiler.basis.small_right_svd`'s two Gram passes
# instead
# of the one-sided Jacobi SVD, on accelerators. One H100, paper configuration, the generation at
# 10,000 / 30,000 / 100,000 conditions (70,000+ systems): 9.5 / 8.3 / 9 % faster; at 1,000
# (7,000 systems) 7 % slower, its Jacobi rounds being more kernels there (CHANGELOG.md; between
# the two sizes not measured).
GRAM_SVD_MIN_MATRICES = 65_536
# Floor of the constant's prior scale [rad], so that a joint no neighbour moves keeps a usable
# constant (its column would otherwise be zero and no BC could be met).
MIN_CONSTANT_SCALE = 1e-3
# A joint whose eq. 1-2 coefficients lie beyond this many prior standard deviations
# (`coefficient_scale`) has left what its demonstrations span: it follows their mean motion
# moved onto its BCs instead (`mean_onto_boundary`). The paper configuration's 300 conditions
# reach 7.9 at most (median 0.27, 99th percentile 4.8); recorded reaches, whose few trials of
# one person end alike and not quite at rest, reach hundreds to thousands, with paths spanning
# up to 31 times the joint's move (CHANGELOG.md).
MAX_PRIOR_SIGMA = 10.0


class Boundary(NamedTuple):
    """Boundary conditions of eq. 2 for C conditions.

    q0, qf: (C, J) start and end joint angles [rad]; qd0, qdf: (C, J) start and end joint
    velocities [rad/s]; duration: (C,) motion duration D [s].
    """

    q0: jnp.ndarray
    qf: jnp.ndarray
    qd0: jnp.ndarray
    qdf: jnp.ndarray
    duration: jnp.ndarray


class BCSolution(NamedTuple):
    """The affine set of coefficients that meet the BCs, per condition and joint.

    coeffs: (C, J, K+1) minimum-norm (in prior units) coefficients [rad] of the K unit-norm
    components and the constant; null: (C, J, K+1, K) coefficient directions that leave the
    binding BCs unchanged (columns zero where ``null_mask`` is False), scaled to prior units
    (interpolation rule) or to unit RMS of q (``leak`` rule); null_mask: (C, J, K);
    rank: (C, J) int32 number of binding BC directions (of 4).
    Any ``coeffs + null @ z`` meets the binding BCs as well as ``coeffs`` does. With the
    interpolation rule the null directions may still move the end velocities noticeably (see
    `RANK_RTOL`); use ``leak`` (`settings.compiler.BC_LEAK`) to move without disturbing the BCs.
    """

    coeffs: jnp.ndarray
    null: jnp.ndarray
    null_mask: jnp.ndarray
    rank: jnp.ndarray


class Interpolated(NamedTuple):
    """Result of `compile_interpolation` for C conditions.

    q: (C, T, J) [rad]; coeffs: (C, J, K+1) eq. 1's weights of the K components and the
    constant; bc_residual: (C,) max over joints of the BC errors of q (|q| in rad, |qd| in
    rad/s); rank: (C, J) numerical rank of each joint's BC system (4 = fully determined with
    K >= 3); mean_path: (C, J) the joint's eq. 1 weights were beyond `MAX_PRIOR_SIGMA` (or not
    finite) and its q is `mean_onto_boundary`'s instead.
    """

    q: jnp.ndarray
    coeffs: jnp.ndarray
    bc_residual: jnp.ndarray
    rank: jnp.ndarray
    mean_path: jnp.ndarray


def basis_functions(basis: Basis, n_components: int) -> jnp.ndarray:
    """The first K components and the constant as trajectories: ``(C, J, K+1, T)``."""
    if basis.components.shape[1] < n_components:
        raise ValueError(
            f"n_components: expected <= {basis.components.shape[1]} (the basis' size), "
            f"got {n_components}"
        )
    pcs = jnp.transpose(basis.components[:, :n_components], (0, 3, 1, 2))  # (C, J, K, T)
    ones = jnp.ones((*pcs.shape[:2], 1, pcs.shape[3]), pcs.dtype)
    return jnp.concatenate([pcs, ones], axis=2)


def coefficient_scale(basis: Basis, n_components: int) -> jnp.ndarray:
    """Prior scale of each unknown [rad]: ``(C, J, K+1)`` (see the module docstring).

    Components: the standard deviation of the neighbours along them (0 for padding components);
    constant: the neighbours' RMS standard deviation per sample, ``sqrt(sum_i var_i / T)``.
    """
    var = jnp.transpose(basis.variance[:, :n_components], (0, 2, 1))  # (C, J, K)
    t = basis.components.shape[2]
    const = jnp.sqrt(jnp.sum(jnp.transpose(basis.variance, (0, 2, 1)), axis=2) / t)
    const = jnp.maximum(const, MIN_CONSTANT_SCALE)
    return jnp.concatenate([jnp.sqrt(var), const[..., None]], axis=2)


def trajectory(basis: Basis, coeffs: jnp.ndarray) -> jnp.ndarray:
    """Eq. 1/3, ``q = mean + sum_i x_i pc_i + x_{K+1}``: ``coeffs (C, J, K+1)`` -> ``(C, T, J)``."""
    funcs = basis_functions(basis, coeffs.shape[2] - 1)
    return basis.mean + jnp.einsum("cjk,cjkt->ctj", coeffs, funcs)


def _svd(a, jacobi: bool):
    """``(u, s (k,), vt (n, n))`` of a small ``a (m, n)``, ``k = min(m, n)``: LAPACK, or
    with ``jacobi`` the elementwise `basis.gram_svd` (accelerators; exact enough for `RANK_RTOL`,
    its pseudo-inverse error is removed by the refinement step of `_joint_system`)."""
    if jacobi:
        return gram_svd(a)
    return lapack.svd(a, full_matrices=True)


def _pinv(a, rtol, ref=None, jacobi: bool = False, svd=None):
    """``r -> a^+ r`` with singular values below ``rtol * ref`` dropped (``ref`` None: the largest
    of ``a``'s own, its 2-norm); also the kept count.

    ``svd``: ``a``'s SVD where the caller has it (`_svd`'s); else by `basis.gram_svd` with
    ``jacobi``, or `compiler.basis.small_svd` (LAPACK on CPU)."""
    if svd is None:
        svd = gram_svd(a) if jacobi else small_svd(a, full_matrices=False)
    u, sv, vt = svd
    k = sv.shape[0]
    u, vt = u[:, :k], vt[:k]
    keep = sv > rtol * (sv[0] if ref is None else ref)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0), 0.0)
    return (lambda r: vt.T @ (inv * (u.T @ r))), jnp.sum(keep).astype(jnp.int32)


def end_slopes(d1_ends, f):
    """``(2, ...)``: the first and last rows ``d1_ends (2, T)`` of the derivative operator applied
    to ``f (..., T)`` (slopes per unit of normalised time, not yet divided by the duration).

    The rows sum to zero, so differencing ``f`` against its first and last sample first changes
    nothing in exact arithmetic; in float32 it keeps the rounding of |f| (amplified ~1,000x by the
    one-sided stencil at T = 100) out of slopes that are compared with thresholds ~1e-4
    (`settings.compiler.BC_LEAK`). Without it, paper-scale BC solves in float32 missed float64's
    by up to 0.3 rad in q (CPU) and 0.8 rad (H100), and the GPU and the CPU set up different
    problems.
    """
    hi = jax.lax.Precision.HIGHEST
    return jnp.stack(
        [
            jnp.matmul(f - f[..., :1], d1_ends[0], precision=hi),
            jnp.matmul(f - f[..., -1:], d1_ends[1], precision=hi),
        ]
    )


def _bc_rows(d1_ends, f):
    """The four BC rows (start and end value, start and end slope per unit of normalised time)
    of functions ``f (n, T)``: ``(4, n)``."""
    return jnp.concatenate([jnp.stack([f[:, 0], f[:, -1]]), end_slopes(d1_ends, f)])


def _bc_gap(d1_ends, mean, q0, qf, qd0, qdf, duration):
    """``(4,)``: what one joint's BCs ask beyond its mean trajectory ``mean (T,)``, in the units
    of `_bc_rows` (slopes times the duration)."""
    return jnp.concatenate(
        [
            jnp.stack([q0 - mean[0], qf - mean[-1]]),
            duration * jnp.stack([qd0, qdf]) - end_slopes(d1_ends, mean),
        ]
    )


def _joint_system(
    funcs, mean, scale, q0, qf, qd0, qdf, duration, d1_ends, rank_rtol, leak, jacobi=False,
    two_pass_gram=False,
):  # fmt: skip
    """One joint's BC solve. ``funcs (K+1, T)``, ``mean (T,)``, ``scale (K+1,)``,
    ``d1_ends (2, T)`` (the first and last rows of the derivative operator).

    ``leak`` None: interpolation (rank in prior units, positions before velocities); else the
    optimisation compiler's rule (module docstring); ``jacobi``: the interpolation rule's SVDs by
    `basis.gram_svd` (see `_svd`); ``two_pass_gram``: the optimisation rule's coordinates by
    `compiler.basis.small_right_svd`'s two Gram passes (`GRAM_SVD_MIN_MATRICES`). Returns ``coeffs
    (K+1,)``, ``null (K+1, K)``, ``null_mask (K,)``, ``rank ()``.
    """
    n, t = funcs.shape
    rows = _bc_rows(d1_ends, funcs)
    b = _bc_gap(d1_ends, mean, q0, qf, qd0, qdf, duration)
    a = rows * scale[None, :]  # (4, K+1) in prior units
    if leak is None:
        # Positions first, then velocities in what freedom is left (a prioritised minimum-norm
        # least squares): a degenerate velocity row then costs nothing in the end postures. Where
        # all four rows are solvable this is the plain pseudo-inverse solution.
        ap, av = a[:2], a[2:]
        up, sp, vpt = _svd(ap, jacobi)  # vpt: (K+1, K+1)
        pos_solve, rank_p = _pinv(ap, rank_rtol, svd=(up, sp, vpt))
        # Null space of the position rows; the constant's column gives rank >= 1 (static K).
        pos_null = jnp.where((jnp.arange(1, n) >= rank_p)[None, :], vpt[1:].T, 0.0)  # (K+1, K)
        av_null = av @ pos_null
        vel_solve, rank_v = _pinv(av_null, rank_rtol, sp[0], jacobi)

        def solve(r):
            x = pos_solve(r[:2])
            return x + pos_null @ vel_solve(r[2:] - av @ x)

        rank = rank_p + rank_v
        # The null space of all four rows at the same tolerance: rows of vt past the rank.
        _, sv, vt = _svd(a, jacobi)
        rank_all = jnp.sum(sv > rank_rtol * sv[0])
        null_mask = jnp.arange(1, n) >= rank_all
        null = jnp.where(null_mask[None, :], vt[1:].T * scale[:, None], 0.0)
    else:
        # Which BC directions bind is a physical question: in coordinates y of the basis' span
        # that are orthonormal in q (|y| = RMS of the q change over the samples), a direction
        # binds when moving q by 1 rad RMS changes its BC by more than `leak`. Which solution
        # among those is a prior one: the minimum norm in prior units, as for interpolation.
        # No solver call per matrix on accelerators (`small_right_svd`, `small_svd`: Jacobi
        # rotations, as accurate as LAPACK's SVD; ``two_pass_gram``: `GRAM_SVD_MIN_MATRICES`).
        sg, wt = small_right_svd(funcs.T / jnp.sqrt(jnp.asarray(t, funcs.dtype)), two_pass_gram)
        span = sg > STRICT_RANK_RTOL * sg[0]
        to_c = wt.T * jnp.where(span, 1.0 / jnp.where(span, sg, 1.0), 0.0)[None, :]  # c = to_c y
        u, sq, vt = small_svd(rows @ to_c, full_matrices=True)
        binding = sq > leak
        rank = jnp.sum(binding).astype(jnp.int32)
        m = sq.shape[0]
        proj = jnp.where(binding[:, None], u[:, :m].T, 0.0)  # the binding combinations of rows
        solve_bound, _ = _pinv(proj @ a, STRICT_RANK_RTOL)

        def solve(r):
            return solve_bound(proj @ r)

        null_mask = jnp.arange(1, n) >= rank
        null = jnp.where(null_mask[None, :], to_c @ vt[1:].T, 0.0)

    x = solve(b)
    x = x + solve(b - a @ x)  # one refinement step: float32 SVD error ~ eps * cond -> ~ eps
    return x * scale, null, null_mask, rank


def solve_boundary(
    basis: Basis,
    boundary: Boundary,
    grid: TimeGrid,
    n_components: int,
    rank_rtol: float = RANK_RTOL,
    leak: float | None = None,
) -> BCSolution:
    """Minimum-norm BC coefficients and the BC null space for every condition and joint.

    ``basis`` holds at least ``n_components`` components; shapes as in `Boundary`. ``leak`` None:
    the interpolation rule (``rank_rtol`` in prior units); a number: the optimisation compiler's
    rule (module docstring). Pure, jittable; used by both compilers.
    """
    funcs = basis_functions(basis, n_components)  # (C, J, K+1, T)
    scale = coefficient_scale(basis, n_components)  # (C, J, K+1)
    dtype = funcs.dtype
    d1_ends = jnp.asarray(np.asarray(grid.d1)[[0, -1]], dtype)
    mean = jnp.transpose(basis.mean, (0, 2, 1))  # (C, J, T)
    system = functools.partial(
        _joint_system,
        d1_ends=d1_ends,
        rank_rtol=rank_rtol,
        leak=leak,
        jacobi=leak is None and jacobi_backend(),
        two_pass_gram=funcs.shape[0] * funcs.shape[1] >= GRAM_SVD_MIN_MATRICES,
    )
    coeffs, null, null_mask, rank = jax.vmap(jax.vmap(system))(
        funcs,
        mean,
        scale,
        boundary.q0.astype(dtype),
        boundary.qf.astype(dtype),
        boundary.qd0.astype(dtype),
        boundary.qdf.astype(dtype),
        jnp.broadcast_to(boundary.duration.astype(dtype)[:, None], boundary.q0.shape),
    )
    return BCSolution(coeffs=coeffs, null=null, null_mask=null_mask, rank=rank)


def boundary_residual(grid: TimeGrid, q: jnp.ndarray, boundary: Boundary) -> jnp.ndarray:
    """Max over joints of the BC errors of ``q (C, T, J)``: ``(C,)`` (rad for q, rad/s for qd).

    NaN anywhere gives NaN (so ``residual <= tol`` rejects it).
    """
    d1 = jnp.asarray(np.asarray(grid.d1)[[0, -1]], q.dtype)
    qd0, qdf = end_slopes(d1, jnp.swapaxes(q, 1, 2)) / boundary.duration[:, None]
    err = jnp.stack(
        [q[:, 0] - boundary.q0, q[:, -1] - boundary.qf, qd0 - boundary.qd0, qdf - boundary.qdf]
    )
    bad = ~jnp.all(jnp.isfinite(err), axis=(0, 2)) | ~jnp.all(jnp.isfinite(q), axis=(1, 2))
    return jnp.where(bad, jnp.nan, jnp.max(jnp.abs(err), axis=(0, 2)))


def compile_interpolation(
    basis: Basis,
    boundary: Boundary,
    grid: TimeGrid,
    n_components: int = 3,
    rank_rtol: float = RANK_RTOL,
) -> Interpolated:
    """The movement compiler via interpolation (paper sec. 2.1): eq. 1 under the BCs of eq. 2.

    ``basis`` (C conditions, >= ``n_components`` components, e.g. from `pca_basis`),
    ``boundary`` (C conditions), ``grid`` the time grid of the basis' T samples.
    Returns `Interpolated` (``q (C, T, J)``, ``coeffs (C, J, K+1)``, ``bc_residual (C,)``,
    ``rank (C, J)``). Pure; jit it with ``n_components`` and ``grid`` closed over, e.g.
    ``jax.jit(lambda b, bc: compile_interpolation(b, bc, grid))``. No optimisation: real time.
    """
    sol = solve_boundary(basis, boundary, grid, n_components, rank_rtol)
    far = outside_prior(basis, sol.coeffs)
    q = jnp.where(
        far[:, None, :], mean_onto_boundary(basis, boundary, grid), trajectory(basis, sol.coeffs)
    )
    return Interpolated(
        q=q,
        coeffs=sol.coeffs,
        bc_residual=boundary_residual(grid, q, boundary),
        rank=sol.rank,
        mean_path=far,
    )


def outside_prior(basis: Basis, coeffs: jnp.ndarray) -> jnp.ndarray:
    """``(C, J)``: a joint's weights ``coeffs (C, J, K+1)`` are beyond `MAX_PRIOR_SIGMA` prior
    standard deviations (`coefficient_scale`; an unknown of scale 0 counts by its weight's being
    nonzero), or not finite."""
    scale = coefficient_scale(basis, coeffs.shape[2] - 1)
    size = jnp.abs(coeffs) / jnp.where(scale > 0, scale, 1.0)
    size = jnp.where((scale > 0) | (coeffs != 0), size, 0.0)
    return ~(jnp.max(size, axis=2) <= MAX_PRIOR_SIGMA)  # NaN: outside


def mean_onto_boundary(basis: Basis, boundary: Boundary, grid: TimeGrid) -> jnp.ndarray:
    """The basis' mean motion moved onto the BCs: ``(C, T, J)``.

    ``q = mean + sum_e c_e h_e`` with ``h`` the quintic offsets of
    `motion.profiles.quintic_hermite` (each sets one end value or slope, zero acceleration at
    both ends), ``c`` solved on the grid's own BC rows (end samples, `end_slopes`), so the BCs
    hold as exactly as eq. 1-2's. The demonstrations' shape, without weights beyond their
    spread (`MAX_PRIOR_SIGMA`).
    """
    s = np.asarray(grid.s, np.float64)
    h = np.stack(profiles.quintic_hermite(s))  # (4, T)
    d1 = np.asarray(grid.d1, np.float64)[[0, -1]]
    rows = np.concatenate([h[:, [0, -1]].T, (h @ d1.T).T])  # `_bc_rows` in float64, inverted here
    dtype = basis.mean.dtype
    solve = jnp.asarray(np.linalg.inv(rows), dtype)
    offsets, d1_ends = jnp.asarray(h, dtype), jnp.asarray(d1, dtype)

    def joint(mean, q0, qf, qd0, qdf, duration):  # mean (T,) -> (T,)
        c = solve @ _bc_gap(d1_ends, mean, q0, qf, qd0, qdf, duration)
        return mean + c @ offsets

    mean = jnp.swapaxes(basis.mean, 1, 2)  # (C, J, T)
    dur = jnp.broadcast_to(boundary.duration.astype(dtype)[:, None], boundary.q0.shape)
    q0, qf, qd0, qdf = (
        a.astype(dtype) for a in (boundary.q0, boundary.qf, boundary.qd0, boundary.qdf)
    )
    q = jax.vmap(jax.vmap(joint))(mean, q0, qf, qd0, qdf, dur)
    return jnp.swapaxes(q, 1, 2)


def validate_boundary(
    boundary: Boundary,
    n_joints: int,
    lower=None,
    upper=None,
    where: str = "boundary",
) -> Boundary:
    """Check a user's boundary conditions at the API edge; returns them as float32 arrays.

    Shapes ``(C, J)`` with ``J = n_joints`` and ``duration (C,)``; every value finite; durations
    > 0 s; with ``lower``/``upper (J,)`` given, ``q0`` and ``qf`` inside the joint ranges.
    Raises `UserError` naming the field. (Inside a jitted batch bad entries are flagged instead.)
    """
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in boundary._asdict().items()}
    c = arrays["duration"].reshape(-1).shape[0]
    if arrays["duration"].ndim != 1:
        raise UserError(f"{where}.duration: expected shape (C,), got {arrays['duration'].shape}")
    for name in ("q0", "qf", "qd0", "qdf"):
        if arrays[name].shape != (c, n_joints):
            raise UserError(
                f"{where}.{name}: expected shape ({c}, {n_joints}), got {arrays[name].shape}"
            )
    for name, arr in arrays.items():
        if not np.isfinite(arr).all():
            raise UserError(f"{where}.{name}: expected finite values, got NaN/inf")
    if not (arrays["duration"] > 0).all():
        raise UserError(f"{where}.duration: expected durations > 0 s")
    if lower is not None and upper is not None:
        lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        for name in ("q0", "qf"):
            outside = (arrays[name] < lo) | (arrays[name] > hi)
            if outside.any():
                cond, joint = np.argwhere(outside)[0]
                raise UserError(
                    f"{where}.{name}: expected joint angles within the joint limits, "
                    f"condition {cond} joint {joint} is {arrays[name][cond, joint]:.4g} rad "
                    f"outside [{lo[joint]:.4g}, {hi[joint]:.4g}]"
                )
    return Boundary(*(jnp.asarray(arrays[k], jnp.float32) for k in Boundary._fields))
