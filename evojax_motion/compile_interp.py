"""Movement compiler via interpolation (paper sec. 2.1, eq. 1-2) and the boundary-condition algebra
shared with the optimisation compiler (sec. 2.2, eq. 3).

Per joint, a trajectory is the basis mean plus K weighted principal components plus a constant:

    q(s) = q_mean(s) + sum_{i=1..K} x_i q_pc_i(s) + x_{K+1}                   (eq. 1: K = 3; eq. 3: 4)

and the boundary conditions (eq. 2) ``q(0) = q0, q(1) = qf, qd(0) = qd0, qd(1) = qdf`` are four
linear equations ``A x = b`` in the K + 1 unknowns. The velocity rows use the time grid's derivative
operator, ``qd = (d1 @ q) / D``; they are multiplied by the duration D so that every row is in
radians and the rows are comparable.

Solving. The unknowns are scaled to prior units before solving: component i by the standard
deviation of the neighbours' coefficients along it (``sqrt(Basis.variance)``), the constant by the
neighbours' RMS spread per sample. The minimum-norm solution in these units is then the most likely
trajectory under the basis' Gaussian model (the conditional mean given the BCs), which stays closest
to the demonstrations. ``A`` is solved by an SVD pseudo-inverse with the relative rank tolerance
`RANK_RTOL`: exact when the system is solvable, least squares of minimum norm when it is degenerate.
Degenerate is common: primitives that all start and end at rest have components with vanishing end
velocities, so the two velocity rows carry only finite-difference noise (O(h^4), see
``timegrid``) and are dropped rather than fitted with huge coefficients.

The same SVD also yields the null space of ``A``: ``x = x_ls + N z`` satisfies the BCs for every z,
so the optimisation compiler moves in z (static shapes: N always has K columns, masked by
``null_mask``, since the constant's column makes the rank at least 1).

Example::

    basis = pca_basis(db.q, db.duration, neighbours, n_components=3)
    out = compile_interpolation(basis, Boundary(q0, qf, qd0, qdf, duration), make_time_grid(T))
    out.q            # (C, T, J) trajectories meeting the BCs; out.bc_residual (C,) says how well
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.basis import Basis
from evojax_motion.errors import UserError
from evojax_motion.timegrid import TimeGrid

# Singular values of the scaled BC matrix below RANK_RTOL * (largest) count as zero. The velocity
# rows of rest-to-rest bases sit at ~1e-6 (T = 100) .. 1e-2 (T = 16) of the position rows (the
# finite-difference error of a zero end slope); genuinely solvable systems have condition numbers
# of ~10..2000 (PROBES.md). 1e-3 keeps the latter and, from T ~ 24 samples up, drops the former.
RANK_RTOL = 1e-3
# Floor of the constant's prior scale [rad], so that a joint no neighbour moves keeps a usable
# constant (its column would otherwise be zero and no BC could be met).
MIN_CONSTANT_SCALE = 1e-3


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
    components and the constant; null: (C, J, K+1, K) coefficient directions that leave
    ``A x`` unchanged (columns zero where ``null_mask`` is False); null_mask: (C, J, K);
    rank: (C, J) int32 numerical rank of the 4 x (K+1) BC matrix.
    Any ``coeffs + null @ z`` meets the BCs as well as ``coeffs`` does.
    """

    coeffs: jnp.ndarray
    null: jnp.ndarray
    null_mask: jnp.ndarray
    rank: jnp.ndarray


class Interpolated(NamedTuple):
    """Result of `compile_interpolation` for C conditions.

    q: (C, T, J) [rad]; coeffs: (C, J, K+1) weights of the K components and the constant;
    bc_residual: (C,) max over joints of the BC errors of q (|q| in rad, |qd| in rad/s);
    rank: (C, J) numerical rank of each joint's BC system (4 = fully determined with K >= 3).
    """

    q: jnp.ndarray
    coeffs: jnp.ndarray
    bc_residual: jnp.ndarray
    rank: jnp.ndarray


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
    """Eq. 1/3: ``q = mean + sum_i x_i pc_i + x_{K+1}``. ``coeffs: (C, J, K+1)`` -> ``(C, T, J)``."""
    funcs = basis_functions(basis, coeffs.shape[2] - 1)
    return basis.mean + jnp.einsum("cjk,cjkt->ctj", coeffs, funcs)


