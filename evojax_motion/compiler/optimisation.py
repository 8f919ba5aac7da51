"""Movement compiler via optimisation (paper sec. 2.2, eq. 3-5).

Per joint the trajectory is the basis mean plus K = 4 weighted principal components plus a
constant (eq. 3); the weights minimise the torque cost

    0.5 * int_0^D |tau(q, qd, qdd)|^2 dt,   tau = M(q) qdd + C(q, qd) qd + g(q)    (eq. 4-5)

subject to the boundary conditions of eq. 2. The BCs are linear in the weights, so we move in their
null space: ``x = x_ls + N z`` (`compiler.interpolation.solve_boundary` with ``leak``) meets them
after every step by construction, whatever the optimiser does. Which BC directions bind is decided
in q units (`settings.compiler.BC_LEAK`); z is the RMS change of q [rad] along q-orthonormal null
directions, at most ``max_free_per_joint`` per joint, masked (static shapes). The start z = 0 is
the interpolation compiler's answer (eq. 1-2 with ``interp_components`` = 3 of the components,
`compiler.problems.interpolation_base`; with 0, the prior minimum-norm BC solution with all K),
and the free directions move it within the BCs it meets. The start is a candidate of its own:
each condition returns the best, by the penalised objective on all T samples, of the
optimiser's results and the start, feasible ones (finite, within the joint, velocity and torque
limits) first. So no result costs more than the interpolation, nor leaves a limit the
interpolation keeps (paper configuration, 300 problems of generation 1: it ended above the
interpolation on 19 and outside the joint limits on 2 before; CHANGELOG.md).

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
    penalty's exact Hessian (`compiler.search_objective.penalty_model`) plus a damped-BFGS model
    of the torque cost, started from its Gauss-Newton matrix (``initial_model``,
    `compiler.search_objective.gauss_newton_model`). The model is positive definite, so the step
    minimises it on the plane of the gradient and the Newton step (`solvers.steps.subspace_step`;
    Nocedal & Wright, sec. 4.1; the Newton step by `linalg.cholesky.cholesky_solve`): no
    eigendecomposition (on GPUs a cuSOLVER call per iteration, 22 % of an iteration at 1,000
    conditions on an H100).
  - ``"adam"``: plain ``optax.adam`` in z for ``max_iters`` steps (the paper's projected-gradient
    baseline, kept for comparison).
  - ``"lbfgs"``: ``optax.lbfgs`` with its zoom line search, stopped on the gradient norm.
With ``n_starts > 1`` the optimiser also starts from random z (``start_scale`` rad RMS), all
starts of a condition from the same first BFGS model (the one at z = 0); the start with the
lowest search objective (`best_start`) then competes with z = 0 as above. The solvers
themselves (`solvers`) know nothing of trajectories: this module sets up the reduced problems
(`compiler.problems`) and their objective (`compiler.search_objective`), hands them to one, and
checks its results against the limits.

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

The bfgs row: ``--variants bfgs`` (its result file is in the git history of
``benchmarks/results/``; BFGS keeps its model through a
rejected step: restarting it there gave median -0.003 %, p95 2.5 %, max 12.5 %).
The paper config (``search_stride: 4``, ``max_free_per_joint: 2``) in a later run of the same
benchmark (``results/optimality_cpu_fast.json``): median -0.0015 %, p95 0.22 %, max 3.0 %, 15 s
where the default took 82 s in that run. These figures predate the interpolation start; with it,
the paper config on the 300 problems of its generation 1 (``--variants shipped --conditions
300``, ``results/optimality_cpu_shipped.json``, on the shipped demonstrations): median
-0.0005 %, p95 1.27 %, max 4.3 %, 6.7 % above 1 %, none outside the joint limits or above the
interpolation; 87.0 % within SLSQP's cost + 0.1 %. With 4, 8 and 16 starts (variants
``shipped-4starts`` ...): p95 0.031, 0.018 and 0.017 %, 96.3, 98.7 and 99.3 % within, at 2.1,
3.9 and 7.5x the optimiser's time on 2 CPU cores (1.2, 1.2 and 2.1x on one H200; README.md).

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

from evojax_motion.compiler.basis import Basis, small_eigh
from evojax_motion.compiler.interpolation import Boundary, boundary_residual
from evojax_motion.compiler.problems import (
    Problem,
    problem_trajectory,
    reduced_problems,
)
from evojax_motion.compiler.search_objective import (
    gauss_newton_model,
    limit_penalty,
    make_search_value,
    penalty_model,
    rate_bound,
)
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics, unfused_cpu_program
from evojax_motion.motion.objective import cost_from_torques
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.settings.compiler import OptimSettings
from evojax_motion.solvers.base import Descent, HessianModel, SolverResult
from evojax_motion.solvers.chunking import in_chunks, optimise_in_chunks
from evojax_motion.solvers.quasi_newton import ExactHessian, StructuredBFGS
from evojax_motion.solvers.steps import ExactStep, SubspaceStep
from evojax_motion.solvers.trust_region import trust_region

# Samples may exceed a joint limit by this much [rad] and still count as within it: float32
# rounding of a BC that sits exactly on a limit.
LIMIT_TOL = 1e-5
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
    iterations used (of the chosen start; where the start itself is returned, of the optimiser's
    run from it); converged: (C,) stopping test met within the budget (the same run);
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


class Prepared(NamedTuple):
    """A batch of C conditions made ready for the optimiser (`prepare_optimisation`): its B =
    ``n_starts * C`` problems (start-major) and what the optimiser starts from.

    problems: `compiler.problems.Problem` with ``(B, ...)`` arrays; z0, free: ``(B, J F)`` the
    start and the free directions (bool); coeffs_ls: ``(C, J, K+1)`` the coefficients at z = 0;
    null: ``(C, J, K+1, F)`` its free directions in the weights; initial: ``(B, J F, J F)``
    BFGS's first model of the torque cost (`compiler.search_objective.gauss_newton_model` at
    the condition's first start, the same for all its starts), or None (other methods, or
    ``initial_model: identity``).
    """

    problems: Problem
    z0: jnp.ndarray
    free: jnp.ndarray
    coeffs_ls: jnp.ndarray
    null: jnp.ndarray
    initial: jnp.ndarray | None


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
    coordinates. BFGS only: ``known`` the cheap part of the objective
    (`compiler.search_objective.penalty_model`), ``initial (B, n, n)`` the first model of the
    rest (`compiler.search_objective.gauss_newton_model`) or None
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
        settings.max_free_per_joint, settings.search_stride, settings.interp_components,
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
        # One model per condition, at the first start, shared by all its starts.
        gn = functools.partial(gauss_newton_model, dyn, every=GN_NODE_STRIDE)
        initial = in_chunks(gn, (problem, z0[:c]), settings.max_batch)
        initial = jnp.concatenate([initial] * n_s, axis=0)
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
    ``settings``), each result's eq. 5 cost on the full grid and the best per condition of
    the results and the first start (module docstring). ``velocity_limit`` [rad/s],
    ``torque_limit`` [N m]: ``(J,)`` (inf: none) or None, penalised beyond ``1 -
    settings.limit_headroom`` of them (`compiler.search_objective.rate_bound`); static."""
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

    # Candidates per condition: the best start's result (`best_start`) and the first start
    # itself (the interpolation's answer), ranked on all T samples.
    res = best_start(res, n_s)
    z_all = jnp.concatenate([res.z, prep.z0[:c]], axis=0)
    probs_all = jax.tree_util.tree_map(lambda a: jnp.concatenate([a[:c], a[:c]], axis=0), probs)

    def evaluate(zf, prob: Problem):
        z = zf.reshape(j, k)
        q = problem_trajectory(prob, z)
        qd, qdd = derivatives(grid, q, prob.duration)
        tau = jax.vmap(dyn.inverse)(q, qd, qdd)
        cost = cost_from_torques(grid, tau, prob.duration)  # eq. 5 on the full grid
        bounded = [(q, lo, hi)] + [
            (x, -b, b) for x, b in ((qd, vmax), (tau, taumax)) if b is not None
        ]
        penalty = sum(limit_penalty(grid.w, x, prob.duration, a, b, weight) for x, a, b in bounded)
        return q, cost, penalty, jnp.max(jnp.abs(tau), axis=0), jnp.max(jnp.abs(qd), axis=0)

    q_all, cost_all, pen_all, tau_all, qd_all = jax.vmap(evaluate)(z_all, probs_all)
    finite = jnp.isfinite(cost_all) & jnp.all(jnp.isfinite(q_all), axis=(1, 2))
    within = jnp.all((q_all >= lower - LIMIT_TOL) & (q_all <= upper + LIMIT_TOL), axis=(1, 2))
    n_c = 2
    results = SolverResult(
        z=z_all.reshape(n_c, c, j, k),
        f=(cost_all + pen_all).reshape(n_c, c),
        iterations=jnp.concatenate([res.iterations, res.iterations[:c]]).reshape(n_c, c),
        converged=jnp.concatenate([res.converged, res.converged[:c]]).reshape(n_c, c),
    )
    q_all, tau_all, qd_all = (a.reshape(n_c, c, *a.shape[1:]) for a in (q_all, tau_all, qd_all))
    cost_all, finite, within = (a.reshape(n_c, c) for a in (cost_all, finite, within))
    # Best candidate: finite and within every limit first (the evolution's test), then the
    # lowest penalised objective; a tie goes to the first (an optimiser's result over its start).
    feasible = finite & within
    for peak, limit in ((qd_all, velocity_limit), (tau_all, torque_limit)):
        if limit is not None:
            feasible &= jnp.all(peak <= jnp.asarray(limit, dtype), axis=-1)
    rank_key = jnp.where(finite, results.f, jnp.inf) + jnp.where(feasible, 0.0, 1e30)
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


def best_start(res: SolverResult, n_starts: int) -> SolverResult:
    """Per condition, the result of its start with the lowest search objective ``f`` (the
    optimiser's own, on the search nodes; not finite: last; a tie goes to the first start):
    ``res`` of ``B = n_starts * C`` problems (start-major) -> C. Only that result and the first
    start are then evaluated on all T samples (2 evaluations per condition instead of
    ``n_starts + 1``)."""
    if n_starts == 1:
        return res
    c = res.f.shape[0] // n_starts
    f = res.f.reshape(n_starts, c)
    best = jnp.argmin(jnp.where(jnp.isfinite(f), f, jnp.inf), axis=0)  # (C,)
    cols = jnp.arange(c)
    return jax.tree_util.tree_map(lambda a: a.reshape(n_starts, c, *a.shape[1:])[best, cols], res)


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
    velocity_limit = validate_rate_limits(velocity_limit, lower.shape[0], "velocity limits")
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
