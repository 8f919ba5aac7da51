"""The reduced problems of the movement compiler via optimisation (`compiler.optimisation`, paper
sec. 2.2): each condition's trajectory ``q(z) = q_ls + sum_jk z_jk Q_jk`` in the null space of its
boundary conditions (`reduced_problems`, `Problem`), and q, qd and qdd at the quadrature nodes of
the search objective (`search_nodes`, `node_states`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.basis import Basis, small_svd
from evojax_motion.compiler.interpolation import (
    Boundary,
    basis_functions,
    solve_boundary,
    trajectory,
)
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.settings.compiler import BC_LEAK

# Null directions moving q by less than this fraction of the joint's largest one are dropped.
DIRECTION_RTOL = 1e-5


class Problem(NamedTuple):
    """One condition's reduced problem: ``q(z) = q_ls + sum_jk z_jk Q_jk``.

    q_ls: (T, J); dirs: (J, F, T) trajectories of the free null directions, orthonormal in q
    with unit RMS (zero where masked); mask: (J, F) bool; duration: () [s]. The search objective
    reads q, qd, qdd at its M quadrature nodes (`search_nodes`), linear in z too:
    node_ls: (3, M, J) q, qd, qdd of ``q_ls``; node_dirs: (3, M, J, F) those of the directions;
    node_w: (M,) the nodes' quadrature weights (summing to 1).
    """

    q_ls: jnp.ndarray
    dirs: jnp.ndarray
    mask: jnp.ndarray
    duration: jnp.ndarray
    node_ls: jnp.ndarray
    node_dirs: jnp.ndarray
    node_w: jnp.ndarray


def search_nodes(grid: TimeGrid, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature nodes of the search objective: ``(index (M,), weights (M,))``.

    Every ``stride``-th sample and the last; trapezoid weights on those nodes (summing to 1, so
    ``int f dt = D * sum_m w_m f(s_m)``). ``stride = 1`` is the time grid's own quadrature.
    """
    t = len(grid.s)
    idx = np.unique(np.append(np.arange(0, t, stride), t - 1))
    s = np.asarray(grid.s, np.float64)[idx]
    w = np.zeros(len(idx))
    w[:-1] += 0.5 * np.diff(s)
    w[1:] += 0.5 * np.diff(s)
    return idx, w.astype(np.asarray(grid.w).dtype)


def _orthonormal_directions(null, funcs, mask):
    """One joint's null directions made orthonormal in q: ``(null (K+1, F), dirs (F, T), mask)``.

    Measured in prior units the torque optimum can lie hundreds of units away along directions
    that barely move q (a first version optimised there: SLSQP needed ~100 iterations, Newton's
    trust region ~10 just to grow). With z the RMS change of q [rad] along q-orthogonal
    directions, a trust region, Adam's step size and random starts mean the same on every joint
    and condition. Directions that do not move q (padding components) are masked out.
    """
    t = funcs.shape[1]
    dirs = jnp.where(mask[:, None], null.T @ funcs, 0.0)  # (K, T)
    # dirs = u diag(sv) vt, from the SVD of the tall dirs^T (`small_svd`: Jacobi on GPUs)
    vt_t, sv, u_t = small_svd(dirs.T, full_matrices=False)
    u, vt = u_t.T, vt_t.T
    keep = sv > DIRECTION_RTOL * sv[0]
    inv = jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0), 0.0)
    root_t = jnp.sqrt(jnp.asarray(t, funcs.dtype))
    new_null = root_t * (jnp.where(mask[None, :], null, 0.0) @ (u * inv[None, :]))
    new_dirs = jnp.where(keep[:, None], root_t * vt, 0.0)
    return new_null, new_dirs, keep


def reduced_problems(
    basis: Basis,
    boundary: Boundary,
    grid: TimeGrid,
    n_components: int,
    leak: float = BC_LEAK,
    max_free: int | None = None,
    stride: int = 1,
    interp_components: int = 0,
) -> tuple[Problem, jnp.ndarray, jnp.ndarray]:
    """The batch of reduced problems: ``(Problem (C, ...), coeffs_ls (C, J, K+1), null)``.

    ``null: (C, J, K+1, F)`` maps z to coefficient changes; z is in rad (RMS over the samples) of
    q-orthogonal directions per joint. ``max_free`` (F, static, default K): null directions kept
    per joint, those the BCs constrain least. ``stride``: the search objective's nodes
    (`search_nodes`). ``interp_components`` (static): 0, z = 0 is the minimum-norm solution of
    the binding BCs (``q_ls``, ``coeffs_ls``); else the interpolation compiler's answer with
    that many components (`interpolation_base`) where it is finite.
    """
    sol = solve_boundary(basis, boundary, grid, n_components, leak=leak)
    funcs = basis_functions(basis, n_components)  # (C, J, K+1, T)
    coeffs = sol.coeffs
    if interp_components:
        coeffs = interpolation_base(basis, boundary, grid, n_components, interp_components, coeffs)
    q_ls = trajectory(basis, coeffs)
    # Keep F columns of the null space per joint: the least constrained (the last) of those that
    # move q. A column can be free and still not move q (a zero component of a basis whose
    # neighbours span fewer than K directions); keeping it would waste a slot of z.
    f = n_components if max_free is None else max_free
    moving = jnp.linalg.norm(jnp.einsum("cjkn,cjkt->cjnt", sol.null, funcs), axis=-1)
    usable = sol.null_mask & (moving > DIRECTION_RTOL * jnp.max(moving, axis=-1, keepdims=True))
    col = jnp.arange(n_components)
    order = jnp.argsort(jnp.where(usable, -col, n_components + col), axis=-1)[..., :f]
    null, dirs, mask = jax.vmap(jax.vmap(_orthonormal_directions))(
        jnp.take_along_axis(sol.null, order[..., None, :], axis=-1),
        funcs,
        jnp.take_along_axis(sol.null_mask, order, axis=-1),
    )
    idx, w = search_nodes(grid, stride)
    c, t, j = q_ls.shape
    f = dirs.shape[2]
    d_t = jnp.moveaxis(dirs, -1, 1).reshape(c, t, j * f)  # (C, T, J F)
    node_ls = jnp.stack([q_ls, *derivatives(grid, q_ls, boundary.duration)], axis=1)
    node_dirs = jnp.stack([d_t, *derivatives(grid, d_t, boundary.duration)], axis=1)
    problem = Problem(
        q_ls=q_ls,
        dirs=dirs,
        mask=mask,
        duration=boundary.duration,
        node_ls=node_ls[:, :, idx],
        node_dirs=node_dirs[:, :, idx].reshape(c, 3, len(idx), j, f),
        node_w=jnp.broadcast_to(jnp.asarray(w, q_ls.dtype), (c, len(idx))),
    )
    return problem, coeffs, null


