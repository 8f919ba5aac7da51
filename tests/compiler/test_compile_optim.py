"""Movement compiler via optimisation (eq. 3-5): gradients, optimality vs float64 SLSQP, BCs,
limits, bad inputs, no recompilation. A 3-joint version of the shipped arm keeps compiles short."""

import functools
import logging
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evojax_motion.compiler.basis as basis_module
import evojax_motion.compiler.optimisation as optim_module
import evojax_motion.compiler.search_objective as objective_module
from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import Boundary, compile_interpolation
from evojax_motion.compiler.optimisation import (
    cpu_fast_path,
    make_optimisation_compiler,
    optimise_in_chunks,
    validate_limits,
)
from evojax_motion.compiler.problems import (
    joint_lists,
    problem_trajectory,
    reduced_problems,
    search_nodes,
)
from evojax_motion.compiler.search_objective import (
    fused_search_gradient,
    gauss_newton_model,
    limit_penalty,
    make_objective,
    make_search_value,
    penalty_model,
)
from evojax_motion.errors import UserError
from evojax_motion.linalg.cholesky import cholesky_solve
from evojax_motion.linalg.eigh2 import eigh_2x2
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.objective import torque_cost, trajectory_torques
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.compiler import DEFAULT_ITERS, OptimSettings
from evojax_motion.solvers.base import SolverResult
from evojax_motion.solvers.quasi_newton import bfgs_update
from evojax_motion.solvers.steps import subspace_step

# benchmarks/ is not a package of the project; its SLSQP reference is shared with the benchmark.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.slsqp_reference import (
    SLSQP_MAXITER,
    ReferenceSolver,
    solve_reference,
    torque_costs_f64,
)

JOINTS = ("shoulder_pitch", "shoulder_roll", "elbow")
T, N_DEMOS, K = 24, 40, 4
GOOD = 5  # conditions 0..4 are well posed; 5: NaN BC, 6: no neighbour, 7: BC outside the limits
# Relative gap to SLSQP per condition (negative allowed: a lower local minimum). Largest gap
# measured with SSE4.2 / the default (AVX2) on a 2-core AMD EPYC: -0.257 % / -0.257 %
# (test_matches_float64_slsqp), -0.429 % / -0.429 % (both loops).
TOL_GAP = 0.01
TOL_BC_POS = 1e-4  # rad: end postures (BCs that bind)
# rad/s: end velocities; at T = 24 the minimum-jerk ends carry ~5e-4 x range / D of finite-
# difference slope, which binds neither in the start nor in the optimisation (BC_LEAK)
TOL_BC_VEL = 3e-3
TOL_GRAD = 1e-6  # relative: float64 gradient in null-space coordinates vs central differences
TOL_COST = 1e-5  # relative: returned cost vs eq. 5 recomputed from the returned q
TOL_START_Q = 1e-5  # rad: a returned start vs the interpolation (float32 rounding of one sum)
# relative, per condition: eq. 5 cost of the optimum searched on every 2nd sample (search_stride;
# 12 intervals at T = 24, measured <= 0.34 % worse) vs on all samples
TOL_STRIDE = 5e-3
TOL_SAME_SOLVE = 1e-12  # relative: the same float64 SLSQP solve, kept programs vs fresh ones
TOL_JACOBI = 1e-4  # relative: optimum cost on the accelerators' Jacobi path vs LAPACK's
# relative: BFGS optimum through the CPU fast path (scalar RNEA, fusion emitters off) vs the
# default program; the same iterations up to float32 rounding of a differently fused program
TOL_FAST_PATH = 1e-3  # measured 2.1e-6 / 1.0e-6 (SSE4.2 / default, AVX2)
# Chunked vs whole batch: the same problems, rounding may differ with the batch size (float32).
TOL_CHUNKS = 1e-5  # relative cost
TOL_CHUNKS_Q = 1e-3  # rad
# Iterations: a convergence test that sits on its threshold can pass one iteration earlier or
# later in a differently batched program (seen: 10 against 11, costs 2.3e-6 apart).
TOL_CHUNKS_ITERS = 1
TOL_LINALG = 1e-10  # float64: trust-region steps and BFGS updates vs their closed forms (numpy)
# relative: length (12 Newton iterations on the secular equation: 1.6e-8 measured) and model
# value of the subspace step vs a search over 200,000 angles on the circle (its own error is
# ~ (2 pi / 200,000)^2, 1e-9)
TOL_CIRCLE = 1e-7
TOL_GN = 1e-6  # relative: Gauss-Newton model vs central differences (h = 1e-6, float64)
TOL_LAYOUT = 1e-5  # relative, float32: objective and gradient, joint lists vs one array
TOL_FUSED = 1e-10  # relative, float64: the fused search gradient vs autodiff (summation order)
# Relative cost, float32: an optimiser's result, fused gradient vs autodiff (`_first_order_case`:
# Adam / L-BFGS differ by 0.6-2.4e-6 / 0.7-1.0e-6 under SSE4.2 / AVX2 / default)
TOL_FUSED_RUN = 1e-4
# rad: start trajectories (q_ls) of the paper's reduced problems built in float32 (LAPACK, and the
# accelerators' Jacobi SVDs) vs float64 (100 conditions of the catching config's generation 1).
# Measured 2.4e-4 on both paths (1.5e-4 on the same problems' bases from an H100); on the first
# 100 of `PAPER_CONDITIONS`, SSE4.2 / AVX2 / default (= AVX2 there) on a 2-core AMD EPYC:
# 3.4e-4 / 1.6e-4 / 1.6e-4, both paths, masks equal in each; on the shipped demonstrations
# (`demonstrations.shipped`, another synthesis' last bits): 1.1e-3 / 6.1e-4 / 6.1e-4. With the end
# slopes taken from the samples themselves instead of their differences to the end sample, the
# masks differ, and on the H100's bases q_ls was 0.32 rad off (CPU build) and 0.77 rad (H100).
TOL_PAPER_START = 2e-3
# The catching config's compiler (BFGS, 30 iterations) on the paper's problems of generation 1:
# `PAPER_CONDITIONS` of them, the first `PAPER_SLSQP` also solved by float64 SLSQP. The problems
# themselves differ from one CPU to another: float32 PCA rounding turns the components by ~1e-3
# rad, and the reduced problems' BC solve amplifies that (start trajectories 0.05-0.8 rad apart,
# free directions different in 63 of 100), so the optima differ by ~10 % (median) between CPUs
# and each of these problems can fall into another local minimum, on either side. A percentile of
# 100 gaps in the dense part of their distribution moves with that: the 75th, once asserted here
# <= 1.5e-4, read 0.0074 % on one 2-core EPYC, 0.022 % on an AVX-512 EPYC and 0.030 % in a draw
# under SSE4.2, while with BFGS's model restarted after a rejected step (the code before
# CHANGELOG.md's "BFGS keeps its model") it read 0.010-0.23 % over the same draws. Hence
# quantities that such switches cannot flip. Values below, "SSE4.2 / AVX2 / default (= AVX2
# on that CPU, bit-identical) / AVX", measured with `--xla_cpu_max_isa` on one 2-core AMD EPYC
# (AVX2); "restart": the same runs with the model restarted.
PAPER_CONDITIONS = 300
PAPER_SLSQP = 100
# Budget: how many of the `PAPER_CONDITIONS` stop at the iteration budget unconverged: 51 / 45 /
# 45 / 49; restart 74 / 77 / 77 / 80. (Over 100 problems the same count read 11-23, restart
# 18-33: 300 it takes to tell them apart. Of those stopped, the same optimiser given 300
# iterations ends more than 0.03 % lower on 27 / 24 / 24 / 28, restart 57 / 55 / 55 / 56.)
TOL_PAPER_AT_BUDGET = 62
# Relative gap to float64 SLSQP over the first `PAPER_SLSQP`: its median (typical problems end
# at the float64 optimum; -1.9e-5 / -2.4e-6 / -2.4e-6 / -4.8e-5, and within +-4.8e-5 in all 9
# draws of 100 measured, restart included) and how many end more than 1 % above it (other local
# minima, SLSQP's on the other side as often: 3 / 6 / 6 / 7, 3-11 in the 9 draws; restart 4-16).
TOL_PAPER_MEDIAN = 2e-4
TOL_PAPER_ABOVE_1PCT = 15
# Of the `PAPER_CONDITIONS`, how many may end outside their joint limits (rejected, as the
# evolution rejects such offspring): a problem stopped at the budget on the edge of a limit is
# inside or 4e-4 rad outside depending on the CPU's rounding. 2 / 2 / 2 / 2 before the
# optimiser went through the interpolation and kept it where it ended worse (CHANGELOG.md); since,
# 0 under the default ISA (AVX2; at the budget 52, above 1 % 4 of 100, median gap 3.4e-6; the
# other ISAs not measured again).
TOL_PAPER_OUTSIDE = 5


