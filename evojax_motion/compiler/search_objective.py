"""The objective the movement compiler via optimisation (`compiler.optimisation`, paper eq. 4-5)
searches on the reduced problems (`compiler.problems`): the torque cost plus quadratic penalties on
the joint, velocity and torque limits (`make_objective`; `make_search_value`, the optimiser's, with
value and gradient in one reduction over the nodes), and the BFGS method's models of its Hessian
(`penalty_model`, `gauss_newton_model`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.problems import Problem, joint_lists, node_states
from evojax_motion.linalg.reductions import sum_together
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.solvers.quasi_newton import gauss_newton_matrix


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
    problem's quadrature nodes (`compiler.problems.search_nodes`; stride 1: the time grid's,
    eq. 5 exactly). The penalty: `limit_penalty` on q in ``[lo, hi]`` and, with ``vmax (J,)`` /
    ``taumax (J,)``, on qd in ``[-vmax, vmax]`` / tau in ``[-taumax, taumax]`` (`rate_bound`).

    q, qd and qdd are linear in z, so one evaluation is a product with the precomputed node
    arrays of `compiler.problems.Problem` (`compiler.problems.node_states`) and the inverse
    dynamics at the M nodes (no derivative operators).
    """

    def objective(z, problem: Problem):
        lists = joint_lists(dyn)
        q, qd, qdd = node_states(z, problem, lists)
        tau = jax.vmap(dyn.inverse)(q, qd, qdd)
        w = problem.node_w.astype(tau.dtype)
        cost = 0.5 * problem.duration * jnp.sum(w * jnp.sum(tau**2, -1))
        bounds = [(q, lo, hi)] if vmax is None else [(q, lo, hi), (qd, -vmax, vmax)]
        bounded = [(jnp.stack(x, axis=-1) if lists else x, a, b) for x, a, b in bounds]
        if taumax is not None:
            bounded.append((tau, -taumax, taumax))
        penalty = sum(limit_penalty(w, x, problem.duration, a, b, weight) for x, a, b in bounded)
        return cost + penalty, cost

    return objective


def fused_search_gradient(dyn: Dynamics) -> bool:
    """Whether `make_search_value` evaluates the gradient in one reduction over the nodes: where
    ``dyn`` has unstacked torques (`Dynamics.torques`: the scalar RNEA layout, on accelerators
    and in the CPU's fast path, `compiler.optimisation.cpu_fast_path`).

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