def interpolation_base(
    basis: Basis, boundary: Boundary, grid: TimeGrid, n_components: int, k: int, coeffs_ls
) -> jnp.ndarray:
    """Coefficients ``(C, J, K+1)`` of the point z = 0 of the reduced problems: the
    interpolation compiler's answer (eq. 1-2 with the first ``k`` components,
    `compiler.interpolation.compile_interpolation`; the others 0) where it is finite, else
    ``coeffs_ls``.

    Why not the minimum-norm solution of the binding BCs with all K: the two rules meet the
    end velocities differently. Velocity BCs that bind weakly (1 rad RMS of motion changes them
    by little more than `settings.compiler.BC_LEAK`) are met exactly by the optimisation
    compiler's rule and to ~1e-4 rad/s by the interpolation's, and that difference is a q
    difference of ~0.07 rad RMS (median; up to 1 rad) on the paper's problems: the
    interpolation was not a point of the problems, and the optimiser ended above it on 19 of
    300. The null directions are the same either way, so every point keeps the
    interpolation's BC errors (<= 2.5e-4 rad/s there).
    """
    sol = solve_boundary(basis, boundary, grid, k)
    pad = jnp.zeros((*sol.coeffs.shape[:2], n_components - k), sol.coeffs.dtype)
    interp = jnp.concatenate([sol.coeffs[..., :k], pad, sol.coeffs[..., k:]], axis=-1)
    ok = jnp.all(jnp.isfinite(interp), axis=(1, 2), keepdims=True)
    return jnp.where(ok, interp, coeffs_ls)


def problem_trajectory(problem: Problem, z: jnp.ndarray) -> jnp.ndarray:
    """``q (T, J)`` of one condition at null-space coordinates ``z (J, K)``."""
    return problem.q_ls + jnp.einsum("jk,jkt->tj", z, problem.dirs)


def fused_products() -> bool:
    """Whether the search objective forms q, qd, qdd at its nodes by elementwise products and a
    sum (accelerators) or by an einsum (CPU, where `joint_lists` does not apply). Read at trace
    time.

    On 2 CPU cores the products made a paper-scale generation 4-23 % slower in an A/B
    (CHANGELOG.md). On an H100 the einsum (a product over the 2 free directions per
    joint, and in the gradient over the nodes) ran as a GEMM kernel of its own, 37 us of a 309
    us optimiser pass at 1,000 conditions; as products XLA fuses it into the dynamics' kernels.
    """
    return jax.default_backend() != "cpu"


def node_states(z, problem: Problem, joint_lists: bool = False):
    """q, qd and qdd of one condition at its M search nodes for ``z (J, F)``: ``(3, M, J)``, or
    with ``joint_lists`` three lists of J arrays ``(M,)``, each joint's formed from its own
    slices of the node arrays (`joint_lists`: on the CPU, for dynamics that read them as they
    are, `model.dynamics.Dynamics.form`).

    Why joint by joint on the CPU: the gradient then reaches z joint by joint. Sliced from one
    array, the cotangents are padded back into it, and XLA's CPU compiler emitted the RNEA's
    adjoint as one loop over that array's elements that recomputed the shared adjoint for every
    element: the value and gradient of the paper-scale batch took 9.6 ms there against 5.2 ms
    this way (2 CPU cores, 300 conditions x 26 nodes; CHANGELOG.md). For the vector
    layout, which stacks them again, lists made the float64 SLSQP reference 10 % slower.
    """
    if not joint_lists:
        if fused_products():
            return problem.node_ls + jnp.sum(z * problem.node_dirs, axis=-1)
        return problem.node_ls + jnp.einsum(
            "jf,amjf->amj", z, problem.node_dirs, precision=jax.lax.Precision.HIGHEST
        )
    ls, dirs = problem.node_ls, problem.node_dirs

    def joint(a, j):
        return ls[a, :, j] + sum(z[j, f] * dirs[a, :, j, f] for f in range(dirs.shape[-1]))

    return [[joint(a, j) for j in range(ls.shape[-1])] for a in range(3)]


def joint_lists(dyn: Dynamics) -> bool:
    """Whether the search objective hands ``dyn`` joint-by-joint node states (`node_states`): on
    the CPU, with the scalar RNEA layout. Read at trace time."""
    return not fused_products() and dyn.form == "scalar"