def synthetic_demos(robot, dyn, rng):
    """Rest-to-rest minimum-jerk demonstrations with a smooth bump, and their hand positions."""
    lo, hi = np.asarray(robot.lower), np.asarray(robot.upper)
    rest = np.asarray(robot.rest)
    final = rest + rng.uniform(0.3, 1.0, (N_DEMOS, len(lo))) * (0.7 * hi - rest)
    s = np.linspace(0.0, 1.0, T)[None, :, None]
    shape = s**3 * (10 - 15 * s + 6 * s**2)
    bump = (s * (1 - s)) ** 2 * rng.standard_normal((N_DEMOS, 1, len(lo))) * 2.0
    q = (rest + (final[:, None] - rest) * shape + bump).astype(np.float32)
    pos = jax.vmap(lambda qq: dyn.site_pose(qq)[0])(jnp.asarray(q[:, -1]))
    return q, np.asarray(pos), rng.uniform(0.8, 1.2, N_DEMOS).astype(np.float32)


def reduced(basis, boundary, grid, *static, **kw):
    """`reduced_problems` as one program (run eagerly, each of its operations compiles alone)."""
    return jax.jit(lambda b, bc: reduced_problems(b, bc, grid, *static, **kw))(basis, boundary)


@pytest.fixture(scope="module")
def setup():
    robot = load_robot("mahru_arm", joints=JOINTS)
    dyn = make_dynamics(robot, "rnea")
    grid = make_time_grid(T)
    rng = np.random.default_rng(0)
    q, cond, dur = synthetic_demos(robot, dyn, rng)
    # Limits: the demonstrations' envelope plus 0.15 rad, so that torque-optimal motions press on
    # them (unconstrained optima leave the ranges, PROBES.md) and the limit handling is exercised.
    lower = np.maximum(q.min(axis=(0, 1)) - 0.15, robot.lower).astype(np.float64)
    upper = np.minimum(q.max(axis=(0, 1)) + 0.15, robot.upper).astype(np.float64)
    targets = cond[:8] + rng.normal(0, 0.01, (8, 3)).astype(np.float32)
    targets[6] = np.nan  # selects no neighbour: NaN basis
    nb = jax.jit(select_neighbours, static_argnums=(3, 4))(
        jnp.asarray(cond), jnp.ones(N_DEMOS, bool), jnp.asarray(targets), 8, 0.15
    )
    basis = jax.jit(pca_basis, static_argnums=3)(jnp.asarray(q), jnp.asarray(dur), nb, K)
    qf = np.clip(q[:8, -1] + rng.normal(0, 0.05, (8, 3)), lower + 0.05, upper - 0.05)
    qf[5, 1] = np.nan
    qf[7, 2] = upper[2] + 0.3
    z = np.zeros((8, 3), np.float32)
    rest = np.broadcast_to(np.asarray(robot.rest, np.float32), (8, 3))
    boundary = Boundary(*(jnp.asarray(a, jnp.float32) for a in (rest, qf, z, z, dur[:8])))
    compile_fn = make_optimisation_compiler(dyn, grid, lower, upper, OptimSettings())
    out = compile_fn(basis, boundary)
    return dict(robot=robot, dyn=dyn, grid=grid, basis=basis, boundary=boundary, lower=lower,
                upper=upper, compile_fn=compile_fn, out=out)  # fmt: skip


def test_settings_validation():
    assert OptimSettings().method == "newton"
    bad = [
        ("method", "sgd"), ("max_iters", 0), ("learning_rate", 0.0), ("limit_margin", -0.1),
        ("n_starts", 0), ("hessian_every", 0), ("bc_leak", 2.0), ("n_components", 0),
        ("max_free_per_joint", 5), ("search_stride", 0), ("max_batch", 0), ("max_batch", 2.5),
        ("initial_model", "newton"),
    ]  # fmt: skip
    for field, value in bad:
        with pytest.raises(ValueError, match=f"^{field}: expected"):
            OptimSettings(**{field: value})
    with pytest.raises(UserError, match="joint limits: expected finite limits"):
        validate_limits(np.array([0.0, 1.0]), np.array([1.0, 0.5]), 2)


def _central_differences(f, z, prob, h: float = 1e-6) -> np.ndarray:
    """Central differences (step ``h``) of ``f(z, prob)`` in ``z``'s free entries (``prob.mask``;
    zero elsewhere)."""
    fd = np.zeros(z.shape)
    for idx in zip(*np.nonzero(np.asarray(prob.mask)), strict=True):
        e = jnp.zeros_like(z).at[idx].set(h)
        fd[idx] = (f(z + e, prob) - f(z - e, prob)) / (2 * h)
    return fd


