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
- start: z = 0, the minimum-norm BC solution, the same start as ``compile_optim``.

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

from evojax_motion.basis import Basis
from evojax_motion.compile_interp import Boundary
from evojax_motion.compile_optim import OptimSettings, make_objective, reduced_problems
from evojax_motion.dynamics import make_dynamics
from evojax_motion.objective import torque_cost
from evojax_motion.robot import Robot, mj_inverse_torques
from evojax_motion.timegrid import TimeGrid

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


def torque_costs_f64(robot: Robot, grid: TimeGrid, q, duration) -> np.ndarray:
    """Float64 eq. 5 cost of each ``q (C, T, J)`` with ``duration (C,)`` (JAX RNEA, x64)."""
    with jax.enable_x64(True), _on_cpu():
        dyn = _dynamics_f64(robot)
        g64 = grid._replace(**{k: np.asarray(v, np.float64) for k, v in grid._asdict().items()})
        fn = jax.jit(jax.vmap(lambda qq, dd: torque_cost(dyn, g64, qq, dd)))
        out = fn(
            jnp.asarray(np.asarray(q, np.float64)), jnp.asarray(np.asarray(duration, np.float64))
        )
        return np.asarray(out)


def solve_reference(
    robot: Robot,
    grid: TimeGrid,
    basis: Basis,
    boundary: Boundary,
    settings: OptimSettings | None = None,
    gradient: str = "jax",
    maxiter: int = SLSQP_MAXITER,
    ftol: float = SLSQP_FTOL,
    lower=None,
    upper=None,
) -> ReferenceResult:
    """SLSQP on every condition of the batch (see the module docstring). Float64 throughout.

    ``lower``, ``upper``: joint limits ``(J,)`` [rad], default the robot's; the constraints use
    them shrunk by ``settings.limit_margin``.
    """
    if gradient not in GRADIENTS:
        raise ValueError(f"gradient: expected one of {GRADIENTS}, got {gradient!r}")
    settings = OptimSettings() if settings is None else settings
    # The reduced problem is built exactly as the compiler builds it (same dtype and device, so
    # the same binding BC directions, start and null space), then solved in float64 on the CPU.
    build = jax.jit(
        lambda b, bc: reduced_problems(
            b, bc, grid, settings.n_components, settings.bc_leak, settings.max_free_per_joint
        )
    )
    problems, _, _ = build(basis, boundary)
    problems = jax.tree_util.tree_map(
        lambda a: np.asarray(a, np.float64) if np.asarray(a).dtype.kind == "f" else np.asarray(a),
        problems,
    )
    with _on_cpu():
        return _solve_on_cpu(robot, grid, problems, settings, gradient, maxiter, ftol, lower, upper)


def _solve_on_cpu(
    robot, grid, problems, settings, gradient, maxiter, ftol, lower, upper
) -> ReferenceResult:
    with jax.enable_x64(True):
        lower = robot.lower if lower is None else lower
        upper = robot.upper if upper is None else upper
        lo = np.asarray(lower, np.float64) + settings.limit_margin
        hi = np.asarray(upper, np.float64) - settings.limit_margin
        if gradient == "jax":
            dyn = _dynamics_f64(robot)
            objective = make_objective(dyn, lo, hi, 0.0)
            value_and_grad = jax.jit(jax.value_and_grad(lambda z, prob: objective(z, prob)[1]))
        else:
            mj_cost = MujocoCost(robot, grid)

        c, t, j = problems.q_ls.shape
        out_q = np.empty((c, t, j))
        cost = np.empty(c)
        success = np.zeros(c, bool)
        iters = np.zeros(c, np.int64)
        wall = np.zeros(c)
        viol = np.zeros(c)
        messages = []
        for i in range(c):
            prob = jax.tree_util.tree_map(lambda a, i=i: a[i], problems)
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
                {
                    "type": "ineq",
                    "fun": lambda x, a=a_mat, q0=q_in, h=hi_in: h - (q0 + a @ x),
                    "jac": lambda x, a=a_mat: -a,
                },
                {
                    "type": "ineq",
                    "fun": lambda x, a=a_mat, q0=q_in, lw=lo_in: (q0 + a @ x) - lw,
                    "jac": lambda x, a=a_mat: a,
                },
            ]
            duration = float(prob.duration)

            def full(x, mask=mask):
                z = np.zeros(mask.size)
                z[mask.reshape(-1)] = x
                return z.reshape(mask.shape)

            if gradient == "jax":
                f0 = float(value_and_grad(jnp.zeros(mask.shape), prob)[0])
                scale = 1.0 / max(abs(f0), 1e-12)

                def fun(x, prob=prob, scale=scale, full=full, free=free):
                    f, g = value_and_grad(jnp.asarray(full(x)), prob)
                    return float(f) * scale, np.asarray(g).reshape(-1)[free] * scale

                jac = True
            else:

                def qz(x, prob=prob, lin=lin):
                    return prob.q_ls + lin @ x

                f0 = mj_cost(qz(np.zeros(free.size)), duration)
                scale = 1.0 / max(abs(f0), 1e-12)

                def fun(x, qz=qz, scale=scale, duration=duration):
                    return mj_cost(qz(x), duration) * scale

                jac = None
            start = time.perf_counter()
            res = minimize(
                fun,
                np.zeros(free.size),
                jac=jac,
                method="SLSQP",
                constraints=constraints,
                options={"maxiter": maxiter, "ftol": ftol},
            )
            wall[i] = time.perf_counter() - start
            q_i = prob.q_ls + lin @ res.x
            out_q[i] = q_i
            success[i] = bool(res.success)
            iters[i] = int(res.nit)
            viol[i] = max(0.0, float(np.max(q_i[inner] - hi)), float(np.max(lo - q_i[inner])))
            messages.append(str(res.message))
        cost = torque_costs_f64(robot, grid, out_q, problems.duration)
    return ReferenceResult(out_q, cost, success, iters, wall, viol, messages)
