"""Float64 SciPy SLSQP reference for the movement compiler via optimisation (paper sec. 2.2).

The paper solved eq. 3-5 with DONLP2, a sequential quadratic programming code; this is the same
kind of solver on exactly our reduced problem, in float64, one condition at a time:

- variables: the free null-space coordinates z of the BC system (``compile_optim``'s reduced
  problem, built by the same code from the same basis and boundary, then cast to float64), so the
  BCs hold as well as ours and the feasible set is the same;
- objective: ``0.5 * int |tau|^2 dt`` (eq. 5), divided by its value at the start so that SLSQP's
  ``ftol`` is relative; torques from C MuJoCo's ``mj_inverse`` (a loop over the samples, gradient
  by finite differences: ``gradient="mujoco-fd"``) or from the float64 JAX RNEA with its exact
  gradient (``gradient="jax"``, ~5x faster, same optimum to rounding);
- joint limits: linear inequality constraints ``lower + margin <= q(s_i) <= upper - margin`` on
  the interior samples (the end samples are fixed by the BCs);
- start: z = 0, the same start as ``compile_optim`` (the interpolation compiler's answer, or with
  ``interp_components: 0`` the minimum-norm BC solution).

Usage: ``ref = solve_reference(robot, grid, basis, boundary, settings)``; ``ref.cost (C,)`` is the
float64 torque cost of ``ref.q``. `torque_costs_f64` evaluates any trajectories the same way, so a
relative gap is ``(torque_costs_f64(ours) - ref.cost) / ref.cost``.

Both run on the CPU (SciPy is a CPU solver; on a GPU machine each of its many small float64
gradient calls would wait on a device round trip), with the RNEA layout for CPUs.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from scipy.optimize import minimize

from evojax_motion.compile_options import FULL_LEVEL
from evojax_motion.compiler.basis import Basis
from evojax_motion.compiler.interpolation import Boundary
from evojax_motion.compiler.problems import reduced_problems
from evojax_motion.compiler.search_objective import make_objective
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import Robot, mj_inverse_torques
from evojax_motion.motion.objective import torque_cost
from evojax_motion.motion.timegrid import TimeGrid
from evojax_motion.settings.compiler import OptimSettings

GRADIENTS = ("jax", "mujoco-fd")
SLSQP_FTOL = 1e-12  # on the objective normalised to 1 at the start
SLSQP_MAXITER = 500


class ReferenceResult(NamedTuple):
    """Per condition: ``q (C, T, J)``, ``cost (C,)`` float64 eq. 5 cost, ``success (C,)``,
    ``iterations (C,)``, ``wall_s (C,)`` seconds of SLSQP, ``max_violation (C,)`` [rad] of the
    margin-shrunk limits, ``message`` list of SciPy's messages."""

    q: np.ndarray
    cost: np.ndarray
    success: np.ndarray
    iterations: np.ndarray
    wall_s: np.ndarray
    max_violation: np.ndarray
    message: list


class MujocoCost:
    """``0.5 * D * sum_i w_i |tau_i|^2`` with ``tau`` from C MuJoCo's ``mj_inverse`` (float64)."""

    def __init__(self, robot: Robot, grid: TimeGrid):
        self.robot = robot
        self.data = mujoco.MjData(robot.mj_model)
        self.d1 = np.asarray(grid.d1, np.float64)
        self.d2 = np.asarray(grid.d2, np.float64)
        self.w = np.asarray(grid.w, np.float64)

    def torques(self, q: np.ndarray, duration: float) -> np.ndarray:
        """``q (T, J)`` -> ``tau (T, J)``; uncontrolled joints at ``qpos0``, at rest."""
        qd = self.d1 @ q / duration
        qdd = self.d2 @ q / duration**2
        return mj_inverse_torques(self.robot, q, qd, qdd, self.data)

    def __call__(self, q: np.ndarray, duration: float) -> float:
        tau = self.torques(q, duration)
        return 0.5 * duration * float(self.w @ np.sum(tau**2, axis=1))


def _on_cpu():
    """The context of every float64 computation here: the CPU device (module docstring)."""
    return jax.default_device(jax.devices("cpu")[0])