def test_gradient_in_null_space_matches_finite_differences(setup, x64):
    s = setup
    dyn = make_dynamics(s["robot"], "rnea", jnp.float64)
    problems, _ = _f64_problems(s)
    # Tight limits so that the penalty term is active in the gradient too.
    lo, hi = s["lower"] + 0.2, s["upper"] - 0.2
    objective = make_objective(dyn, lo, hi, 1e3)
    rng = np.random.default_rng(1)
    f = jax.jit(lambda z, prob: objective(z, prob)[0])
    grad_f = jax.jit(jax.grad(f))
    for c in range(2):
        prob = jax.tree_util.tree_map(lambda a, c=c: a[c], problems)
        z = jnp.asarray(rng.normal(0, 0.2, prob.mask.shape)) * prob.mask
        grad = np.asarray(grad_f(z, prob))
        fd = _central_differences(f, z, prob)
        assert np.abs(grad - fd).max() <= TOL_GRAD * max(1.0, np.abs(fd).max())
        assert np.abs(fd).max() > 0  # a real check: the gradient is not trivially zero


@pytest.fixture(scope="module")
def slsqp(setup):
    """The float64 SLSQP reference of the well-posed conditions (default settings)."""
    s = setup
    take = jax.tree_util.tree_map(lambda a: a[:GOOD], (s["basis"], s["boundary"]))
    ref = solve_reference(s["robot"], s["grid"], *take, OptimSettings(), lower=s["lower"],
                          upper=s["upper"])  # fmt: skip
    # SLSQP stops either on ftol or when its line search cannot improve further (converged to
    # float64 precision); it must not run out of iterations.
    assert (ref.iterations < SLSQP_MAXITER).all()
    return ref


def _compile_logs(records) -> list[str]:
    return [r.getMessage() for r in records if "ompil" in r.getMessage()]


def test_reference_solver_compiles_only_in_its_first_call(setup, slsqp, caplog):
    """The timed SLSQP baseline (`benchmarks/generations_per_sec.py`) must time solves, not XLA:
    after its first call a `ReferenceSolver` compiles nothing, whatever the batch size, and its
    kept programs give the one-shot `solve_reference` answers."""
    s = setup
    solver = ReferenceSolver(
        s["robot"], s["grid"], OptimSettings(), "jax", lower=s["lower"], upper=s["upper"]
    )
    batch = jax.tree_util.tree_map(lambda a: a[:GOOD], (s["basis"], s["boundary"]))
    first = jax.tree_util.tree_map(lambda a: a[:1], batch)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        solver(*first)
    assert _compile_logs(caplog.records)  # the check sees compiles where there are some
    caplog.clear()
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        ref = solver(*batch)
    assert _compile_logs(caplog.records) == []
    np.testing.assert_allclose(ref.cost, slsqp.cost, rtol=TOL_SAME_SOLVE)
    np.testing.assert_array_equal(ref.iterations, slsqp.iterations)


def gap_to_slsqp(setup, ref, out) -> np.ndarray:
    """Relative float64 eq. 5 cost gap of ``out``'s well-posed conditions to ``ref``."""
    s = setup
    ours = torque_costs_f64(s["robot"], s["grid"], out.q[:GOOD], s["boundary"].duration[:GOOD])
    gap = (ours - ref.cost) / ref.cost
    print("gap to SLSQP:", np.round(gap * 100, 4), "%")
    return gap


def test_matches_float64_slsqp(setup, slsqp):
    s, ref = setup, slsqp
    out = s["out"]
    good = slice(0, GOOD)
    assert gap_to_slsqp(s, ref, out).max() <= TOL_GAP
    assert np.asarray(out.within_limits[good]).all()
    # The limits bind for some condition, else this test would not check the limit handling.
    assert ref.max_violation.max() < 1e-6
    near = np.min(np.minimum(ref.q - (s["lower"] + 0.02), (s["upper"] - 0.02) - ref.q), axis=(1, 2))
    assert (near < 1e-4).any()


def test_result_is_consistent_and_meets_bcs(setup):
    s = setup
    out = s["out"]
    good = slice(0, GOOD)
    assert np.asarray(out.finite[good]).all()
    q, bc = (
        np.asarray(out.q[good]),
        jax.tree_util.tree_map(lambda a: np.asarray(a[good]), s["boundary"]),
    )
    assert (
        np.abs(q[:, 0] - bc.q0).max() <= TOL_BC_POS and np.abs(q[:, -1] - bc.qf).max() <= TOL_BC_POS
    )
    assert np.asarray(out.bc_residual[good]).max() <= TOL_BC_VEL
    cost = jax.vmap(lambda q, d: torque_cost(s["dyn"], s["grid"], q, d))(
        out.q[good], s["boundary"].duration[good]
    )
    np.testing.assert_allclose(np.asarray(out.cost[good]), np.asarray(cost), rtol=TOL_COST)
    assert (np.asarray(out.iterations[good]) >= 1).all()


def test_bad_inputs_are_flagged(setup):
    out = setup["out"]
    assert not bool(out.finite[5])  # NaN boundary condition
    assert not bool(out.finite[6])  # no valid neighbour: NaN basis
    assert bool(out.finite[7]) and not bool(out.within_limits[7])  # BC outside the joint range
    assert np.asarray(out.within_limits[:GOOD]).all()


def test_second_call_does_not_recompile(setup):
    s = setup
    fn = s["compile_fn"]
    before = fn._cache_size()
    shifted = s["boundary"]._replace(duration=s["boundary"].duration * 1.1)
    jax.block_until_ready(fn(s["basis"], shifted))
    assert fn._cache_size() == before == 1


def _interpolation(s):
    """The interpolation compiler's answer (eq. 1-2, K = 3) on the setup's problems: ``(q, cost,
    within limits)``."""
    interp = compile_interpolation(s["basis"], s["boundary"], s["grid"], 3)
    cost = jax.vmap(lambda q, d: torque_cost(s["dyn"], s["grid"], q, d))(
        interp.q, s["boundary"].duration
    )
    q = np.asarray(interp.q, np.float64)
    within = np.all((q >= s["lower"]) & (q <= s["upper"]), axis=(1, 2))
    return np.asarray(interp.q), np.asarray(cost), within


def test_never_above_the_interpolation_nor_outside_its_limits(setup):
    """The interpolation's answer is the optimiser's start and a candidate of its own: an
    optimiser that ends above it or outside the limits (Adam with far too long steps, a few of
    them) returns it instead, and the default optimiser never ends above it."""
    s = setup
    good = slice(0, GOOD)
    q_int, c_int, within_int = (a[good] for a in _interpolation(s))
    assert within_int.all()  # the start is inside the limits: so must every result be
    wild = OptimSettings(method="adam", max_iters=3, learning_rate=5.0)
    out = make_optimisation_compiler(s["dyn"], s["grid"], s["lower"], s["upper"], wild)(
        s["basis"], s["boundary"]
    )
    q = np.asarray(out.q[good])
    kept = np.abs(q - q_int).max(axis=(1, 2)) <= TOL_START_Q
    # Plain optimisation would have returned more than the start here (a tie goes to it).
    assert kept.any()
    for res in (out, s["out"]):
        assert (np.asarray(res.cost[good]) <= c_int * (1 + TOL_COST)).all()
        assert np.asarray(res.within_limits[good]).all()
    np.testing.assert_allclose(np.asarray(out.cost[good])[kept], c_int[kept], rtol=TOL_COST)


