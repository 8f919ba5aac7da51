"""Movement compiler via optimisation (paper sec. 2.2, eq. 3-5).

Per joint the trajectory is the basis mean plus K = 4 weighted principal components plus a
constant (eq. 3); the weights minimise the torque cost

    0.5 * int_0^D |tau(q, qd, qdd)|^2 dt,   tau = M(q) qdd + C(q, qd) qd + g(q)    (eq. 4-5)

subject to the boundary conditions of eq. 2. The BCs are linear in the weights, so we move in their
null space: ``x = x_ls + N z`` (`compiler.interpolation.solve_boundary` with ``leak``) meets them
after every step by construction, whatever the optimiser does. Which BC directions bind is decided
in q units (`settings.compiler.BC_LEAK`); z is the RMS change of q [rad] along q-orthonormal null
directions, at most ``max_free_per_joint`` per joint, masked (static shapes). The start z = 0 is
the prior minimum-norm BC solution, i.e. the interpolation compiler's answer with K = 4.

Joint limits (the paper discards offspring that leave them, sec. 3.1): the objective adds a smooth
quadratic penalty ``limit_penalty * int relu(q - hi)^2 + relu(lo - q)^2 dt`` on the box shrunk by
``limit_margin``, ``[lower + margin, upper - margin]``; the margin absorbs the small violation a
finite penalty leaves, and the result is checked against the true limits (``within_limits``).

Optimisers (``OptimSettings.method``), batched over conditions (and starts):
  - ``"newton"`` (default): trust-region Newton on the reduced problem with the exact Hessian
    (``jax.hessian`` in z; the problem is not convex, so the trust-region subproblem is solved
    exactly through an eigendecomposition, negative curvature included). Each iteration also tries
    1/4 and 1/16 of the step (three cheap values) before it gives up on a direction, and stops on
    the Newton decrement (``tol``) or the budget. ``hessian_every > 1`` refreshes the Hessian
    only every so many iterations, with damped BFGS updates in between.
  - ``"bfgs"``: the same trust-region loop with a quasi-Newton model instead of the Hessian (no
    second derivatives of the dynamics: ~10x cheaper per iteration on a CPU): the limit
    penalty's exact Hessian (`penalty_model`) plus a damped-BFGS model of the torque cost,
    started from its Gauss-Newton matrix (``initial_model``, `gauss_newton_model`). The model
    is positive definite, so the step minimises it on the plane of the gradient and the Newton
    step (`solvers.steps.subspace_step`; Nocedal & Wright, sec. 4.1; the Newton step by
    `linalg.cholesky.cholesky_solve`): no eigendecomposition (on GPUs a cuSOLVER call per
    iteration, 22 % of an iteration at 1,000 conditions on an H100).
  - ``"adam"``: plain ``optax.adam`` in z for ``max_iters`` steps (the paper's projected-gradient
    baseline, kept for comparison).
  - ``"lbfgs"``: ``optax.lbfgs`` with its zoom line search, stopped on the gradient norm.
With ``n_starts > 1`` the optimiser also starts from random z (``start_scale`` rad RMS) and keeps
the best result that is finite and within limits. The solvers themselves (`solvers`) know nothing
of trajectories: this module sets up the reduced problems and their objective, hands them to one,
and checks its results against the limits.

Measured (``benchmarks/optimality.py``, 100 conditions of the default synthetic database, T = 100,
2 shared CPU cores; gap = (ours - SLSQP) / SLSQP on the float64 cost, same problem and start):

| method | median gap | p95 gap | max gap | run [s] |
|---|---|---|---|---|
| newton (default, 25 iterations) | -0.006 % | 0.71 % | 12.5 % | 33 |
| newton, 2 starts | -0.007 % | 0.34 % | 2.3 % | 67 |
| newton, 4 starts | -0.008 % | 0.001 % | 0.71 % | 218 |
| bfgs (100 iterations; later runs, below) | -0.007 % | 0.089 % | 9.7 % | 0.5 |
| adam, 200 steps, lr 0.1 | 0.19 % | 3.2 % | 6.0 % | 9 |
| adam, 1000 steps, lr 0.03 | -0.002 % | 0.64 % | 8.7 % | 41 |
| lbfgs (optax, 60 iterations) | -0.003 % | 0.53 % | 12.5 % | 118 |

The bfgs row: ``optimality_cpu_bfgs.json`` (``--variants bfgs``; BFGS keeps its model through a
rejected step: restarting it there gave median -0.003 %, p95 2.5 %, max 12.5 %).
The paper config (``search_stride: 4``, ``max_free_per_joint: 2``) in a later run of the same
benchmark (``results/optimality_cpu_fast.json``): median -0.0015 %, p95 0.22 %, max 3.0 %, 15 s
where the default took 82 s in that run.

Example::

    compile = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, OptimSettings())
    out = compile(basis, boundary)      # basis: >= 4 components; one jit, vmap over conditions
    out.q, out.cost, out.within_limits  # (C, T, J), (C,), (C,)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.basis import Basis, small_eigh, small_svd
from evojax_motion.compiler.interpolation import (
    Boundary,
    basis_functions,
    boundary_residual,
    solve_boundary,
    trajectory,
)
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.linalg.reductions import sum_together
from evojax_motion.model.dynamics import Dynamics, unfused_cpu_program
from evojax_motion.motion.objective import cost_from_torques
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.settings.compiler import BC_LEAK, OptimSettings
from evojax_motion.solvers.base import Descent, HessianModel, SolverResult
from evojax_motion.solvers.chunking import in_chunks, optimise_in_chunks
from evojax_motion.solvers.quasi_newton import (
    ExactHessian,
    StructuredBFGS,
    gauss_newton_matrix,
)
from evojax_motion.solvers.steps import ExactStep, SubspaceStep
from evojax_motion.solvers.trust_region import trust_region

# Samples may exceed a joint limit by this much [rad] and still count as within it: float32
# rounding of a BC that sits exactly on a limit.
LIMIT_TOL = 1e-5
# Null directions moving q by less than this fraction of the joint's largest one are dropped.
DIRECTION_RTOL = 1e-5
# BFGS's first model of the torque cost (``initial_model="gauss-newton"``): the Gauss-Newton
# matrix on every GN_NODE_STRIDE-th search node (plus a ridge, `quasi_newton.INITIAL_RIDGE`).
# Paper configuration, 100 conditions, 2 CPU cores (CHANGELOG.md): strides 1, 2, 3
# and 5 took 20, 20, 18 and 21.5 iterations (median); strides 1 and 3 cost 74 and 25 ms per 300
# conditions.
GN_NODE_STRIDE = 3


class Optimised(NamedTuple):
    """Result of the optimisation compiler for C conditions.

    q: (C, T, J) [rad]; coeffs: (C, J, K+1) weights of the K components and the constant;
    cost: (C,) eq. 5 torque cost of q (no penalty) [N^2 m^2 s]; bc_residual: (C,) max BC error
    (rad, rad/s); within_limits: (C,) every sample inside [lower, upper] (+`LIMIT_TOL`; an
    infinite limit is never violated); finite: (C,) q and cost are finite; iterations: (C,) int32
    iterations used (of the chosen start); converged: (C,) stopping test met within the budget;
    peak_torque [N m], peak_velocity [rad/s]: (C, J) largest |tau| and |qd| over the T samples
    (the torques of ``cost``).
    """

    q: jnp.ndarray
    coeffs: jnp.ndarray
    cost: jnp.ndarray
    bc_residual: jnp.ndarray
    within_limits: jnp.ndarray
    finite: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray
    peak_torque: jnp.ndarray
    peak_velocity: jnp.ndarray


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


class Prepared(NamedTuple):
    """A batch of C conditions made ready for the optimiser (`prepare_optimisation`): its B =
    ``n_starts * C`` problems (start-major) and what the optimiser starts from.

    problems: `Problem` with ``(B, ...)`` arrays; z0, free: ``(B, J F)`` the start and the free
    directions (bool); coeffs_ls: ``(C, J, K+1)`` the BC solution at z = 0; null: ``(C, J, K+1,
    F)`` its free directions in the weights; initial: ``(B, J F, J F)`` BFGS's first model of
    the torque cost (`gauss_newton_model` at z0), or None (other methods, or ``initial_model:
    identity``).
    """

    problems: Problem
    z0: jnp.ndarray
    free: jnp.ndarray
    coeffs_ls: jnp.ndarray
    null: jnp.ndarray
    initial: jnp.ndarray | None


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
) -> tuple[Problem, jnp.ndarray, jnp.ndarray]:
    """The batch of reduced problems: ``(Problem (C, ...), coeffs_ls (C, J, K+1), null)``.

    ``null: (C, J, K+1, F)`` maps z to coefficient changes; z is in rad (RMS over the samples) of
    q-orthogonal directions per joint. ``max_free`` (F, static, default K): null directions kept
    per joint, those the BCs constrain least. ``stride``: the search objective's nodes
    (`search_nodes`).
    """
    sol = solve_boundary(basis, boundary, grid, n_components, leak=leak)
    funcs = basis_functions(basis, n_components)  # (C, J, K+1, T)
    q_ls = trajectory(basis, sol.coeffs)
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
    return problem, sol.coeffs, null


def problem_trajectory(problem: Problem, z: jnp.ndarray) -> jnp.ndarray:
    """``q (T, J)`` of one condition at null-space coordinates ``z (J, K)``."""
    return problem.q_ls + jnp.einsum("jk,jkt->tj", z, problem.dirs)


def squared_violation(q, lo, hi):
    """``relu(q - hi)^2 + relu(lo - q)^2``, elementwise (arrays or scalars)."""
    return jnp.maximum(q - hi, 0.0) ** 2 + jnp.maximum(lo - q, 0.0) ** 2


def limit_penalty(w, q, duration, lo, hi, weight) -> jnp.ndarray:
    """``weight * int relu(q - hi)^2 + relu(lo - q)^2 dt`` for ``q (M, J)`` at nodes with
    quadrature weights ``w (M,)``: a scalar."""
    viol = squared_violation(q, lo, hi)
    return weight * duration * jnp.sum(jnp.asarray(w, q.dtype) * jnp.sum(viol, axis=-1))


def rate_bound(limit, margin: float, dtype) -> jnp.ndarray | None:
    """A velocity or torque penalty's bound ``(J,)`` [rad/s or N m]: ``limit (J,)`` (inf: none)
    less the fraction ``margin`` of it, or None (no penalty) when every joint's is inf."""
    if limit is None or not np.isfinite(np.asarray(limit)).any():
        return None
    return jnp.asarray((1.0 - margin) * np.asarray(limit, np.float64), dtype)


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