def _joint_system(funcs, mean, scale, q0, qf, qd0, qdf, duration, d1_ends, rank_rtol):
    """One joint's BC solve. ``funcs (K+1, T)``, ``mean (T,)``, ``scale (K+1,)``, ``d1_ends (2, T)``.

    Returns ``coeffs (K+1,)``, ``null (K+1, K)``, ``null_mask (K,)``, ``rank ()``.
    """
    n = funcs.shape[0]
    rows = jnp.stack([funcs[:, 0], funcs[:, -1], d1_ends[0] @ funcs.T, d1_ends[1] @ funcs.T])
    a = rows * scale[None, :]  # (4, K+1) in prior units
    b = jnp.stack(
        [
            q0 - mean[0],
            qf - mean[-1],
            duration * qd0 - d1_ends[0] @ mean,
            duration * qdf - d1_ends[1] @ mean,
        ]
    )
    u, sv, vt = jnp.linalg.svd(a, full_matrices=True)  # vt: (K+1, K+1)
    keep = sv > rank_rtol * sv[0]
    inv = jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0), 0.0)
    m = sv.shape[0]

    def pinv(r):
        return vt[:m].T @ (inv * (u[:, :m].T @ r))

    x = pinv(b)
    x = x + pinv(b - a @ x)  # one refinement step: float32 SVD error ~ eps * cond -> ~ eps
    rank = jnp.sum(keep).astype(jnp.int32)
    # Rows of vt past the rank span the null space; the constant's column gives rank >= 1, so the
    # last K rows always contain it (static shape), masked by index.
    null_mask = jnp.arange(1, n) >= rank
    null = jnp.where(null_mask[None, :], vt[1:].T, 0.0)
    return x * scale, null * scale[:, None], null_mask, rank


def solve_boundary(
    basis: Basis,
    boundary: Boundary,
    grid: TimeGrid,
    n_components: int,
    rank_rtol: float = RANK_RTOL,
) -> BCSolution:
    """Minimum-norm BC coefficients and the BC null space for every condition and joint.

    ``basis`` holds at least ``n_components`` components; shapes as in `Boundary`. Pure, jittable;
    used by both compilers.
    """
    funcs = basis_functions(basis, n_components)  # (C, J, K+1, T)
    scale = coefficient_scale(basis, n_components)  # (C, J, K+1)
    dtype = funcs.dtype
    d1_ends = jnp.asarray(np.asarray(grid.d1)[[0, -1]], dtype)
    mean = jnp.transpose(basis.mean, (0, 2, 1))  # (C, J, T)
    joint = jax.vmap(_joint_system, in_axes=(0, 0, 0, 0, 0, 0, 0, None, None, None))
    cond = jax.vmap(joint, in_axes=(0, 0, 0, 0, 0, 0, 0, 0, None, None))
    coeffs, null, null_mask, rank = cond(
        funcs,
        mean,
        scale,
        boundary.q0.astype(dtype),
        boundary.qf.astype(dtype),
        boundary.qd0.astype(dtype),
        boundary.qdf.astype(dtype),
        boundary.duration.astype(dtype),
        d1_ends,
        rank_rtol,
    )
    return BCSolution(coeffs=coeffs, null=null, null_mask=null_mask, rank=rank)


def boundary_residual(grid: TimeGrid, q: jnp.ndarray, boundary: Boundary) -> jnp.ndarray:
    """Max over joints of the BC errors of ``q (C, T, J)``: ``(C,)`` (rad for q, rad/s for qd).

    NaN anywhere gives NaN (so ``residual <= tol`` rejects it).
    """
    # The derivative rows annihilate constants; differencing against the end sample first keeps
    # float32 rounding of |q| out of the velocity (the stencil amplifies it by ~10 / h).
    d1 = jnp.asarray(np.asarray(grid.d1)[[0, -1]], q.dtype)
    qd0 = jnp.einsum("t,ctj->cj", d1[0], q - q[:, :1]) / boundary.duration[:, None]
    qdf = jnp.einsum("t,ctj->cj", d1[1], q - q[:, -1:]) / boundary.duration[:, None]
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
    q = trajectory(basis, sol.coeffs)
    return Interpolated(
        q=q,
        coeffs=sol.coeffs,
        bc_residual=boundary_residual(grid, q, boundary),
        rank=sol.rank,
    )


def validate_boundary(
    boundary: Boundary,
    n_joints: int,
    lower=None,
    upper=None,
    where: str = "boundary",
) -> Boundary:
    """Check a user's boundary conditions at the API edge; returns them as float32 numpy arrays.

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
    return Boundary(**{k: v.astype(np.float32) for k, v in arrays.items()})