def test_chunks_cover_the_batch_in_order():
    """`optimise_in_chunks` hands each problem (and its initial model, where given) to exactly
    one chunk of at most ``max_batch`` and returns the results in the batch's order (a solve
    that tags each row with its problem)."""
    sizes = []

    def solve(problems, z0, free, initial):
        sizes.append(z0.shape[0])
        tag = problems if initial is None else problems + initial[:, 0, 0]
        return SolverResult(z=z0 + tag[:, None], f=tag, iterations=free[:, 0], converged=free[:, 1])

    b, n = 11, 2
    problems = jnp.arange(b, dtype=jnp.float32) * 10
    z0 = jnp.ones((b, n))
    free = jnp.tile(jnp.arange(b)[:, None] % 3 == jnp.arange(n), (1, 1))
    initial = jnp.arange(b, dtype=jnp.float32)[:, None, None] * 1000 * jnp.ones((1, n, n))
    for model in (None, initial):
        tag = problems if model is None else problems + model[:, 0, 0]
        for max_batch, chunk in [(None, b), (b, b), (4, 4), (5, 4), (10, 6), (1, 1)]:
            sizes.clear()
            chunked = functools.partial(optimise_in_chunks, solve, max_batch=max_batch)
            res = jax.jit(chunked)(problems, z0, free, initial=model)
            assert sizes == [chunk], (max_batch, sizes)
            np.testing.assert_array_equal(np.asarray(res.z), np.asarray(z0 + tag[:, None]))
            np.testing.assert_array_equal(np.asarray(res.f), np.asarray(tag))
            np.testing.assert_array_equal(np.asarray(res.iterations), np.asarray(free[:, 0]))
            np.testing.assert_array_equal(np.asarray(res.converged), np.asarray(free[:, 1]))


def test_accelerator_loop_in_chunks_gives_the_whole_batch_results(setup, monkeypatch):
    """The fixture's 8 conditions (bad ones among them) optimised as on accelerators (a loop of
    fixed trip count, `compiler.optimisation.fixed_trip_loops`) and in chunks of 3 find what the
    whole
    batch found with the CPU's loop: passes after the batch is done change nothing, and each
    problem's result does not depend on its batch (up to rounding)."""
    s = setup
    calls = []
    monkeypatch.setattr(optim_module, "fixed_trip_loops", lambda: calls.append(1) or True)
    settings = OptimSettings(max_batch=3)
    out = make_optimisation_compiler(s["dyn"], s["grid"], s["lower"], s["upper"], settings)(
        s["basis"], s["boundary"]
    )
    assert calls  # traced the accelerators' loop
    assert_same_results(out, s["out"])


def assert_same_results(out, ref) -> None:
    """Two runs of the same problems: the same flags; iterations, costs and trajectories equal up
    to the rounding of a differently batched program (`TOL_CHUNKS_ITERS`, `TOL_CHUNKS`,
    `TOL_CHUNKS_Q`)."""
    for name in ("finite", "within_limits", "converged"):
        np.testing.assert_array_equal(
            np.asarray(getattr(out, name)), np.asarray(getattr(ref, name))
        )
    iters = np.asarray(out.iterations).astype(int) - np.asarray(ref.iterations)
    assert np.abs(iters).max() <= TOL_CHUNKS_ITERS
    np.testing.assert_allclose(np.asarray(out.cost), np.asarray(ref.cost), rtol=TOL_CHUNKS)
    np.testing.assert_allclose(np.asarray(out.q), np.asarray(ref.q), atol=TOL_CHUNKS_Q)


def test_bfgs_matches_float64_slsqp_in_both_loops(setup, slsqp, monkeypatch):
    """The BFGS method (two-dimensional subspace steps) on the well-posed conditions: within
    `TOL_GAP` of float64 SLSQP with the CPU's loop, and the accelerators' loop (fixed trip
    count, in chunks of 3) finds the same on all 8 conditions."""
    s = setup
    args = (s["dyn"], s["grid"], s["lower"], s["upper"])
    cpu = make_optimisation_compiler(*args, OptimSettings(method="bfgs"))(s["basis"], s["boundary"])
    assert gap_to_slsqp(s, slsqp, cpu).max() <= TOL_GAP
    assert np.asarray(cpu.within_limits[:GOOD]).all()
    monkeypatch.setattr(optim_module, "fixed_trip_loops", lambda: True)
    fixed = make_optimisation_compiler(*args, OptimSettings(method="bfgs", max_batch=3))(
        s["basis"], s["boundary"]
    )
    assert_same_results(fixed, cpu)


def _spd_batch(rng, b, n):
    a = rng.standard_normal((b, n, n))
    return a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(n)


def test_subspace_step_minimises_the_model_on_its_plane(x64):
    """`subspace_step` (the BFGS method's step), float64 against numpy: the Newton step where it
    fits; else the minimum of the model on the circle of the radius in the plane of ``g`` and
    the Newton step (dense search over the angle), for radii below the Cauchy point's length,
    between it and the Newton step's, and for a model with no plane (``B = 2 I``)."""
    rng = np.random.default_rng(1)
    bm, g = _spd_batch(rng, 4, 6), rng.standard_normal((4, 6))
    bm[3] = 2.0 * np.eye(6)
    newton = -np.linalg.solve(bm, g[..., None])[..., 0]
    gbg = np.einsum("bi,bij,bj->b", g, bm, g)
    cauchy = -(np.sum(g * g, axis=1) / gbg)[:, None] * g
    ln, lc = np.linalg.norm(newton, axis=1), np.linalg.norm(cauchy, axis=1)
    assert (lc[:3] < ln[:3]).all()  # else the middle case below is not one
    radius = np.array([1.5 * ln[0], 0.5 * lc[1], 0.5 * (lc[2] + ln[2]), 0.5 * ln[3]])
    p, pred, decrement = (
        np.asarray(a) for a in subspace_step(*map(jnp.asarray, (bm, newton, g, radius)))
    )

    def model(x, i):
        return g[i] @ x + 0.5 * x @ bm[i] @ x

    np.testing.assert_allclose(p[0], newton[0], rtol=TOL_LINALG)
    np.testing.assert_allclose(p[3], radius[3] * newton[3] / ln[3], rtol=TOL_LINALG)
    theta = np.linspace(0.0, 2 * np.pi, 200_001)
    for i in (1, 2):
        plane = np.linalg.qr(np.stack([g[i], newton[i]], axis=1))[0]  # (n, 2) orthonormal
        np.testing.assert_allclose(plane @ (plane.T @ p[i]), p[i], atol=TOL_LINALG)
        np.testing.assert_allclose(np.linalg.norm(p[i]), radius[i], rtol=TOL_CIRCLE)
        circle = radius[i] * (plane @ np.stack([np.cos(theta), np.sin(theta)]))  # (n, S)
        values = g[i] @ circle + 0.5 * np.einsum("ns,nm,ms->s", circle, bm[i], circle)
        np.testing.assert_allclose(model(p[i], i), values.min(), rtol=TOL_CIRCLE)
    np.testing.assert_allclose(pred, [-model(p[i], i) for i in range(4)], rtol=TOL_LINALG)
    np.testing.assert_allclose(decrement, -0.5 * np.sum(g * newton, axis=1), rtol=TOL_LINALG)