def penalty_model(z, problems: Problem, lo, hi, weight, vmax=None):
    """Gradient ``(B, J F)`` and Hessian ``(B, J F, J F)`` of `limit_penalty` at the search
    nodes for a batch of problems at ``z (B, J F)``, in closed form (q and qd are linear in z,
    the penalty a sum of squared violations): per joint, ``2 weight D sum_m w_m v_m d_m`` and
    ``2 weight D sum_m w_m [q_m outside] d_m d_m^T``, ``d_m (F,)`` the joint's directions at
    node m, ``v_m`` its signed violation; joints do not mix (block diagonal). With ``vmax (J,)``
    the same for the velocity penalty on ``[-vmax, vmax]`` (`rate_bound`), qd's
    directions in place of q's. The BFGS method's exact part of its model
    (`solvers.quasi_newton.StructuredBFGS`'s ``known``).

    Elementwise products summed over the nodes in one reduction (`sum_together`): as einsums,
    on 2 CPU cores, the Hessian's blocks alone were a dot of ~0.35 ms a pass at paper scale (in
    a profiler trace), the whole model 800 against 257 us a call now."""
    b, _, _, j, f = problems.node_dirs.shape
    zf = z.reshape(b, 1, j, f)
    c = ((2.0 * weight * problems.duration)[:, None] * problems.node_w)[:, :, None]  # (B, M, 1)
    pairs = [(k, m) for k in range(f) for m in range(k, f)]
    bounds = [(0, lo, hi)] if vmax is None else [(0, lo, hi), (1, -vmax, vmax)]
    terms: list[list[jnp.ndarray]] = [[] for _ in range(f + len(pairs))]
    for order, low, high in bounds:
        dirs = problems.node_dirs[:, order]  # (B, M, J, F)
        x = problems.node_ls[:, order] + sum(zf[..., k] * dirs[..., k] for k in range(f))
        viol = jnp.maximum(x - high, 0.0) - jnp.maximum(low - x, 0.0)  # (B, M, J)
        c_outside = jnp.where(viol != 0.0, c, 0.0)
        for k in range(f):
            terms[k].append(c * viol * dirs[..., k])
        for i, (k, m) in enumerate(pairs):
            terms[f + i].append(c_outside * dirs[..., k] * dirs[..., m])
    sums = sum_together([functools.reduce(jnp.add, t) for t in terms], axis=1)  # each (B, J)
    g = jnp.stack(sums[:f], axis=-1)  # (B, J, F)
    pair_of = np.array([[pairs.index((min(k, m), max(k, m))) for m in range(f)] for k in range(f)])
    blocks = jnp.stack(sums[f:], axis=-1)[..., pair_of]  # (B, J, F, F)
    eye = jnp.eye(j, dtype=dirs.dtype)
    h = blocks[:, :, :, None, :] * eye[None, :, None, :, None]  # (B, J, F, J, F)
    return g.reshape(b, j * f), h.reshape(b, j * f, j * f)