def _dynamics_f64(robot: Robot):
    return make_dynamics(robot, "rnea", jnp.float64, form="vector")  # the CPU layout


class TorqueCostF64:
    """``cost(q (C, T, J), duration (C,)) -> (C,)``: float64 eq. 5 cost (JAX RNEA, x64), its
    program compiled once per batch size and kept."""

    def __init__(self, robot: Robot, grid: TimeGrid):
        with jax.enable_x64(True), _on_cpu():
            dyn = _dynamics_f64(robot)
            g64 = grid._replace(**{k: np.asarray(v, np.float64) for k, v in grid._asdict().items()})
            self.fn = jax.jit(jax.vmap(lambda qq, dd: torque_cost(dyn, g64, qq, dd)))

    def __call__(self, q, duration) -> np.ndarray:
        with jax.enable_x64(True), _on_cpu():
            out = self.fn(
                jnp.asarray(np.asarray(q, np.float64)),
                jnp.asarray(np.asarray(duration, np.float64)),
            )
            return np.asarray(out)


def torque_costs_f64(robot: Robot, grid: TimeGrid, q, duration) -> np.ndarray:
    """Float64 eq. 5 cost of each ``q (C, T, J)`` with ``duration (C,)`` (JAX RNEA, x64)."""
    return TorqueCostF64(robot, grid)(q, duration)


def solve_reference(
    robot: Robot,
    grid: TimeGrid,
    basis: Basis,
    boundary: Boundary,
    settings: OptimSettings | None = None,
    **options,
) -> ReferenceResult:
    """SLSQP on every condition of the batch (see the module docstring). Float64 throughout.

    ``options``: ``gradient``, ``maxiter``, ``ftol``, ``lower``, ``upper`` of `ReferenceSolver`.
    One call, one solver (its programs are compiled in this call); to time solves without
    compiling, keep a `ReferenceSolver` and call it again.
    """
    return ReferenceSolver(robot, grid, settings, **options)(basis, boundary)