def test_closed_form_2x2_eigh_matches_numpy(x64):
    """`eigh_2x2` against ``np.linalg.eigh``: random symmetric matrices, a multiple of the
    identity (any basis), diagonal ones in either order, and an ill-conditioned positive
    definite one, whose small eigenvalue must keep its relative accuracy (``mean - radius``
    errs by ~3e-5 there)."""
    rng = np.random.default_rng(3)
    a, b, c = rng.standard_normal((3, 50))
    a[:3], b[:3], c[:3] = [2.0, 1.0, 3.0], [0.0, 0.0, 0.0], [2.0, 3.0, 1.0]
    a[3], b[3], c[3] = 1e12, 1e5, 1.0  # eigenvalues ~1e12 and ~0.99
    m = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)
    e, v = (np.asarray(x) for x in eigh_2x2(*map(jnp.asarray, (a, b, c))))
    ref = np.linalg.eigvalsh(m)
    np.testing.assert_allclose(e[:3], ref[:3], rtol=TOL_LINALG)
    np.testing.assert_allclose(e[3], ref[3], rtol=1e-8)
    np.testing.assert_allclose(e, ref, atol=TOL_LINALG * np.abs(ref).max())
    np.testing.assert_allclose(m @ v, v * e[:, None, :], atol=TOL_LINALG)
    np.testing.assert_allclose(np.swapaxes(v, 1, 2) @ v, np.broadcast_to(np.eye(2), m.shape),
                               atol=TOL_LINALG)  # fmt: skip


def test_bfgs_update_meets_the_secant_condition(x64):
    """`bfgs_update`: where accepted, the model meets the secant condition of its damped pair
    (``B s = y`` where Powell's damping leaves ``y`` as it is) and stays symmetric; elsewhere it
    stays. One pair has ``s.y < 0``, so is damped and must keep the model positive definite."""
    rng = np.random.default_rng(2)
    bm, s = _spd_batch(rng, 4, 5), rng.standard_normal((4, 5))
    y = np.einsum("bij,bj->bi", bm, s) + 0.1 * rng.standard_normal((4, 5))
    y[1] = -y[1]
    assert s[1] @ y[1] < 0
    accept = np.array([True, True, False, True])
    new_b = np.asarray(bfgs_update(*map(jnp.asarray, (bm, s, y, accept))))
    for i in (0, 3):
        np.testing.assert_allclose(new_b[i] @ s[i], y[i], rtol=TOL_LINALG * 1e3)
    np.testing.assert_allclose(new_b, np.swapaxes(new_b, 1, 2), atol=TOL_LINALG)
    np.testing.assert_allclose(new_b[2], bm[2], rtol=0)
    assert np.linalg.eigvalsh(new_b[1]).min() > 0  # damped: still positive definite
    assert not np.allclose(new_b[1], bm[1])


def test_cholesky_solve_matches_numpy(x64):
    """`cholesky_solve` (unrolled, elementwise) against ``np.linalg.solve`` on positive definite
    matrices, one of them ill-conditioned (1e8); an indefinite matrix is flagged, not solved."""
    rng = np.random.default_rng(4)
    a, b = _spd_batch(rng, 5, 7), rng.standard_normal((5, 7))
    a[3] = a[3] @ np.diag(np.logspace(0, 4, 7)) @ a[3].T / 7 + 1e-4 * np.eye(7)
    a[4] = np.diag([1.0, 2.0, -1.0, 3.0, 1.0, 1.0, 1.0])
    x, ok = (np.asarray(v) for v in cholesky_solve(jnp.asarray(a), jnp.asarray(b)))
    np.testing.assert_array_equal(ok, [True, True, True, True, False])
    expect = np.linalg.solve(a[:4], b[:4, :, None])[..., 0]
    cond = np.linalg.cond(a[:4])
    assert cond.max() > 1e6  # the ill-conditioned case is one
    err = np.abs(x[:4] - expect).max(axis=1) / np.abs(expect).max(axis=1)
    assert (err <= TOL_LINALG * cond).all(), err


@pytest.mark.parametrize("stride", [1, 3, 5])
def test_search_objective_is_the_quadrature_of_eq5(setup, stride):
    """The search objective (node arrays linear in z) equals the trapezoid rule on its nodes of the
    torques of the full trajectory; with stride 1 that is eq. 5 itself."""
    s = setup
    take = jax.tree_util.tree_map(lambda a: a[:GOOD], (s["basis"], s["boundary"]))
    problems, _, _ = reduced(*take, s["grid"], K, max_free=2, stride=stride)
    idx, w = search_nodes(s["grid"], stride)
    assert idx[0] == 0 and idx[-1] == T - 1 and abs(w.sum() - 1) < 1e-6
    objective = make_objective(s["dyn"], s["lower"], s["upper"], 0.0)
    z = jnp.asarray(np.random.default_rng(2).normal(0, 0.1, problems.mask.shape), jnp.float32)
    z = z * problems.mask
    cost = jax.vmap(lambda zz, p: objective(zz, p)[1])(z, problems)
    q = jax.vmap(problem_trajectory)(problems, z)
    tau = jax.vmap(lambda qq, d: trajectory_torques(s["dyn"], s["grid"], qq, d))(
        q, problems.duration
    )
    expect = 0.5 * problems.duration * jnp.sum(w * jnp.sum(tau[:, idx] ** 2, -1), axis=1)
    np.testing.assert_allclose(np.asarray(cost), np.asarray(expect), rtol=TOL_COST)
    if stride == 1:
        full = jax.vmap(lambda qq, d: torque_cost(s["dyn"], s["grid"], qq, d))(q, problems.duration)
        np.testing.assert_allclose(np.asarray(cost), np.asarray(full), rtol=TOL_COST)


def test_strided_search_finds_the_full_optimum(setup):
    """Optimising on every 2nd sample (and 2 free directions per joint) lands where the full
    search does: eq. 5 on all samples within `TOL_STRIDE`; the returned cost is eq. 5. (The
    basis of this setup spans fewer than K directions: a free but motionless null column must
    not take one of the 2 slots.)"""
    s = setup
    take = jax.tree_util.tree_map(lambda a: a[:GOOD], (s["basis"], s["boundary"]))
    settings = OptimSettings(search_stride=2, max_free_per_joint=2)
    out = make_optimisation_compiler(s["dyn"], s["grid"], s["lower"], s["upper"], settings)(*take)
    full = np.asarray(s["out"].cost[:GOOD])
    assert np.asarray(out.within_limits).all() and (np.asarray(out.iterations) > 0).all()
    assert (np.asarray(out.cost) <= full * (1 + TOL_STRIDE)).all()
    cost = jax.vmap(lambda q, d: torque_cost(s["dyn"], s["grid"], q, d))(out.q, take[1].duration)
    np.testing.assert_allclose(np.asarray(out.cost), np.asarray(cost), rtol=TOL_COST)