def gauss_newton_model(dyn: Dynamics, problems: Problem, z, every: int):
    """Gauss-Newton model ``D sum_m w_m J_m^T J_m`` of the torque cost's Hessian for a batch of
    problems at ``z (B, J F)``: ``(B, J F, J F)``, ``J_m = d tau_m / d z`` (forward mode) at every
    ``every``-th search node, its weights scaled to the same total. The BFGS method's first
    model of the torque cost (`solvers.quasi_newton.StructuredBFGS`'s ``initial``)."""
    j, f = problems.node_dirs.shape[3:]
    w = problems.node_w[:, ::every]
    w = w * (jnp.sum(problems.node_w, axis=1) / jnp.sum(w, axis=1))[:, None]
    nodes = problems.node_ls[:, :, ::every], problems.node_dirs[:, :, ::every]
    sub = problems._replace(node_ls=nodes[0], node_dirs=nodes[1], node_w=w)

    def residual(zf, prob: Problem):
        tau = jax.vmap(dyn.inverse)(*node_states(zf.reshape(j, f), prob, joint_lists(dyn)))
        return tau * jnp.sqrt(prob.duration * prob.node_w)[:, None]

    return gauss_newton_matrix(residual, z, sub)


def make_objective(dyn: Dynamics, lo, hi, weight, vmax=None, taumax=None):
    """``f(z, problem) -> (penalised objective, torque cost)`` for one condition, both by the
    problem's quadrature nodes (`search_nodes`; stride 1: the time grid's, eq. 5 exactly).
    The penalty: `limit_penalty` on q in ``[lo, hi]`` and, with ``vmax (J,)`` / ``taumax
    (J,)``, on qd in ``[-vmax, vmax]`` / tau in ``[-taumax, taumax]`` (`rate_bound`).

    q, qd and qdd are linear in z, so one evaluation is a product with the precomputed node
    arrays of `Problem` (`node_states`) and the inverse dynamics at the M nodes (no derivative
    operators).
    """

    def objective(z, problem: Problem):
        lists = joint_lists(dyn)
        q, qd, qdd = node_states(z, problem, lists)
        tau = jax.vmap(dyn.inverse)(q, qd, qdd)
        w = problem.node_w.astype(tau.dtype)
        cost = 0.5 * problem.duration * jnp.sum(w * jnp.sum(tau**2, -1))
        q_nodes, qd_nodes = (jnp.stack(x, axis=-1) if lists else x for x in (q, qd))
        penalty = limit_penalty(w, q_nodes, problem.duration, lo, hi, weight)
        if vmax is not None:
            penalty += limit_penalty(w, qd_nodes, problem.duration, -vmax, vmax, weight)
        if taumax is not None:
            penalty += limit_penalty(w, tau, problem.duration, -taumax, taumax, weight)
        return cost + penalty, cost

    return objective