class ReferenceSolver:
    """``solver(basis, boundary) -> ReferenceResult``: `solve_reference` with its compiled
    programs kept between calls, as a user's own SLSQP loop would keep them.

    Every program works on one condition at a time (the reduced problem's build, the float64
    value and gradient, the returned cost), so after one call of any batch size no later call
    compiles anything: a baseline timed with it times the solves, not XLA. ``gradient``: of
    ``GRADIENTS``; ``lower``, ``upper``: joint limits ``(J,)`` [rad], default the robot's; the
    constraints use them shrunk by ``settings.limit_margin``.
    """

    def __init__(
        self,
        robot: Robot,
        grid: TimeGrid,
        settings: OptimSettings | None = None,
        gradient: str = "jax",
        maxiter: int = SLSQP_MAXITER,
        ftol: float = SLSQP_FTOL,
        lower=None,
        upper=None,
    ):
        if gradient not in GRADIENTS:
            raise ValueError(f"gradient: expected one of {GRADIENTS}, got {gradient!r}")
        self.gradient = gradient
        self.maxiter, self.ftol = maxiter, ftol
        st = OptimSettings() if settings is None else settings
        lower = robot.lower if lower is None else lower
        upper = robot.upper if upper is None else upper
        self.lo = np.asarray(lower, np.float64) + st.limit_margin
        self.hi = np.asarray(upper, np.float64) - st.limit_margin
        # The reduced problem is built as the compiler builds it (same dtype, device and matmul
        # precision, so the same binding BC directions, start and null space), then solved in
        # float64 on the CPU.
        self.build = jax.jit(
            exact_matmuls(
                lambda b, bc: reduced_problems(
                    b,
                    bc,
                    grid,
                    st.n_components,
                    st.bc_leak,
                    st.max_free_per_joint,
                    interp_components=st.interp_components,
                )[0]
            )
        )
        with jax.enable_x64(True), _on_cpu():
            dyn = _dynamics_f64(robot)
            objective = make_objective(dyn, self.lo, self.hi, 0.0)
            # Called once per SLSQP evaluation, thousands of times a batch: at XLA's full level
            # even where XLA_FLAGS lowers it (the test run: 100 paper problems 7 -> 17 s at 0).
            self.value_and_grad = jax.jit(
                jax.value_and_grad(lambda z, prob: objective(z, prob)[1]),
                compiler_options=FULL_LEVEL,
            )
        self.cost = TorqueCostF64(robot, grid)
        self.mj_cost = MujocoCost(robot, grid) if gradient == "mujoco-fd" else None

    def __call__(self, basis: Basis, boundary: Boundary) -> ReferenceResult:
        c = jax.tree_util.tree_leaves(boundary)[0].shape[0]
        results = [self._solve_one(basis, boundary, i) for i in range(c)]
        q, cost, success, iters, wall, viol, messages = zip(*results, strict=True)
        return ReferenceResult(
            np.stack(q), np.array(cost), np.array(success), np.array(iters, np.int64),
            np.array(wall), np.array(viol), list(messages),
        )  # fmt: skip

    def _solve_one(self, basis: Basis, boundary: Boundary, i: int):
        one = jax.tree_util.tree_map(lambda a: a[i : i + 1], (basis, boundary))
        prob = jax.tree_util.tree_map(
            lambda a: np.asarray(a[0], np.float64) if a.dtype.kind == "f" else np.asarray(a[0]),
            self.build(*one),
        )
        with jax.enable_x64(True), _on_cpu():
            return self._slsqp(prob)

    def _slsqp(self, prob):
        lo, hi = self.lo, self.hi
        t, j = prob.q_ls.shape
        mask = prob.mask
        free = np.flatnonzero(mask.reshape(-1))
        # q(z) = q_ls + M z_free: the (T*J, n_free) matrix of the free directions.
        dirs = prob.dirs.reshape(j * prob.dirs.shape[1], t)[free]  # (n_free, T)
        joint_of = np.repeat(np.arange(j), prob.dirs.shape[1])[free]
        lin = np.zeros((t, j, free.size))
        lin[:, joint_of, np.arange(free.size)] = dirs.T
        inner = slice(1, t - 1)
        a_mat = lin[inner].reshape(-1, free.size)
        q_in = prob.q_ls[inner].reshape(-1)
        lo_in = np.broadcast_to(lo, (t - 2, j)).reshape(-1)
        hi_in = np.broadcast_to(hi, (t - 2, j)).reshape(-1)
        constraints = [
            {"type": "ineq", "fun": lambda x: hi_in - (q_in + a_mat @ x), "jac": lambda x: -a_mat},
            {"type": "ineq", "fun": lambda x: (q_in + a_mat @ x) - lo_in, "jac": lambda x: a_mat},
        ]
        duration = float(prob.duration)

        def qz(x):
            return prob.q_ls + lin @ x

        if self.gradient == "jax":

            def full(x):
                z = np.zeros(mask.size)
                z[mask.reshape(-1)] = x
                return z.reshape(mask.shape)

            f0 = float(self.value_and_grad(jnp.zeros(mask.shape), prob)[0])
            scale = 1.0 / max(abs(f0), 1e-12)

            def fun(x):
                f, g = self.value_and_grad(jnp.asarray(full(x)), prob)
                return float(f) * scale, np.asarray(g).reshape(-1)[free] * scale

            jac = True
        else:
            f0 = self.mj_cost(qz(np.zeros(free.size)), duration)
            scale = 1.0 / max(abs(f0), 1e-12)

            def fun(x):
                return self.mj_cost(qz(x), duration) * scale

            jac = None
        start = time.perf_counter()
        res = minimize(
            fun,
            np.zeros(free.size),
            jac=jac,
            method="SLSQP",
            constraints=constraints,
            options={"maxiter": self.maxiter, "ftol": self.ftol},
        )
        wall = time.perf_counter() - start
        q = qz(res.x)
        viol = max(0.0, float(np.max(q[inner] - hi)), float(np.max(lo - q[inner])))
        cost = float(self.cost(q[None], np.asarray([duration]))[0])
        return q, cost, bool(res.success), int(res.nit), wall, viol, str(res.message)