def test_accelerator_path_matches_lapack(setup, monkeypatch):
    """The GPU code path (one-sided Jacobi SVDs in the BC solve and the null directions, Jacobi
    eigh of the 9 x 9 trust-region models: no solver call per matrix) gives the same problems and
    the same optima as LAPACK's (the fixture's run)."""
    s = setup
    take = jax.tree_util.tree_map(lambda a: a[:GOOD], (s["basis"], s["boundary"]))
    settings = OptimSettings()
    free = settings.max_free_per_joint

    def problems():  # traced anew: after the patch, the other code path
        return reduced(*take, s["grid"], K, max_free=free)[0]

    ref = problems()
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: True)
    acc = problems()
    np.testing.assert_array_equal(np.asarray(acc.mask), np.asarray(ref.mask))
    np.testing.assert_allclose(np.asarray(acc.q_ls), np.asarray(ref.q_ls), atol=1e-5)
    # Directions are unique up to rotations within a joint's span: compare the projectors.
    proj = [np.einsum("cjft,cjfu->cjtu", p.dirs, p.dirs) for p in (acc, ref)]
    np.testing.assert_allclose(proj[0], proj[1], atol=1e-4 * T)
    out = make_optimisation_compiler(s["dyn"], s["grid"], s["lower"], s["upper"], settings)(*take)
    np.testing.assert_allclose(
        np.asarray(out.cost), np.asarray(s["out"].cost[:GOOD]), rtol=TOL_JACOBI
    )
    assert np.asarray(out.within_limits).all()


def _first_order_case(s, method: str):
    """``(problems, settings, limits)`` of the first-order tests: the setup's first 2 problems, 40
    iterations of ``method`` without a limit penalty, inside joint ranges wide enough never to
    bind."""
    take = jax.tree_util.tree_map(lambda a: a[:2], (s["basis"], s["boundary"]))
    settings = OptimSettings(method=method, max_iters=40, limit_penalty=0.0)
    return take, settings, (np.asarray(s["lower"]) - 10.0, np.asarray(s["upper"]) + 10.0)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["adam", "lbfgs"])
def test_first_order_methods_run_on_the_fused_search_gradient(setup, method):
    """Adam and L-BFGS (optax) through `make_search_value`'s custom VJP (the scalar RNEA layout,
    as on accelerators) reach the optima they reach through autodiff of the vector layout (on
    `_first_order_case`'s problems: the vector layout's program is
    `test_first_order_methods_improve_on_the_start`'s, compiled once in the test run's cache)."""
    s = setup
    take, settings, limits = _first_order_case(s, method)
    costs = {}
    for form in ("scalar", "vector"):
        dyn = make_dynamics(s["robot"], "rnea", jnp.float32, form)
        assert fused_search_gradient(dyn) == (form == "scalar")
        compile_fn = make_optimisation_compiler(dyn, s["grid"], *limits, settings)
        costs[form] = np.asarray(compile_fn(*take).cost)
    np.testing.assert_allclose(costs["scalar"], costs["vector"], rtol=TOL_FUSED_RUN)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["bfgs", "adam", "lbfgs"])
def test_first_order_methods_improve_on_the_start(setup, method):
    """The comparison optimisers run and lower the cost from the interpolation start (z = 0).
    Without a limit penalty, inside joint ranges wide enough never to bind: a result outside the
    limits that the start keeps would be replaced by the start."""
    s = setup
    take, settings, wide = _first_order_case(s, method)
    out = make_optimisation_compiler(s["dyn"], s["grid"], *wide, settings)(*take)
    problems, _, _ = reduced(
        *take, s["grid"], K, settings.bc_leak, settings.max_free_per_joint,
        interp_components=settings.interp_components,
    )  # fmt: skip
    q0 = jax.vmap(problem_trajectory)(problems, jnp.zeros(problems.mask.shape))
    start = jax.vmap(lambda q, d: torque_cost(s["dyn"], s["grid"], q, d))(q0, take[1].duration)
    assert (np.asarray(out.cost) < 0.99 * np.asarray(start)).all()
    assert np.asarray(out.bc_residual).max() <= TOL_BC_VEL


@pytest.mark.parametrize(
    "method, max_iters, expect",
    [
        ("bfgs", None, DEFAULT_ITERS["bfgs"]),
        ("newton", None, DEFAULT_ITERS["newton"]),
        ("adam", None, DEFAULT_ITERS["adam"]),
        ("newton", 3, 3),
    ],
)
def test_default_iteration_budget_is_per_method(method, max_iters, expect):
    got = OptimSettings(method=method, max_iters=max_iters).resolved()
    assert (got.method, got.max_iters) == (method, expect)
    assert got.resolved() == got  # concrete settings stay as they are


def test_cpu_fast_path_matches_the_default_program(setup):
    """BFGS through `cpu_fast_path` (on CPU: scalar RNEA layout, XLA fusion emitters off for the
    program) finds the optima of the default program, and flags the bad conditions alike;
    Newton keeps the default program. (All 8 conditions: the fast program is then
    `test_bfgs_matches_float64_slsqp_in_both_loops`'s, compiled once in the test run's cache.)"""
    s = setup
    settings = OptimSettings(method="bfgs")
    dyn, options = cpu_fast_path(s["dyn"], settings)
    assert options is not None and dyn is not s["dyn"]  # the test suite runs on CPU
    assert cpu_fast_path(s["dyn"], OptimSettings(method="newton")) == (s["dyn"], None)
    args = (s["dyn"], s["grid"], s["lower"], s["upper"], settings)
    fast = make_optimisation_compiler(*args)(s["basis"], s["boundary"])
    plain = make_optimisation_compiler(*args, fast_path=False)(s["basis"], s["boundary"])
    good = slice(0, GOOD)
    assert np.asarray(fast.converged[good]).all() and np.asarray(plain.converged[good]).all()
    np.testing.assert_allclose(
        np.asarray(fast.cost[good]), np.asarray(plain.cost[good]), rtol=TOL_FAST_PATH
    )
    for name in ("finite", "within_limits", "converged"):
        np.testing.assert_array_equal(
            np.asarray(getattr(fast, name)), np.asarray(getattr(plain, name))
        )


def _f64(tree):
    """``tree`` (e.g. a `Basis`, a `Boundary`, a `TimeGrid`) with its floating-point leaves as
    float64 numpy arrays."""
    return jax.tree_util.tree_map(
        lambda a: np.asarray(a, np.float64) if np.asarray(a).dtype.kind == "f" else a, tree
    )


def _f64_problems(s, n=2, stride=1):
    """The first ``n`` reduced problems of the setup, and a random z, in float64."""
    take = jax.tree_util.tree_map(lambda a: a[:n], (s["basis"], s["boundary"]))
    st = OptimSettings()
    problems = reduced(
        *_f64(take), _f64(s["grid"]), K, st.bc_leak, st.max_free_per_joint, stride=stride
    )[0]
    z = np.random.default_rng(5).normal(0, 0.3, problems.mask.shape) * np.asarray(problems.mask)
    return problems, jnp.asarray(z)