def fused_search_gradient(dyn: Dynamics) -> bool:
    """Whether `make_search_value` evaluates the gradient in one reduction over the nodes: where
    ``dyn`` has unstacked torques (`Dynamics.torques`: the scalar RNEA layout, on accelerators
    and in the CPU's fast path, `cpu_fast_path`).

    On the CPU it is what makes the fast path fast (`make_search_value`). On one H200 it was
    faster too (a generation at 1,000 / 10,000 conditions 8.54 / 45.5 ms against 10.15 / 59.6
    ms; CHANGELOG.md): the value and gradient of a pass are ~10 kernels there."""
    return dyn.torques is not None


def make_search_value(dyn: Dynamics, lo, hi, weight, method: str, vmax=None, taumax=None):
    """``f(z (J, F), problem) -> penalised objective``: `make_objective`'s first output, for the
    optimiser of ``method`` (`settings.compiler.METHODS`).

    For the first-order methods (BFGS, Adam and L-BFGS, which take no second derivatives of
    ``f``; Newton takes its Hessian) where `fused_search_gradient`, ``f`` has a custom VJP. Its
    forward pass evaluates the value and the gradient as one reduction over the nodes with
    1 + J F outputs (`sum_together`): each node's gradient with respect to its q, qd and qdd
    by reverse mode on that node's scalars (`Dynamics.torques`), contracted with the node's
    directions. The value alone (the trial steps) is one reduction too.

    Why: XLA's CPU compiler emits one loop per output array and recomputes in each loop what
    the loops share. Autodiff of the stacked torques gave 21 cotangent arrays per node (q, qd,
    qdd of 7 joints), each a loop that recomputed the recursion and its adjoint; the stacked
    torques themselves were a loop that evaluated the recursion once per joint. The outputs of
    one reduction come from one loop, where XLA computes what they share once: value and
    gradient of the paper-scale batch 1.0-1.2 against 7.9-10.2 ms, the value 0.7 against 2.7 ms
    (2 CPU cores; CHANGELOG.md). Otherwise ``f`` is `make_objective`'s first output.
    """
    if method == "newton" or not fused_search_gradient(dyn):
        objective = make_objective(dyn, lo, hi, weight, vmax, taumax)
        return lambda z, problem: objective(z, problem)[0]
    torques = dyn.torques
    assert torques is not None  # fused_search_gradient

    def node_parts(q, qd, qdd):
        """Torque and penalty integrands at one node: q, qd, qdd sequences of J scalars."""
        viol = sum(squared_violation(q[k], lo[k], hi[k]) for k in range(len(q)))
        if vmax is not None:
            viol += sum(squared_violation(qd[k], -vmax[k], vmax[k]) for k in range(len(qd)))
        tau = torques(q, qd, qdd)
        if taumax is not None:
            viol += sum(squared_violation(t, -taumax[k], taumax[k]) for k, t in enumerate(tau))
        return 0.5 * sum(t * t for t in tau), weight * viol

    def node_value(q, qd, qdd):
        torque, penalty = node_parts(q, qd, qdd)
        return torque + penalty

    def scaled_nodes(problem: Problem):
        return (problem.duration * problem.node_w).astype(problem.node_ls.dtype)  # (M,)

    @jax.custom_vjp
    def value(z, problem: Problem):
        torque, penalty = jax.vmap(node_parts)(*node_states(z, problem, joint_lists=True))
        scale = scaled_nodes(problem)
        sums = sum_together([scale * torque, scale * penalty])
        return sums[0] + sums[1]

    def fwd(z, problem: Problem):
        j, f = z.shape
        states = node_states(z, problem, joint_lists=True)
        h, gs = jax.vmap(jax.value_and_grad(node_value, argnums=(0, 1, 2)))(*states)
        scale, dirs = scaled_nodes(problem), problem.node_dirs  # (M,), (3, M, J, F)
        grads = [
            sum(gs[a][k] * dirs[a, :, k, m] for a in range(3)) for k in range(j) for m in range(f)
        ]
        sums = sum_together([scale * t for t in (h, *grads)])
        return sums[0], jnp.stack(sums[1:]).reshape(j, f)

    def bwd(g, ct):
        return ct * g, None  # no cotangent for the problem's arrays

    value.defvjp(fwd, bwd)
    return value


