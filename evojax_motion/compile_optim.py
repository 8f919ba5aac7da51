"""Movement compiler via optimisation (paper sec. 2.2, eq. 3-5).

Per joint the trajectory is the basis mean plus K = 4 weighted principal components plus a
constant (eq. 3); the weights minimise the torque cost

    0.5 * int_0^D |tau(q, qd, qdd)|^2 dt,   tau = M(q) qdd + C(q, qd) qd + g(q)    (eq. 4-5)

subject to the boundary conditions of eq. 2. The BCs are linear in the weights, so we move in their
null space: ``x = x_ls + N z`` (`compile_interp.solve_boundary`) meets them after every step by
construction, whatever the optimiser does; z has a static size J * K with a mask of the real null
directions (rank-deficient BC systems, e.g. rest-to-rest bases, leave up to 3 free weights per joint,
full-rank ones 1).

Joint limits (the paper discards offspring that leave them, sec. 3.1): the objective adds a smooth
quadratic penalty ``limit_penalty * int relu(q - hi)^2 + relu(lo - q)^2 dt`` on the box shrunk by
``limit_margin``, ``[lower + margin, upper - margin]``; the margin absorbs the small violation a finite
penalty leaves, and the result is checked against the true limits (``within_limits``).

Optimisers (``OptimSettings.method``), all batched with vmap over conditions (and starts):
  - ``"newton"`` (default): a trust-region Newton method on the reduced problem with the exact
    Hessian (``jax.hessian`` in z). The step is ``-(|H| + lam I)^-1 g`` with ``|H|`` the Hessian with
    its eigenvalues made positive (saddle-free Newton, so every step descends), ``lam`` adapted
    Levenberg-Marquardt-style from the ratio of actual to predicted decrease, rejected steps
    retried with more damping; stops on the Newton decrement or the iteration budget.
  - ``"adam"``: plain ``optax.adam`` in z for ``max_iters`` steps (the paper's projected-gradient
    baseline, kept for comparison).
  - ``"lbfgs"``: ``optax.lbfgs`` with its zoom line search, stopped on the gradient norm.
The problem is not convex for some conditions (PROBES.md); with ``n_starts > 1`` the optimiser also
starts from random z (prior standard deviations ``start_scale``) and keeps the best result that is
finite and within limits. Start 0 is always z = 0, the minimum-norm BC solution (the interpolation
compiler with K = 4).

Example::

    compile = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, OptimSettings())
    out = compile(basis, boundary)      # basis: >= 4 components; one jit, vmap over conditions
    out.q, out.cost, out.within_limits  # (C, T, J), (C,), (C,)
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from evojax_motion.basis import Basis
from evojax_motion.compile_interp import (
    RANK_RTOL,
    Boundary,
    basis_functions,
    boundary_residual,
    solve_boundary,
    trajectory,
)
from evojax_motion.dynamics import Dynamics
from evojax_motion.errors import UserError
from evojax_motion.objective import cost_from_torques, trajectory_torques
from evojax_motion.timegrid import TimeGrid

METHODS = ("newton", "adam", "lbfgs")
# Samples may exceed a joint limit by this much [rad] and still count as within it: float32
# rounding of a BC that sits exactly on a limit.
LIMIT_TOL = 1e-5
# Trust-region constants of the Newton method: damping lam = mu * max |eigenvalue of H|.
MU_INIT, MU_MIN, MU_MAX = 1e-3, 1e-9, 1e6
RHO_GOOD, RHO_BAD = 0.75, 0.25  # ratio actual/predicted decrease: shrink / grow the damping


def _check(ok: bool, name: str, expected: str, value) -> None:
    if not ok:
        raise ValueError(f"{name}: expected {expected}, got {value!r}")


@dataclass(frozen=True)
class OptimSettings:
    """Settings of the movement compiler via optimisation.

    - ``n_components``: principal components K of eq. 3 (paper: 4).
    - ``method``: ``"newton"`` (default), ``"adam"`` or ``"lbfgs"`` (module docstring).
    - ``max_iters``: iteration budget (Newton / L-BFGS iterations, Adam steps).
    - ``tol``: stop when the predicted decrease (Newton decrement) falls below ``tol * |f|``
      (Newton), or the gradient norm below ``tol * (1 + |f|)`` (L-BFGS; Adam runs its budget).
    - ``learning_rate``: Adam's step size, in prior standard deviations.
    - ``limit_margin`` [rad]: the penalty acts on ``[lower + margin, upper - margin]``.
    - ``limit_penalty`` [cost units / rad^2 / s]: weight of the quadratic limit penalty.
    - ``n_starts``: starts per condition (1 = z = 0 only); ``start_scale``: spread of the others
      [prior standard deviations]; ``seed``: the fixed key of those starts (deterministic).
    - ``rank_rtol``: relative rank tolerance of the BC system (`compile_interp.RANK_RTOL`).
    """

    n_components: int = 4
    method: str = "newton"
    max_iters: int = 25
    tol: float = 1e-7
    learning_rate: float = 0.1
    limit_margin: float = 0.02
    limit_penalty: float = 1e4
    n_starts: int = 1
    start_scale: float = 1.0
    seed: int = 0
    rank_rtol: float = RANK_RTOL

    def __post_init__(self):
        _check(
            isinstance(self.n_components, int) and self.n_components >= 1,
            "n_components",
            "an integer >= 1",
            self.n_components,
        )
        _check(self.method in METHODS, "method", f"one of {METHODS}", self.method)
        _check(
            isinstance(self.max_iters, int) and self.max_iters >= 1,
            "max_iters",
            "an integer >= 1",
            self.max_iters,
        )
        _check(0 <= self.tol < 1, "tol", "a number in [0, 1)", self.tol)
        _check(self.learning_rate > 0, "learning_rate", "a number > 0", self.learning_rate)
        _check(
            0 <= self.limit_margin < 0.5,
            "limit_margin",
            "a number in [0, 0.5) rad",
            self.limit_margin,
        )
        _check(self.limit_penalty >= 0, "limit_penalty", "a number >= 0", self.limit_penalty)
        _check(
            isinstance(self.n_starts, int) and self.n_starts >= 1,
            "n_starts",
            "an integer >= 1",
            self.n_starts,
        )
        _check(self.start_scale >= 0, "start_scale", "a number >= 0", self.start_scale)
        _check(isinstance(self.seed, int), "seed", "an integer", self.seed)
        _check(0 < self.rank_rtol < 1, "rank_rtol", "a number in (0, 1)", self.rank_rtol)


class Optimised(NamedTuple):
    """Result of the optimisation compiler for C conditions.

    q: (C, T, J) [rad]; coeffs: (C, J, K+1) weights of the K components and the constant;
    cost: (C,) eq. 5 torque cost of q (no penalty) [N^2 m^2 s]; bc_residual: (C,) max BC error
    (rad, rad/s); within_limits: (C,) every sample inside [lower, upper] (+`LIMIT_TOL`);
    finite: (C,) q and cost are finite; iterations: (C,) int32 iterations used (of the chosen
    start); converged: (C,) stopping test met within the budget.
    """

    q: jnp.ndarray
    coeffs: jnp.ndarray
    cost: jnp.ndarray
    bc_residual: jnp.ndarray
    within_limits: jnp.ndarray
    finite: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray


class Problem(NamedTuple):
    """One condition's reduced problem: ``q(z) = q_ls + sum_jk z_jk Q_jk``.

    q_ls: (T, J); dirs: (J, K, T) trajectories of the null directions (zero where masked);
    mask: (J, K) bool; duration: ().
    """

    q_ls: jnp.ndarray
    dirs: jnp.ndarray
    mask: jnp.ndarray
    duration: jnp.ndarray


class _Result(NamedTuple):
    z: jnp.ndarray  # (J, K)
    f: jnp.ndarray  # () penalised objective
    iterations: jnp.ndarray
    converged: jnp.ndarray


def reduced_problems(
    basis: Basis, boundary: Boundary, grid: TimeGrid, n_components: int, rank_rtol: float
) -> tuple[Problem, jnp.ndarray, jnp.ndarray]:
    """The batch of reduced problems: ``(Problem (C, ...), coeffs_ls (C, J, K+1), null)``.

    ``null: (C, J, K+1, K)`` maps z to coefficient changes.
    """
    sol = solve_boundary(basis, boundary, grid, n_components, rank_rtol)
    funcs = basis_functions(basis, n_components)  # (C, J, K+1, T)
    q_ls = trajectory(basis, sol.coeffs)
    dirs = jnp.einsum("cjik,cjit->cjkt", sol.null, funcs)
    problem = Problem(q_ls=q_ls, dirs=dirs, mask=sol.null_mask, duration=boundary.duration)
    return problem, sol.coeffs, sol.null


def problem_trajectory(problem: Problem, z: jnp.ndarray) -> jnp.ndarray:
    """``q (T, J)`` of one condition at null-space coordinates ``z (J, K)``."""
    return problem.q_ls + jnp.einsum("jk,jkt->tj", z, problem.dirs)


def limit_penalty(grid: TimeGrid, q, duration, lo, hi, weight) -> jnp.ndarray:
    """``weight * int relu(q - hi)^2 + relu(lo - q)^2 dt`` for ``q (T, J)``: a scalar."""
    viol = jnp.maximum(q - hi, 0.0) ** 2 + jnp.maximum(lo - q, 0.0) ** 2
    w = jnp.asarray(grid.w, q.dtype)
    return weight * duration * jnp.sum(w * jnp.sum(viol, axis=-1))


def make_objective(dyn: Dynamics, grid: TimeGrid, lo, hi, weight):
    """``f(z, problem) -> (penalised objective, torque cost)`` for one condition."""

    def objective(z, problem: Problem):
        q = problem_trajectory(problem, z)
        tau = trajectory_torques(dyn, grid, q, problem.duration)
        cost = cost_from_torques(grid, tau, problem.duration)
        return cost + limit_penalty(grid, q, problem.duration, lo, hi, weight), cost

    return objective


def _newton(fun, z0, mask, settings: OptimSettings) -> _Result:
    """Trust-region (damped, saddle-free) Newton on ``fun(z (J, K)) -> scalar``; masked dims fixed."""
    shape = z0.shape
    n = z0.size
    free = mask.reshape(n)

    def flat(zf):
        return fun(zf.reshape(shape))

    def derivs(zf):
        f, g = jax.value_and_grad(flat)(zf)
        h = jax.hessian(flat)(zf)
        # Masked directions do not move q: unit curvature and zero gradient keep them still.
        h = jnp.where(free[:, None] & free[None, :], h, 0.0) + jnp.diag(jnp.where(free, 0.0, 1.0))
        g = jnp.where(free, g, 0.0)
        ok = jnp.isfinite(f) & jnp.all(jnp.isfinite(g)) & jnp.all(jnp.isfinite(h))
        # A non-finite point (NaN basis or BCs) stops at once; sanitise so eigh sees finite input.
        h = jnp.where(ok, h, jnp.eye(n, dtype=h.dtype))
        g = jnp.where(ok, g, 0.0)
        return f, g, h, ok

    def step(g, h, mu):
        e, v = jnp.linalg.eigh(h)
        a = jnp.abs(e)
        lam = mu * jnp.max(a)
        gv = v.T @ g
        p = -v @ (gv / (a + lam))
        # Predicted decrease of the convexified model, > 0 unless g = 0.
        pred = -(g @ p + 0.5 * jnp.sum(a * (v.T @ p) ** 2))
        decrement = 0.5 * jnp.sum(gv**2 / jnp.maximum(a, jnp.finfo(a.dtype).tiny))
        return p, pred, decrement

    f0, g0, h0, ok0 = derivs(z0.reshape(n))

    def cond(state):
        _, _, _, _, _, it, done, _ = state
        return (~done) & (it < settings.max_iters)

    def body(state):
        zf, f, g, h, mu, it, done, conv = state
        p, pred, decrement = step(g, h, mu)
        conv_now = decrement <= settings.tol * jnp.abs(f)
        f_t, g_t, h_t, ok_t = derivs(zf + p)
        rho = (f - f_t) / pred
        accept = ok_t & (f_t < f) & ~conv_now
        mu_new = jnp.where(
            accept & (rho > RHO_GOOD), mu / 3.0, jnp.where(accept & (rho > RHO_BAD), mu, mu * 4.0)
        )
        mu_new = jnp.clip(mu_new, MU_MIN, MU_MAX)
        sel = functools.partial(jnp.where, accept)
        state = (
            sel(zf + p, zf),
            sel(f_t, f),
            sel(g_t, g),
            sel(h_t, h),
            mu_new,
            it + 1,
            conv_now | (mu >= MU_MAX),
            conv | conv_now,
        )
        return state

    init = (z0.reshape(n), f0, g0, h0, jnp.asarray(MU_INIT, f0.dtype), 0, ~ok0, False)
    zf, f, _, _, _, it, _, conv = jax.lax.while_loop(cond, body, init)
    return _Result(z=zf.reshape(shape), f=f, iterations=jnp.asarray(it, jnp.int32), converged=conv)


def _adam(fun, z0, mask, settings: OptimSettings) -> _Result:
    """``max_iters`` steps of plain ``optax.adam`` (the projected-gradient baseline)."""
    opt = optax.adam(settings.learning_rate)

    def body(_, carry):
        z, state = carry
        g = jax.grad(fun)(z)
        g = jnp.where(mask & jnp.isfinite(g), g, 0.0)
        updates, state = opt.update(g, state, z)
        return optax.apply_updates(z, updates), state

    z, _ = jax.lax.fori_loop(0, settings.max_iters, body, (z0, opt.init(z0)))
    f = fun(z)
    return _Result(z, f, jnp.asarray(settings.max_iters, jnp.int32), jnp.asarray(False))


def _lbfgs(fun, z0, mask, settings: OptimSettings) -> _Result:
    """``optax.lbfgs`` with its zoom line search; stops on the gradient norm or the budget."""
    opt = optax.lbfgs()

    def masked(z):
        # Masked coordinates do not change q, so this is the same function with zero gradient.
        return fun(jnp.where(mask, z, 0.0))

    value_and_grad = optax.value_and_grad_from_state(masked)

    def cond(carry):
        _, state, it, done = carry
        return (~done) & (it < settings.max_iters)

    def body(carry):
        z, state, it, _ = carry
        f, g = value_and_grad(z, state=state)
        updates, state = opt.update(g, state, z, value=f, grad=g, value_fn=masked)
        z = optax.apply_updates(z, updates)
        gnorm = optax.tree.norm(optax.tree.get(state, "grad"))
        done = (gnorm <= settings.tol * (1.0 + jnp.abs(f))) | ~jnp.isfinite(f)
        return z, state, it + 1, done

    z, _, it, done = jax.lax.while_loop(cond, body, (z0, opt.init(z0), 0, False))
    return _Result(z, masked(z), jnp.asarray(it, jnp.int32), done)


_SOLVERS = {"newton": _newton, "adam": _adam, "lbfgs": _lbfgs}


def compile_optimisation(
    basis: Basis,
    boundary: Boundary,
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    settings: OptimSettings,
) -> Optimised:
    """The movement compiler via optimisation (paper sec. 2.2), pure and un-jitted.

    ``basis``: C conditions with >= ``settings.n_components`` components (`basis.pca_basis`);
    ``boundary``: `compile_interp.Boundary` of C conditions; ``lower``, ``upper``: ``(J,)`` joint
    limits [rad]. Everything but ``basis`` and ``boundary`` is static. Use
    `make_optimisation_compiler` for a jitted version, or call this inside a larger jit (the
    evolution's generation step).
    """
    k = settings.n_components
    dtype = basis.mean.dtype
    lower = jnp.asarray(lower, dtype)
    upper = jnp.asarray(upper, dtype)
    lo, hi = lower + settings.limit_margin, upper - settings.limit_margin
    problem, coeffs_ls, null = reduced_problems(basis, boundary, grid, k, settings.rank_rtol)
    objective = make_objective(dyn, grid, lo, hi, jnp.asarray(settings.limit_penalty, dtype))
    solver = _SOLVERS[settings.method]

    c, j = coeffs_ls.shape[:2]
    z_starts = jnp.zeros((settings.n_starts, c, j, k), dtype)
    if settings.n_starts > 1:  # a fixed key: the same batch always compiles to the same result
        noise = jax.random.normal(jax.random.key(settings.seed), (settings.n_starts - 1, c, j, k))
        z_starts = z_starts.at[1:].set(settings.start_scale * noise.astype(dtype))

    def solve_one(z0, prob: Problem) -> _Result:
        z0 = jnp.where(prob.mask, z0, 0.0)
        return solver(lambda z: objective(z, prob)[0], z0, prob.mask, settings)

    per_condition = jax.vmap(solve_one)
    results = jax.vmap(per_condition, in_axes=(0, None))(z_starts, problem)  # leading: starts

    def evaluate(z, prob: Problem):
        q = problem_trajectory(prob, z)
        _, cost = objective(z, prob)
        return q, cost

    q_all, cost_all = jax.vmap(jax.vmap(evaluate), in_axes=(0, None))(results.z, problem)
    finite = jnp.isfinite(cost_all) & jnp.all(jnp.isfinite(q_all), axis=(2, 3))
    within = jnp.all((q_all >= lower - LIMIT_TOL) & (q_all <= upper + LIMIT_TOL), axis=(2, 3))
    # Best start: finite and within limits first, then the lowest penalised objective.
    rank_key = jnp.where(finite, results.f, jnp.inf) + jnp.where(finite & within, 0.0, 1e30)
    best = jnp.argmin(jnp.where(jnp.isnan(rank_key), jnp.inf, rank_key), axis=0)  # (C,)

    def pick(a):
        return jnp.take_along_axis(a, best.reshape((1, c) + (1,) * (a.ndim - 2)), axis=0)[0]

    z = pick(results.z)
    q = pick(q_all)
    coeffs = coeffs_ls + jnp.einsum("cjik,cjk->cji", null, z)
    return Optimised(
        q=q,
        coeffs=coeffs,
        cost=pick(cost_all),
        bc_residual=boundary_residual(grid, q, boundary),
        within_limits=pick(within),
        finite=pick(finite),
        iterations=pick(results.iterations),
        converged=pick(results.converged),
    )


def make_optimisation_compiler(
    dyn: Dynamics, grid: TimeGrid, lower, upper, settings: OptimSettings | None = None
):
    """A jitted ``compile(basis, boundary) -> Optimised`` (see `compile_optimisation`).

    Compiles once per input shape; later calls with the same shapes reuse it.
    """
    settings = OptimSettings() if settings is None else settings
    lower = np.asarray(lower, np.float64)
    upper = np.asarray(upper, np.float64)
    validate_limits(lower, upper, lower.shape[0] if lower.ndim == 1 else -1)

    @jax.jit
    def compile_batch(basis: Basis, boundary: Boundary) -> Optimised:
        return compile_optimisation(basis, boundary, dyn, grid, lower, upper, settings)

    return compile_batch


def validate_limits(lower, upper, n_joints: int, where: str = "joint limits") -> None:
    """``lower``, ``upper``: finite ``(J,)`` arrays with ``lower < upper``; else `UserError`."""
    lo, hi = np.asarray(lower), np.asarray(upper)
    if lo.shape != (n_joints,) or hi.shape != (n_joints,):
        raise UserError(
            f"{where}: expected lower and upper of shape ({n_joints},), got {lo.shape}, {hi.shape}"
        )
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo < hi).all()):
        raise UserError(f"{where}: expected finite limits with lower < upper")