TORQUE_BOUND = 1.0  # [N m] below the test arm's gravity torques: the torque penalty acts


def _active_velocity_bound(problems):
    """A velocity bound ``(J,)`` that half the problems' start speeds cross: the penalty acts."""
    return jnp.asarray(0.5 * np.abs(np.asarray(problems.node_ls[:, 1])).max(axis=(0, 1)))


@pytest.mark.parametrize("velocity", [False, True])
def test_penalty_model_matches_autodiff(setup, x64, velocity):
    """`penalty_model` (closed form, batched) against ``jax.grad`` and ``jax.hessian`` of
    `limit_penalty` at the nodes, with limits tight enough that samples cross them: on q alone,
    and on q and qd (a velocity bound)."""
    s = setup
    problems, z = _f64_problems(s)
    lo, hi = jnp.asarray(s["lower"] + 0.3), jnp.asarray(s["upper"] - 0.3)
    vmax = _active_velocity_bound(problems) if velocity else None
    b, j, f = z.shape
    assert f >= 2  # the blocks' off-diagonal entries are checked too

    def penalty(zf, prob):
        x = prob.node_ls + jnp.einsum("jf,amjf->amj", zf.reshape(j, f), prob.node_dirs)
        out = limit_penalty(prob.node_w, x[0], prob.duration, lo, hi, 1e3)
        if velocity:
            out += limit_penalty(prob.node_w, x[1], prob.duration, -vmax, vmax, 1e3)
        return out

    zf = z.reshape(b, j * f)
    g, h = (np.asarray(a) for a in penalty_model(zf, problems, lo, hi, 1e3, vmax))
    g_ref = np.asarray(jax.vmap(jax.grad(penalty))(zf, problems))
    h_ref = np.asarray(jax.vmap(jax.hessian(penalty))(zf, problems))
    assert np.abs(h_ref).max() > 0  # the penalty acts
    np.testing.assert_allclose(g, g_ref, atol=TOL_LINALG * np.abs(g_ref).max())
    np.testing.assert_allclose(h, h_ref, atol=TOL_LINALG * np.abs(h_ref).max())


@pytest.mark.parametrize("every", [1, 2])
def test_gauss_newton_model_matches_finite_differences(setup, x64, every):
    """`gauss_newton_model` against ``D sum_m w_m J_m^T J_m`` with ``J_m`` the central-difference
    Jacobian of the torques at the nodes it uses (every node, or every 2nd with weights scaled
    to the same total), float64."""
    s = setup
    dyn = make_dynamics(s["robot"], "rnea", jnp.float64)
    problems, z = _f64_problems(s)
    b, j, f = z.shape
    got = np.asarray(gauss_newton_model(dyn, problems, z.reshape(b, j * f), every))
    for c in range(b):
        prob = jax.tree_util.tree_map(lambda a, c=c: a[c], problems)

        def torques(zf, prob=prob):
            x = prob.node_ls + jnp.einsum("jf,amjf->amj", zf.reshape(j, f), prob.node_dirs)
            return np.asarray(jax.vmap(dyn.inverse)(x[0], x[1], x[2]))[::every]  # (M', J)

        zc, h = np.asarray(z[c]).reshape(-1), 1e-6
        jac = np.stack([(torques(zc + h * e) - torques(zc - h * e)) / (2 * h)
                        for e in np.eye(j * f)], axis=-1)  # fmt: skip
        w = np.asarray(prob.node_w)
        w_sub = w[::every] * w.sum() / w[::every].sum()
        expect = float(prob.duration) * np.einsum("m,mji,mjk->ik", w_sub, jac, jac)
        np.testing.assert_allclose(got[c], expect, rtol=TOL_GN, atol=TOL_GN * np.abs(expect).max())


@pytest.mark.parametrize("form", ["vector", "scalar"])
def test_joint_lists_give_the_array_objective(setup, form, monkeypatch):
    """The CPU's joint-by-joint node states (`node_states`, used with the scalar RNEA layout,
    which reads them as they are) give the objective and gradient of one array, for both
    layouts (the vector one stacks the lists)."""
    s = setup
    problems, z = _f64_problems(s)
    problems = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), problems)
    z = z.astype(jnp.float32)
    dyn = make_dynamics(s["robot"], "rnea", jnp.float32, form)
    objective = make_objective(dyn, s["lower"] + 0.3, s["upper"] - 0.3, 1e3)
    assert joint_lists(dyn) == (form == "scalar")  # the test suite runs on CPU

    def value_grad():  # traced anew: joint_lists is read at trace time
        return jax.vmap(jax.value_and_grad(lambda zz, p: objective(zz, p)[0]))(z, problems)

    monkeypatch.setattr(objective_module, "joint_lists", lambda d: True)
    f_lists, g_lists = value_grad()
    monkeypatch.setattr(objective_module, "joint_lists", lambda d: False)
    f_array, g_array = value_grad()
    np.testing.assert_allclose(np.asarray(f_lists), np.asarray(f_array), rtol=TOL_LAYOUT)
    np.testing.assert_allclose(np.asarray(g_lists), np.asarray(g_array),
                               atol=TOL_LAYOUT * np.abs(np.asarray(g_array)).max())  # fmt: skip


def test_fused_search_gradient_matches_autodiff_and_finite_differences(setup, x64):
    """`make_search_value` with the CPU's fused gradient (one reduction over the nodes, the scalar
    RNEA layout's unstacked torques, a custom VJP) against autodiff of `make_objective` (vector
    layout) and central differences, in float64, with joint, velocity and torque limits tight
    enough that the penalty is active; its value alone (the trial steps) too."""
    s = setup
    problems, z = _f64_problems(s)
    lo, hi = jnp.asarray(s["lower"] + 0.2), jnp.asarray(s["upper"] - 0.2)
    vmax = _active_velocity_bound(problems)
    taumax = jnp.full(vmax.shape, TORQUE_BOUND)
    scalar = make_dynamics(s["robot"], "rnea", jnp.float64, "scalar")
    assert fused_search_gradient(scalar)  # the test suite runs on CPU
    vector = make_dynamics(s["robot"], "rnea", jnp.float64, "vector")
    assert not fused_search_gradient(vector)
    fused = make_search_value(scalar, lo, hi, 1e3, "bfgs", vmax, taumax)
    objective = make_objective(vector, lo, hi, 1e3, vmax, taumax)
    no_torque_bound = make_objective(vector, lo, hi, 1e3, vmax)
    reference = jax.jit(jax.vmap(jax.value_and_grad(lambda zz, p: objective(zz, p)[0])))
    f_ref, g_ref = map(np.asarray, reference(z, problems))
    cost_ref = np.asarray(jax.vmap(lambda zz, p: objective(zz, p)[1])(z, problems))
    assert np.all(f_ref > 1.01 * cost_ref)  # the penalty is active
    f_free = np.asarray(jax.vmap(lambda zz, p: no_torque_bound(zz, p)[0])(z, problems))
    assert np.all(f_ref > f_free)  # the torque bound's part of it too
    f, g = map(np.asarray, jax.jit(jax.vmap(jax.value_and_grad(fused)))(z, problems))
    np.testing.assert_allclose(f, f_ref, rtol=TOL_FUSED)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=TOL_FUSED * np.abs(g_ref).max())
    value = np.asarray(jax.jit(jax.vmap(fused))(z, problems))
    np.testing.assert_allclose(value, f_ref, rtol=TOL_FUSED)
    one = jax.tree_util.tree_map(lambda a: a[0], problems)
    fd = _central_differences(jax.jit(fused), z[0], one)
    assert np.abs(g[0] - fd).max() <= TOL_GRAD * np.abs(fd).max()