def fixed_trip_loops() -> bool:
    """Whether the trust-region solver runs a fixed number of loop passes (accelerators) or stops
    when the batch is done (CPU; `solvers.trust_region.trust_region`'s ``fixed_trips``). Read at
    trace time.

    On a GPU, a ``while`` loop with a computed condition and a ``lax.cond`` each wait for their
    predicate on the host, once per iteration: in an H100 trace at 1,000 conditions, 82 gaps of
    ~85 us on average per generation, about 30 % of its time. A loop of known trip count runs
    without them; passes after a problem is done leave it as it is, so the iterates are the
    same. (A first version kept finished passes out with ``where`` selects, whose kernels ate
    most of the gain; they are not needed: `docs/scaling.md`.) On CPU there is nothing to wait
    for, and stopping early saves the passes after the batch is done.
    """
    return jax.default_backend() != "cpu"


def run_solver(
    settings: OptimSettings, fun: Callable, z0, free, known=None, initial=None
) -> SolverResult:
    """The solver of ``settings.method`` (`settings.compiler.METHODS`; ``settings`` resolved) on
    B problems ``fun(z (n,), i) -> scalar`` from ``z0 (B, n)``, moving the ``free (B, n)``
    coordinates. BFGS only: ``known`` the cheap part of the objective (`penalty_model`),
    ``initial (B, n, n)`` the first model of the rest (`gauss_newton_model`) or None
    (`solvers.quasi_newton.StructuredBFGS`)."""
    method, max_iters = settings.method, settings.max_iters
    assert max_iters is not None  # `OptimSettings.resolved`
    if method in ("newton", "bfgs"):
        model: HessianModel = ExactHessian(settings.hessian_every)
        descent: Descent = ExactStep(small_eigh)
        if method == "bfgs":
            model, descent = StructuredBFGS(known, initial), SubspaceStep()
        return trust_region(
            fun, z0, free, model, descent, max_iters, settings.tol, fixed_trip_loops()
        )
    # Imported here: a run whose traced step is cached never needs optax (0.1-0.15 s of imports).
    from evojax_motion.solvers import first_order

    if method == "adam":
        return first_order.adam(fun, z0, free, max_iters, settings.learning_rate)
    return first_order.lbfgs(fun, z0, free, max_iters, settings.tol)


def prepare_optimisation(
    basis: Basis, boundary: Boundary, dyn: Dynamics, grid: TimeGrid, settings: OptimSettings
) -> Prepared:
    """The first half of `compile_optimisation`, pure and un-jitted: the reduced problems of C
    conditions, the starts and BFGS's first model (`Prepared`). Its own program in a run's
    generation step (`evolution.step.generation_stages`): compiled beside `optimise_prepared`, the
    Gauss-Newton model's compile no longer waits for the optimiser's."""
    settings = settings.resolved()
    dtype = basis.mean.dtype
    problem, coeffs_ls, null = reduced_problems(
        basis, boundary, grid, settings.n_components, settings.bc_leak,
        settings.max_free_per_joint, settings.search_stride,
    )  # fmt: skip
    c, j = coeffs_ls.shape[:2]
    k = null.shape[-1]  # free directions per joint
    n_s = settings.n_starts
    z_starts = jnp.zeros((n_s, c, j, k), dtype)
    if n_s > 1:  # a fixed key: the same batch always compiles to the same result
        noise = jax.random.normal(jax.random.key(settings.seed), (n_s - 1, c, j, k))
        z_starts = z_starts.at[1:].set(settings.start_scale * noise.astype(dtype))
    # Starts and conditions share one flat batch of B = n_starts * C problems (start-major).
    probs = jax.tree_util.tree_map(lambda a: jnp.concatenate([a] * n_s, axis=0), problem)
    free = probs.mask.reshape(n_s * c, j * k)
    z0 = jnp.where(free, z_starts.reshape(n_s * c, j * k), 0.0)
    initial = None
    if settings.method == "bfgs" and settings.initial_model == "gauss-newton":
        gn = functools.partial(gauss_newton_model, dyn, every=GN_NODE_STRIDE)
        initial = in_chunks(gn, (probs, z0), settings.max_batch)
    return Prepared(probs, z0, free, coeffs_ls, null, initial)