@pytest.fixture(scope="module")
def paper():
    """The catching config's generation 1 at `PAPER_CONDITIONS` conditions, as the benchmark
    builds it: ``(cfg, robot, dyn, db, conds)``."""
    from benchmarks.generations_per_sec import build
    from evojax_motion.settings import load_config

    return build(load_config("configs/catch_ball.yaml", []), PAPER_CONDITIONS)


@pytest.mark.slow
@pytest.mark.isa_sensitive
def test_paper_problems_built_in_float32_match_float64(paper, monkeypatch):
    """The optimisation compiler's BC rule compares end slopes with `BC_LEAK` ~1e-4; on the paper's
    problems (real bases, T = 100) its float32 build, on either code path, sets up the float64
    build's problem: the same free directions and start trajectories within `TOL_PAPER_START`."""
    from benchmarks.generations_per_sec import generation1_problems

    cfg, robot, dyn, db, conds = paper
    grid, basis, boundary = generation1_problems(cfg, robot, dyn, db, conds, 100)
    st = cfg.compiler

    def problems(b, bc, g):  # `reduced` traces anew each call: the code path and dtype in force
        out = reduced(b, bc, g, st.n_components, st.bc_leak, st.max_free_per_joint)[0]
        return jax.tree_util.tree_map(np.asarray, out)

    with jax.enable_x64(True):
        ref = problems(*_f64((basis, boundary, grid)))
    lapack = problems(basis, boundary, grid)
    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: True)
    jacobi = problems(basis, boundary, grid)
    for p in (lapack, jacobi):
        np.testing.assert_array_equal(p.mask, ref.mask)
        assert np.abs(p.q_ls - ref.q_ls).max() <= TOL_PAPER_START


@pytest.mark.slow
@pytest.mark.isa_sensitive
def test_paper_config_reaches_float64_slsqp_on_paper_problems(paper):
    """The catching config's compiler on the paper problems (see `PAPER_CONDITIONS`): all but
    `TOL_PAPER_AT_BUDGET` of them converge within the iteration budget, the median gap to float64
    SLSQP is within `TOL_PAPER_MEDIAN`, at most `TOL_PAPER_ABOVE_1PCT` of `PAPER_SLSQP` end more
    than 1 % above SLSQP, all within their limits but `TOL_PAPER_OUTSIDE`. The budget count is
    what it measures: it fails when the model is thrown away after a rejected step."""
    from benchmarks.generations_per_sec import generation1_problems

    cfg, robot, dyn, db, conds = paper
    grid, basis, boundary = generation1_problems(cfg, robot, dyn, db, conds, PAPER_CONDITIONS)

    out = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, cfg.compiler)(
        basis, boundary
    )
    ok = np.asarray(out.within_limits) & np.asarray(out.finite)
    at_budget = int(np.sum(~np.asarray(out.converged)))
    first = jax.tree_util.tree_map(lambda a: a[:PAPER_SLSQP], (basis, boundary))
    ref = solve_reference(robot, grid, *first, cfg.compiler, gradient="jax")
    cost = torque_costs_f64(robot, grid, np.asarray(out.q)[:PAPER_SLSQP], first[1].duration)
    gap = ((cost - ref.cost) / ref.cost)[ok[:PAPER_SLSQP]]
    print(
        f"outside {np.sum(~ok)}, at the budget {at_budget} of {PAPER_CONDITIONS}; gap to "
        f"SLSQP: median {np.median(gap):.2e}, above 1 % {np.sum(gap > 0.01)} of {gap.size}"
    )
    assert np.sum(~ok) <= TOL_PAPER_OUTSIDE
    assert at_budget <= TOL_PAPER_AT_BUDGET
    assert abs(np.median(gap)) <= TOL_PAPER_MEDIAN
    assert np.sum(gap > 0.01) <= TOL_PAPER_ABOVE_1PCT


def test_best_start_picks_each_conditions_lowest_value():
    """`best_start`: per condition (start-major rows), the start of lowest finite ``f``; a tie
    goes to the first start, and a condition with no finite value keeps its first."""
    f = np.array(
        [[3.0, 1.0, np.nan, 2.0],  # start 0
         [2.0, 1.0, np.nan, np.inf],  # start 1
         [5.0, 0.5, np.nan, 2.0]],  # start 2
        np.float32,
    )  # fmt: skip
    n_s, c = f.shape
    z = np.arange(n_s * c * 2, dtype=np.float32).reshape(n_s * c, 2)
    res = SolverResult(
        z=jnp.asarray(z),
        f=jnp.asarray(f.reshape(-1)),
        iterations=jnp.arange(n_s * c, dtype=jnp.int32),
        converged=jnp.asarray(np.arange(n_s * c) % 2 == 0),
    )
    best = optim_module.best_start(res, n_s)
    expect = np.array([1, 2, 0, 0])  # rows of each condition's chosen start
    rows = expect * c + np.arange(c)
    np.testing.assert_array_equal(np.asarray(best.z), z[rows])
    np.testing.assert_array_equal(np.asarray(best.iterations), rows)
    np.testing.assert_array_equal(np.asarray(best.converged), rows % 2 == 0)
    np.testing.assert_array_equal(np.asarray(best.f), f.reshape(-1)[rows])
    assert optim_module.best_start(res, 1) is res


def test_more_starts_never_end_higher(setup):
    """With 3 starts the first is the 1-start run (same start, same first model), so the
    returned cost is never above the 1-start result's. These small problems have one minimum
    each (measured: random starts at 0.3 and 1 rad RMS end there too), so the costs agree."""
    s = setup
    good = slice(0, GOOD)
    multi = OptimSettings(n_starts=3, start_scale=1.0)
    out = make_optimisation_compiler(s["dyn"], s["grid"], s["lower"], s["upper"], multi)(
        s["basis"], s["boundary"]
    )
    one, three = np.asarray(s["out"].cost[good]), np.asarray(out.cost[good])
    assert np.asarray(out.within_limits[good]).all()
    assert (three <= one * (1 + TOL_COST)).all()
    np.testing.assert_allclose(three, one, rtol=TOL_COST)