def optimise_prepared(
    prep: Prepared,
    boundary: Boundary,
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    settings: OptimSettings,
    velocity_limit=None,
    torque_limit=None,
) -> Optimised:
    """The second half of `compile_optimisation`, pure and un-jitted: the optimiser on the
    problems of ``prep`` (`prepare_optimisation` with the same ``dyn``, ``grid`` and
    ``settings``), each result's eq. 5 cost on the full grid and the best start per
    condition. ``velocity_limit`` [rad/s], ``torque_limit`` [N m]: ``(J,)`` (inf: none) or
    None, penalised beyond ``1 - settings.limit_headroom`` of them (`rate_bound`); static."""
    settings = settings.resolved()
    dtype = prep.z0.dtype
    lower = jnp.asarray(lower, dtype)
    upper = jnp.asarray(upper, dtype)
    lo, hi = lower + settings.limit_margin, upper - settings.limit_margin
    weight = jnp.asarray(settings.limit_penalty, dtype)
    vmax = rate_bound(velocity_limit, settings.limit_headroom, dtype)
    taumax = rate_bound(torque_limit, settings.limit_headroom, dtype)
    search_value = make_search_value(dyn, lo, hi, weight, settings.method, vmax, taumax)
    c, j = prep.coeffs_ls.shape[:2]
    k = prep.null.shape[-1]
    n_s = settings.n_starts
    probs = prep.problems

    def solve(chunk: Problem, z0, free, initial) -> SolverResult:
        def fun(zf, i):
            prob = jax.tree_util.tree_map(lambda a: a[i], chunk)
            return search_value(zf.reshape(j, k), prob)

        known = functools.partial(
            penalty_model, problems=chunk, lo=lo, hi=hi, weight=weight, vmax=vmax
        )
        return run_solver(settings, fun, z0, free, known, initial)

    res = optimise_in_chunks(solve, probs, prep.z0, prep.free, settings.max_batch, prep.initial)

    def evaluate(zf, prob: Problem):
        z = zf.reshape(j, k)
        q = problem_trajectory(prob, z)
        qd, qdd = derivatives(grid, q, prob.duration)
        tau = jax.vmap(dyn.inverse)(q, qd, qdd)
        cost = cost_from_torques(grid, tau, prob.duration)  # eq. 5 on the full grid
        return q, cost, jnp.max(jnp.abs(tau), axis=0), jnp.max(jnp.abs(qd), axis=0)

    q_all, cost_all, tau_all, qd_all = jax.vmap(evaluate)(res.z, probs)
    finite = jnp.isfinite(cost_all) & jnp.all(jnp.isfinite(q_all), axis=(1, 2))
    within = jnp.all((q_all >= lower - LIMIT_TOL) & (q_all <= upper + LIMIT_TOL), axis=(1, 2))
    results = SolverResult(
        z=res.z.reshape(n_s, c, j, k),
        f=res.f.reshape(n_s, c),
        iterations=res.iterations.reshape(n_s, c),
        converged=res.converged.reshape(n_s, c),
    )
    q_all, tau_all, qd_all = (a.reshape(n_s, c, *a.shape[1:]) for a in (q_all, tau_all, qd_all))
    cost_all, finite, within = (a.reshape(n_s, c) for a in (cost_all, finite, within))
    # Best start: finite and within limits first, then the lowest penalised objective.
    rank_key = jnp.where(finite, results.f, jnp.inf) + jnp.where(finite & within, 0.0, 1e30)
    best = jnp.argmin(jnp.where(jnp.isnan(rank_key), jnp.inf, rank_key), axis=0)  # (C,)

    def pick(a):
        return jnp.take_along_axis(a, best.reshape((1, c) + (1,) * (a.ndim - 2)), axis=0)[0]

    z = pick(results.z)
    q = pick(q_all)
    coeffs = prep.coeffs_ls + jnp.einsum("cjik,cjk->cji", prep.null, z)
    return Optimised(
        q=q,
        coeffs=coeffs,
        cost=pick(cost_all),
        bc_residual=boundary_residual(grid, q, boundary),
        within_limits=pick(within),
        finite=pick(finite),
        iterations=pick(results.iterations),
        converged=pick(results.converged),
        peak_torque=pick(tau_all),
        peak_velocity=pick(qd_all),
    )


def compile_optimisation(
    basis: Basis,
    boundary: Boundary,
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    settings: OptimSettings,
    velocity_limit=None,
    torque_limit=None,
) -> Optimised:
    """The movement compiler via optimisation (paper sec. 2.2), pure and un-jitted:
    `optimise_prepared` of `prepare_optimisation`.

    ``basis``: C conditions with >= ``settings.n_components`` components
    (`compiler.basis.pca_basis`);
    ``boundary``: `compiler.interpolation.Boundary` of C conditions; ``lower``, ``upper``: ``(J,)``
    joint
    limits [rad]. Everything but ``basis`` and ``boundary`` is static. Use
    `make_optimisation_compiler` for a jitted version, or call this inside a larger jit.
    """
    prep = prepare_optimisation(basis, boundary, dyn, grid, settings)
    return optimise_prepared(
        prep, boundary, dyn, grid, lower, upper, settings, velocity_limit, torque_limit
    )


def cpu_fast_path(dyn: Dynamics, settings: OptimSettings) -> tuple[Dynamics, dict | None]:
    """``(dynamics, jit compiler_options)`` for a program that runs this compiler.

    For BFGS: `model.dynamics.unfused_cpu_program` (on CPU with the RNEA backend, the scalar RNEA
    layout
    compiled with XLA's CPU fusion emitters off, for this program only): BFGS runs on value and
    gradient evaluations, which that layout roughly doubles on CPU (`BENCHMARKS.md`, dynamics
    throughput with and without fusion emitters). Not for Newton: in our trials its Hessian
    compiled several times slower that way, for a small gain in run time. Elsewhere
    ``(dyn, None)``: unchanged.
    """
    if settings.resolved().method == "bfgs":
        return unfused_cpu_program(dyn)
    return dyn, None


def make_optimisation_compiler(
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    settings: OptimSettings | None = None,
    fast_path: bool = True,
    velocity_limit=None,
    torque_limit=None,
):
    """A jitted ``compile(basis, boundary) -> Optimised`` (see `compile_optimisation`).

    Compiles once per input shape; later calls with the same shapes reuse it. ``fast_path``:
    compile through `cpu_fast_path` (False: ``dyn`` as given, XLA's default options).
    """
    settings = OptimSettings() if settings is None else settings
    lower, upper = checked_limits(lower, upper)
    if velocity_limit is not None:
        velocity_limit = validate_rate_limits(velocity_limit, lower.shape[0], "velocity limits")
    if torque_limit is not None:
        torque_limit = validate_rate_limits(torque_limit, lower.shape[0], "torque limits")
    dyn, options = cpu_fast_path(dyn, settings) if fast_path else (dyn, None)

    def compile_batch(basis: Basis, boundary: Boundary) -> Optimised:
        return compile_optimisation(
            basis, boundary, dyn, grid, lower, upper, settings, velocity_limit, torque_limit
        )

    return jax.jit(exact_matmuls(compile_batch), compiler_options=options)


def checked_limits(lower, upper) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` as float64 ``(J,)`` arrays, validated (`validate_limits`), for a
    compiler that closes over them."""
    lower = np.asarray(lower, np.float64)
    upper = np.asarray(upper, np.float64)
    validate_limits(lower, upper, lower.shape[0] if lower.ndim == 1 else -1)
    return lower, upper


def validate_limits(lower, upper, n_joints: int, where: str = "joint limits") -> None:
    """``lower``, ``upper``: ``(J,)`` arrays with ``lower < upper``, no NaN, ``lower`` < +inf and
    ``upper`` > -inf; else `UserError`. ``-inf`` / ``+inf``: no limit on that side (a continuous
    joint, `model.robot.Robot.lower`): the limit penalty and `Optimised.within_limits` never see it
    violated."""
    lo, hi = np.asarray(lower), np.asarray(upper)
    if lo.shape != (n_joints,) or hi.shape != (n_joints,):
        raise UserError(
            f"{where}: expected lower and upper of shape ({n_joints},), got {lo.shape}, {hi.shape}"
        )
    ok = (lo < hi) & (lo < np.inf) & (hi > -np.inf)  # False for NaN
    if not ok.all():
        raise UserError(
            f"{where}: expected finite limits (or -inf / +inf: none) with lower < upper, got "
            f"lower {lo.tolist()}, upper {hi.tolist()}"
        )


def validate_rate_limits(limit, n_joints: int, where: str) -> np.ndarray:
    """``limit``: a ``(J,)`` array of values > 0 (inf: none; None: inf for every joint), e.g.
    `model.robot.Robot.torque_limit`; as float64, else `UserError` naming ``where``."""
    arr = np.full(n_joints, np.inf) if limit is None else np.asarray(limit, np.float64)
    if arr.shape != (n_joints,) or not (arr > 0).all():  # False for NaN
        raise UserError(f"{where}: expected {n_joints} values > 0 (inf: no limit), got {arr}")
    return arr
