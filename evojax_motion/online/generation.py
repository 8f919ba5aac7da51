"""Online motion generation from the learned database (paper sec. 3.2 and 4.5), within joint limits.

"The humanoid generates a human-like movement corresponding to a given task in real time by
linearly interpolating the primitive movements in the developed database." One query, for a
target hand position ``p*`` (optionally a duration D and a start posture q0):

1. neighbours: the k primitives of the database nearest to ``p*`` (eq. 6, ``basis``);
2. final posture ``qf``: human-like IK of ``p*`` (``model.ik.solve_ik``) started from the nearest
   neighbour's final posture and pulled, in the redundant directions, toward the neighbours' mean
   final posture; every iterate stays inside the joint limits (as ``conditions`` does offline);
3. movement compiler via interpolation (eq. 1-2, ``compile_interp``) on the neighbours' PCA
   basis with ``q(0) = q0``, ``q(1) = qf``, ``qd(0) = qd(1) = 0`` and D = the neighbours' mean
   duration unless given;
4. joint limits (the paper's open problem, sec. 5: "some motions ... violated some of the joint
   limits"): see below;
5. ``qd, qdd`` from the time grid and ``tau`` by inverse dynamics (eq. 4), the eq. 5 cost;
6. velocity and torque limits by time scaling: see below.

Everything is one jitted function over any number of targets (`make_online_generator`; pieces:
`reach_query` = steps 1-2, `build_problem` + `finish_motion` = steps 1-5). Outside the learned
region (fewer than ``min_neighbours`` primitives within the radius) or out of the IK's reach a
target is flagged, with its distance; `nearest_reachable` finds a reachable point near it.
Float32 matrix products are traced at full precision (`exact_matmuls`): GPUs default to TF32.

Joint limits. Per joint the BC system of eq. 2 is ``A x = b`` in the coefficients of eq. 1; with
``K_lim`` components (default 4, the optimisation compiler's basis) its solutions are
``x = x_ls + N z`` (``compiler.interpolation.solve_boundary``: ``N`` spans the null space, in prior
units
of the neighbours' spread). Any z keeps the BCs, so limits are enforced by the smallest such z:

    min_z 0.5 |z|^2 + 0.5 rho sum_t [relu(q_t - hi_t)^2 + relu(lo_t - q_t)^2],  q = q_eq1 + G z

(``G = basis functions @ N``, ``(T, K_lim)``), a convex piecewise quadratic solved by a few
semi-smooth Newton steps (each a ``K_lim x K_lim`` solve). The bounds ``lo_t, hi_t`` sit
``limit_margin`` inside the limits, relaxed toward the safe path below near the ends (where the
null directions vanish). The penalty leaves a violation of ~1e-4 of the original one, absorbed
by the margin. A guarantee on top: a joint still outside after that is blended toward the
minimum-jerk path ``q0 -> qf`` (inside the limits whenever q0 and qf are, and with the same
rest-to-rest BCs), ``q = (1 - lam) q + lam q_mj`` with the smallest ``lam in [0, 1]`` that brings
every sample inside (closed form). So an online motion never leaves ``[lower, upper]``.

Velocity and torque limits (``Robot.velocity_limit``, ``Robot.torque_limit``; inf: none). The
path ``q(s)`` on normalised time does not depend on the duration D (the BCs are rest to rest), so
a motion over a limit is slowed down, never reshaped. With ``w = 1 / D`` the velocities are
``q'(s) w`` and the torques of MuJoCo's inverse dynamics a polynomial ``tau = c0 + c1 w + c2 w^2``
(gravity and springs; damping; inertia, Coriolis and armature), whose coefficients three inverse
dynamics evaluations give exactly (`time_law`). `shortest_duration` finds the smallest D >= the
asked one with every ``|qd| <= (1 - h) v_max`` and ``|tau| <= (1 - h) tau_max`` (``h =
limit_headroom``, the authority left to a feedback controller): a log-spaced scan up to
`MAX_DURATION`, then bisection between the last infeasible and the first feasible duration
(feasibility is monotone in D without damping; the scan guards the rest). A motion is usable
(``ok``) only when that D fits the time allowed (`MAX_DURATION`; for a catch, until the ball
arrives) and its velocities and torques at that D (the polynomial: the inverse dynamics there,
up to rounding) are within the full limits.
Otherwise the result says which limit binds: joint, value needed, at what time (``worst_*``);
e.g. gravity alone over a torque limit fails at any D.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.basis import BasisSettings, pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import (
    Boundary,
    basis_functions,
    boundary_residual,
    compile_interpolation,
    solve_boundary,
)
from evojax_motion.errors import UserError, check_setting
from evojax_motion.linalg.cholesky import spd_solve
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.linalg.reductions import masked_row_mean
from evojax_motion.model.dynamics import Dynamics, unfused_cpu_program
from evojax_motion.model.ik import solve_ik
from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import EVOLVED, Database
from evojax_motion.motion.objective import cost_from_torques
from evojax_motion.motion.timegrid import TimeGrid, derivatives


@dataclass(frozen=True)
class OnlineSettings:
    """Settings of the online query (static under jit).

    - ``n_components``: principal components of the interpolation (paper eq. 1: 3).
    - ``limit_components``: components whose BC null space the limit projection moves in (>=
      ``n_components``; 4 = the optimisation compiler's eq. 3 basis).
    - ``min_neighbours``: a target is inside the learned region when at least this many valid
      primitives lie within ``BasisSettings.radius`` of it (<= ``BasisSettings.neighbours``).
    - ``prefer_evolved``: take the neighbours among the evolved (robot-optimised) primitives when
      at least ``min_neighbours`` of them lie within the radius, else among all valid ones. The
      human originals stay in the database for the evolution's sake (sec. 4.3); online, a basis
      mixing them in pulls the motion back toward the human's torques (benchmarks/online_quality:
      median eq. 5 cost 9.4 with all entries, 6.1 with evolved ones, paper setting).
    - ``ik_iters``: IK iterations (started from the nearest neighbour's final posture; on the
      paper-setting database 8 already reach the final accuracy, p95 6e-5 m).
    - ``reach_tolerance`` [m]: a target whose IK posture misses it by more is unreachable.
    - ``limit_margin`` [rad]: the limit projection aims this far inside the joint limits.
    - ``projection_iters``: semi-smooth Newton steps of the limit projection.
    - ``penalty``: weight of a limit violation relative to the null-space step (scale-free).
    - ``limit_headroom``: fraction of every velocity and torque limit that time scaling keeps
      free (for a tracking controller's feedback; docs/simulation.md): motions are planned
      within ``(1 - limit_headroom)`` times the limits.
    - ``scaling_scan``, ``scaling_iters``: durations scanned (log-spaced up to `MAX_DURATION`)
      and bisection steps of the time scaling.
    """

    n_components: int = 3
    limit_components: int = 4
    min_neighbours: int = 4
    prefer_evolved: bool = True
    ik_iters: int = 10
    reach_tolerance: float = 1e-3
    limit_margin: float = 2e-3
    projection_iters: int = 8
    penalty: float = 1e4
    limit_headroom: float = 0.05
    scaling_scan: int = 32
    scaling_iters: int = 24

    def __post_init__(self):
        check_setting(self.n_components >= 1, "n_components", "an integer >= 1", self.n_components)
        check_setting(
            self.limit_components >= self.n_components,
            "limit_components",
            f"an integer >= n_components ({self.n_components})",
            self.limit_components,
        )
        check_setting(
            self.min_neighbours >= 1, "min_neighbours", "an integer >= 1", self.min_neighbours
        )
        check_setting(self.ik_iters >= 1, "ik_iters", "an integer >= 1", self.ik_iters)
        check_setting(
            self.reach_tolerance > 0, "reach_tolerance", "a number > 0 [m]", self.reach_tolerance
        )
        check_setting(
            self.limit_margin >= 0, "limit_margin", "a number >= 0 [rad]", self.limit_margin
        )
        check_setting(
            self.projection_iters >= 0, "projection_iters", "an integer >= 0", self.projection_iters
        )
        check_setting(self.penalty > 0, "penalty", "a number > 0", self.penalty)
        check_setting(
            0 <= self.limit_headroom < 1,
            "limit_headroom",
            "a number in [0, 1)",
            self.limit_headroom,
        )
        check_setting(self.scaling_scan >= 2, "scaling_scan", "an integer >= 2", self.scaling_scan)
        check_setting(
            self.scaling_iters >= 0, "scaling_iters", "an integer >= 0", self.scaling_iters
        )


class OnlineResult(NamedTuple):
    """B generated motions (arrays; numpy after `generate_motions`).

    t: (B, T) time from the motion's start [s]; q, qd, qdd, tau: (B, T, J) [rad, rad/s, rad/s^2,
    N m]; duration: (B,) [s]; target: (B, 3) [m]; q_final: (B, J) IK posture [rad];
    hand_error: (B,) |hand(q[-1]) - target| [m]; ik_error: (B,) the IK's miss [m] (~ distance
    to the kinematically reachable set); region_gap: (B,) how far the target lies outside the
    learned region (0 inside) [m]; n_inside: (B,) valid primitives within the radius;
    limit_excess: (B,) largest limit violation of plain eq. 1 interpolation [rad] (0 = none);
    fallback: (B,) the minimum-jerk blend was needed after the projection;
    bc_residual: (B,) BC error of q; cost: (B,) eq. 5 cost [N^2 m^2 s];
    duration_asked: (B,) the duration before time scaling [s] (``duration`` > it: stretched);
    duration_needed: (B,) the shortest duration within the usable velocity and torque limits
    [s] (inf: none up to `MAX_DURATION`); within_time: (B,) it fits the time allowed;
    torque_margin, velocity_margin: (B,) min over joints of ``1 - peak / limit`` (1 without
    limits; < 0 over a limit); joint_margin: (B,) smallest distance to a joint limit [rad];
    worst_joint, worst_kind (0 torque, 1 velocity), worst_value [N m or rad/s], worst_time [s
    from the start]: the sample and joint that use the most of a usable limit (`limit_headroom`);
    reachable: (B,) inside the learned region and reached by the IK;
    ok: (B,) reachable, finite, inside the joint limits, within the velocity and torque limits,
    and within the time allowed (a usable motion).
    """

    t: jnp.ndarray
    q: jnp.ndarray
    qd: jnp.ndarray
    qdd: jnp.ndarray
    tau: jnp.ndarray
    duration: jnp.ndarray
    target: jnp.ndarray
    q_final: jnp.ndarray
    hand_error: jnp.ndarray
    ik_error: jnp.ndarray
    region_gap: jnp.ndarray
    n_inside: jnp.ndarray
    limit_excess: jnp.ndarray
    fallback: jnp.ndarray
    bc_residual: jnp.ndarray
    cost: jnp.ndarray
    duration_asked: jnp.ndarray
    duration_needed: jnp.ndarray
    within_time: jnp.ndarray
    torque_margin: jnp.ndarray
    velocity_margin: jnp.ndarray
    joint_margin: jnp.ndarray
    worst_joint: jnp.ndarray
    worst_kind: jnp.ndarray
    worst_value: jnp.ndarray
    worst_time: jnp.ndarray
    reachable: jnp.ndarray
    ok: jnp.ndarray


class Reach(NamedTuple):
    """Whether points can be targets: the learned region and the kinematics. All ``(P,)``.

    depth: ``radius - d_m`` [m], d_m the distance to the ``min_neighbours``-th nearest valid
    condition: >= 0 inside the learned region; region_gap: ``max(-depth, 0)`` [m] (inf when the
    database has too few valid entries); ik_error: the human-like IK's miss [m];
    q_final: (P, J) its posture [rad]; hand: (P, 3) where it puts the hand [m];
    natural_duration: the neighbours' mean duration [s]; n_inside: valid primitives within the
    radius; reachable: region_gap == 0 and ik_error <= ``reach_tolerance``.
    """

    depth: jnp.ndarray
    region_gap: jnp.ndarray
    ik_error: jnp.ndarray
    q_final: jnp.ndarray
    hand: jnp.ndarray
    natural_duration: jnp.ndarray
    n_inside: jnp.ndarray
    reachable: jnp.ndarray


def reach_query(
    dyn: Dynamics,
    db: Database,
    points,
    lower,
    upper,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
):
    """Steps 1-2 for ``points (P, 3)``: neighbours and the final posture. Pure, jittable.

    ``db`` needs ``q (N, T, J)``, ``duration``, ``condition``, ``valid``. Returns
    ``(Reach, Neighbours)``.
    """
    q_db = jnp.asarray(db.q)
    points = jnp.asarray(points, q_db.dtype)
    cond, valid = jnp.asarray(db.condition, q_db.dtype), jnp.asarray(db.valid)
    select = functools.partial(
        select_neighbours,
        k=basis_settings.neighbours,
        radius=basis_settings.radius,
        w_pos=basis_settings.w_pos,
    )
    region = select(cond, valid, points)  # the learned region: every valid primitive counts
    nb = region
    if settings.prefer_evolved:
        evolved = select(cond, valid & (jnp.asarray(db.origin) == EVOLVED), points)
        use = evolved.n_inside >= settings.min_neighbours  # (P,)
        nb = jax.tree_util.tree_map(
            lambda e, a: jnp.where(use.reshape(use.shape + (1,) * (e.ndim - 1)), e, a),
            evolved,
            region,
        )
    final = q_db[nb.index, -1]  # (P, k, J) the neighbours' final postures
    ik = solve_ik(
        dyn,
        points,
        final[:, 0],
        lower,
        upper,
        q_pref=masked_row_mean(final, nb.mask),
        iters=settings.ik_iters,
        tol=settings.reach_tolerance,
    )
    # The learned region: >= min_neighbours primitives within the radius. d_m is 1-Lipschitz in
    # the point, so the gap is a lower bound of the distance to the region (exact near a cluster).
    kth = region.distance[:, settings.min_neighbours - 1] / basis_settings.w_pos
    depth = jnp.where(jnp.isfinite(kth), basis_settings.radius - kth, -jnp.inf)
    gap = jnp.maximum(-depth, 0.0)
    dur = masked_row_mean(jnp.asarray(db.duration, q_db.dtype)[nb.index], nb.mask)
    reach = Reach(
        depth=depth,
        region_gap=gap,
        ik_error=ik.pos_error,
        q_final=ik.q,
        hand=jax.vmap(lambda q: dyn.site_pose(q)[0])(ik.q),
        natural_duration=jnp.where(jnp.any(nb.mask, axis=1), dur, jnp.nan),
        n_inside=region.n_inside,
        reachable=(gap <= 0.0) & (ik.pos_error <= settings.reach_tolerance),
    )
    return reach, nb


def make_reach_checker(
    robot: Robot,
    dyn: Dynamics,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
) -> Callable:
    """Jitted ``check(db, points (P, 3)) -> Reach``: cheap (no PCA, no dynamics)."""
    basis_settings, settings = resolve_settings(basis_settings, settings)
    lower, upper = joint_limits_f32(robot)

    @jax.jit
    @exact_matmuls
    def check(db, points):
        return reach_query(dyn, db, points, lower, upper, basis_settings, settings)[0]

    return check


def minimum_jerk(grid: TimeGrid, q0, qf) -> jnp.ndarray:
    """Rest-to-rest minimum-jerk paths ``q0 (C, J) -> qf (C, J)``: ``(C, T, J)``.

    Monotone between q0 and qf, so inside any box that holds both ends.
    """
    s = jnp.asarray(grid.s, q0.dtype)
    shape = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    return q0[:, None, :] + (qf - q0)[:, None, :] * shape[None, :, None]


def _joint_projection(a, g, lo, hi, iters: int, penalty: float):
    """Smallest null-space step that brings one joint inside ``[lo_t, hi_t]``.

    ``a (T,)`` trajectory, ``g (T, n)`` null-space directions, ``lo, hi (T,)``. -> ``(T,)``.
    """
    n = g.shape[1]
    # Scale-free penalty: relative to the directions' size, so one setting fits every joint.
    rho = penalty / jnp.maximum(jnp.mean(jnp.sum(g * g, axis=0)), 1e-12)
    eye = jnp.eye(n, dtype=a.dtype)

    def step(_, z):
        x = a + g @ z
        up, dn = x > hi, x < lo
        bound = jnp.where(up, hi, jnp.where(dn, lo, 0.0))
        ga = jnp.where((up | dn)[:, None], g, 0.0)
        h = eye + rho * ga.T @ ga
        return spd_solve(h, rho * ga.T @ (bound - a))

    z = jax.lax.fori_loop(0, iters, step, jnp.zeros(n, a.dtype))
    return a + g @ z


def _blend_inside(a, safe, lower, upper):
    """Smallest ``lam`` per joint with ``(1 - lam) a + lam safe`` inside the limits; applied.

    ``a, safe (T, J)``, ``safe`` inside ``[lower, upper] (J,)``. -> ``(T, J)``, ``lam (J,)``.
    """
    over = jnp.where(a > upper, (a - upper) / jnp.maximum(a - safe, 1e-12), 0.0)
    under = jnp.where(a < lower, (lower - a) / jnp.maximum(safe - a, 1e-12), 0.0)
    lam = jnp.clip(jnp.max(jnp.maximum(over, under), axis=0), 0.0, 1.0)
    q = (1.0 - lam) * a + lam * safe
    return jnp.clip(q, lower, upper), lam  # clip only removes rounding (<= 1 ulp)


def enforce_limits(
    basis,
    boundary: Boundary,
    grid: TimeGrid,
    q,
    lower,
    upper,
    settings: OnlineSettings,
):
    """Step 4: ``q (C, T, J)`` moved inside ``[lower, upper] (J,)`` keeping the BCs (see module).

    ``basis`` must hold ``settings.limit_components`` components. Returns ``(q (C, T, J),
    limit_excess (C,), fallback (C,))``: the largest violation of the input and whether the
    minimum-jerk blend was needed.
    """
    excess = jnp.max(jnp.maximum(q - upper, lower - q), axis=(1, 2))
    outside = jnp.any((q > upper) | (q < lower), axis=1, keepdims=True)  # (C, 1, J)
    proj = functools.partial(
        _joint_projection, iters=settings.projection_iters, penalty=settings.penalty
    )
    per_joint = jax.vmap(proj, in_axes=(1, 0, 1, 1), out_axes=1)  # over J

    def project(q):
        k = settings.limit_components
        sol = solve_boundary(basis, boundary, grid, k)
        funcs = basis_functions(basis, k)  # (C, J, K+1, T)
        g = jnp.einsum("cjnt,cjnm->cjtm", funcs, sol.null)  # (C, J, T, K) null directions
        safe = minimum_jerk(grid, boundary.q0, boundary.qf)
        # Near the ends the null directions vanish: never ask for more than the safe path has.
        lo = jnp.minimum(lower + settings.limit_margin, safe)
        hi = jnp.maximum(upper - settings.limit_margin, safe)
        # Only joints that were outside move: an inside joint keeps its eq. 1 trajectory.
        q = jnp.where(outside, jax.vmap(per_joint)(q, g, lo, hi), q)
        q, lam = jax.vmap(_blend_inside, in_axes=(0, 0, None, None))(q, safe, lower, upper)
        return q, jnp.any(lam > 0, axis=1)

    # Most motions are inside already: skip the work (a select, not a branch, under vmap).
    q, fallback = jax.lax.cond(
        jnp.any(outside), project, lambda q: (q, jnp.zeros(q.shape[0], bool)), q
    )
    return q, jnp.maximum(excess, 0.0), fallback


MAX_DURATION = 60.0  # [s] the longest motion a query may ask for or be stretched to
TORQUE, VELOCITY = 0, 1  # `OnlineResult.worst_kind`


class TimeLaw(NamedTuple):
    """Torques and velocities of paths ``q(s)`` as functions of ``w = 1 / D`` (module doc).

    ``tau = c0 + c1 w + c2 w^2``, ``qd = slope w``; all ``(C, T, J)``.
    """

    c0: jnp.ndarray
    c1: jnp.ndarray
    c2: jnp.ndarray
    slope: jnp.ndarray


def time_law(dyn: Dynamics, grid: TimeGrid, q) -> TimeLaw:
    """The `TimeLaw` of ``q (C, T, J)``: inverse dynamics at ``w = 0, 1, -1``.

    MuJoCo's inverse dynamics is ``M(q) qdd + C(q, qd) qd + g(q) + armature qdd + damping qd +
    stiffness (q - ref)``: with ``qd = q' w`` and ``qdd = q'' w^2`` exactly quadratic in w.
    """
    slope, curve = derivatives(grid, q, jnp.ones(q.shape[0], q.dtype))
    inv = jax.vmap(jax.vmap(dyn.inverse))
    zero = jnp.zeros_like(q)
    # one batch of 3C paths: the inverse dynamics is traced (and compiled) once, not thrice
    tau = inv(
        jnp.concatenate([q, q, q]),
        jnp.concatenate([zero, slope, -slope]),
        jnp.concatenate([zero, curve, curve]),
    ).reshape((3, *q.shape))
    c0, ahead, back = tau[0], tau[1], tau[2]
    return TimeLaw(c0, 0.5 * (ahead - back), 0.5 * (ahead + back) - c0, slope)


def limit_usage(law: TimeLaw, duration, vel_usable, tau_usable):
    """Largest ``|qd| / vel_usable`` or ``|tau| / tau_usable`` of each path at ``duration (C,)``:
    ``(C,)`` (<= 1: within the limits). Limits ``(J,)``; inf: none."""
    w = (1.0 / duration)[:, None, None]
    tau = law.c0 + w * (law.c1 + w * law.c2)
    use = jnp.maximum(jnp.abs(tau) / tau_usable, jnp.abs(law.slope) * w / vel_usable)
    return jnp.max(use, axis=(1, 2))


def shortest_duration(
    law: TimeLaw, duration, vel_usable, tau_usable, scan: int, iters: int
) -> jnp.ndarray:
    """The smallest ``D >= duration (C,)`` within the usable limits (``(J,)``); inf where no D
    up to `MAX_DURATION` is. ``(C,)`` [s].

    ``scan`` log-spaced durations from ``duration`` to `MAX_DURATION`, then ``iters`` bisection
    steps (in log D) between the last infeasible and the first feasible one; the feasible end is
    returned, so the result is always within the limits.
    """
    dtype = law.c0.dtype
    duration = jnp.asarray(duration, dtype)
    top = jnp.maximum(duration, MAX_DURATION)
    frac = jnp.linspace(0.0, 1.0, scan, dtype=dtype)
    cand = duration[:, None] * (top / duration)[:, None] ** frac[None, :]  # (C, K)
    usage = jax.vmap(lambda d: limit_usage(law, d, vel_usable, tau_usable), 1, 1)(cand)
    feasible = usage <= 1.0
    first = jnp.argmax(feasible, axis=1)
    hi = jnp.take_along_axis(cand, first[:, None], axis=1)[:, 0]
    lo = jnp.take_along_axis(cand, jnp.maximum(first - 1, 0)[:, None], axis=1)[:, 0]

    def bisect(_, bounds):
        lo, hi = bounds
        mid = jnp.sqrt(lo * hi)
        ok = limit_usage(law, mid, vel_usable, tau_usable) <= 1.0
        return jnp.where(ok, lo, mid), jnp.where(ok, mid, hi)

    _, hi = jax.lax.fori_loop(0, iters, bisect, (lo, hi))
    hi = jnp.where(first == 0, duration, hi)
    return jnp.where(jnp.any(feasible, axis=1), hi, jnp.inf)


def usable_limits(robot: Robot, settings: OnlineSettings, dtype=np.float32):
    """``(vel_limit, tau_limit, vel_usable, tau_usable)``, each ``(J,)`` numpy (inf: none);
    usable = ``(1 - limit_headroom)`` x limit."""
    vel = np.asarray(robot.velocity_limit, np.float64)
    tau = np.asarray(robot.torque_limit, np.float64)
    keep = 1.0 - settings.limit_headroom
    return tuple(np.asarray(a, dtype) for a in (vel, tau, keep * vel, keep * tau))


def _margin(peak, limit):
    """``min_j 1 - peak_j / limit_j`` over ``peak (C, J)``; 1 where no joint has a limit."""
    return jnp.min(jnp.where(jnp.isfinite(limit), 1.0 - peak / limit, 1.0), axis=1)


def build_problem(
    dyn: Dynamics,
    db: Database,
    targets,
    duration,
    q_start,
    lower,
    upper,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
):
    """Steps 1-2 and the BCs: ``(basis, boundary, reach)`` for ``targets (C, 3)``. Pure.

    ``duration (C,)`` [s] (NaN: the neighbours' mean), ``q_start (C, J)`` inside the limits.
    ``basis`` holds ``settings.limit_components`` components (enough for eq. 1 and eq. 3).
    """
    dtype = jnp.asarray(db.q).dtype
    reach, nb = reach_query(dyn, db, targets, lower, upper, basis_settings, settings)
    basis = pca_basis(
        jnp.asarray(db.q), jnp.asarray(db.duration, dtype), nb, settings.limit_components
    )
    duration = jnp.asarray(duration, dtype)
    zeros = jnp.zeros_like(reach.q_final)
    boundary = Boundary(
        q0=jnp.asarray(q_start, dtype),
        qf=reach.q_final,
        qd0=zeros,
        qdf=zeros,
        duration=jnp.where(jnp.isnan(duration), reach.natural_duration, duration),
    )
    return basis, boundary, reach


def finish_motion(
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    settings: OnlineSettings,
    basis,
    boundary: Boundary,
    reach: Reach,
    targets,
    max_duration=None,
) -> OnlineResult:
    """Steps 3-6: interpolation (eq. 1-2), joint limits, derivatives, torques, time scaling.

    ``max_duration (C,)`` [s]: the time allowed (None: `MAX_DURATION`); a motion that needs
    longer to stay within the velocity and torque limits of ``dyn.robot`` is returned at
    ``max_duration`` with ``ok`` False. Pure.
    """
    interp = compile_interpolation(basis, boundary, grid, settings.n_components)
    q, excess, fallback = enforce_limits(basis, boundary, grid, interp.q, lower, upper, settings)
    asked = boundary.duration
    top = jnp.full_like(asked, MAX_DURATION) if max_duration is None else max_duration
    top = jnp.asarray(top, q.dtype)
    vel_lim, tau_lim, vel_use, tau_use = (
        jnp.asarray(a, q.dtype) for a in usable_limits(dyn.robot, settings)
    )
    inv = jax.vmap(jax.vmap(dyn.inverse))

    def usage(qd, tau):  # (C, T, J): share of the usable limit, torque and velocity
        return jnp.abs(tau) / tau_use, jnp.abs(qd) / vel_use

    qd, qdd = derivatives(grid, q, asked)
    tau = inv(q, qd, qdd)
    over = jnp.max(jnp.maximum(*usage(qd, tau)), axis=(1, 2)) > 1.0  # NaN: not over

    def stretch(_):
        law = time_law(dyn, grid, q)
        scan, iters = settings.scaling_scan, settings.scaling_iters
        needed = shortest_duration(law, asked, vel_use, tau_use, scan, iters)
        needed = jnp.where(over, needed, asked)
        dur = jnp.minimum(needed, jnp.maximum(top, asked))
        qd, qdd = derivatives(grid, q, dur)
        w = (1.0 / dur)[:, None, None]  # the law is the inverse dynamics at dur, exactly
        return needed, dur, qd, qdd, law.c0 + w * (law.c1 + w * law.c2)

    # Most motions are within their limits: skip the work (a branch: C is a batch axis here).
    needed, dur, qd, qdd, tau = jax.lax.cond(
        jnp.any(over), stretch, lambda _: (asked, asked, qd, qdd, tau), None
    )
    use_tau, use_vel = usage(qd, tau)
    kind = (use_vel > use_tau).astype(jnp.int32)  # (C, T, J)
    use = jnp.maximum(use_tau, use_vel).reshape(q.shape[0], -1)
    flat = jnp.argmax(use, axis=1)
    t_idx, j_idx = flat // q.shape[2], flat % q.shape[2]
    pick = jnp.arange(q.shape[0])
    worst_kind = kind[pick, t_idx, j_idx]
    worst_value = jnp.where(
        worst_kind == VELOCITY, jnp.abs(qd[pick, t_idx, j_idx]), jnp.abs(tau[pick, t_idx, j_idx])
    )
    peak_tau, peak_vel = jnp.max(jnp.abs(tau), axis=1), jnp.max(jnp.abs(qd), axis=1)
    within = jnp.all(peak_tau <= tau_lim, axis=1) & jnp.all(peak_vel <= vel_lim, axis=1)
    within_time = needed <= jnp.maximum(top, asked)
    dur = jnp.asarray(dur, q.dtype)
    cost = jax.vmap(functools.partial(cost_from_torques, grid))(tau, dur)
    hand = jax.vmap(lambda x: dyn.site_pose(x)[0])(q[:, -1])
    target = jnp.asarray(targets, q.dtype)
    hand_error = jnp.linalg.norm(hand - target, axis=-1)
    finite = jnp.all(jnp.isfinite(tau), axis=(1, 2)) & jnp.all(jnp.isfinite(qdd), axis=(1, 2))
    inside = jnp.all((q >= lower) & (q <= upper), axis=(1, 2))
    room = jnp.minimum(q - lower, upper - q)  # inf for a continuous joint
    return OnlineResult(
        t=jnp.asarray(grid.s, q.dtype)[None, :] * dur[:, None],
        q=q,
        qd=qd,
        qdd=qdd,
        tau=tau,
        duration=dur,
        target=target,
        q_final=reach.q_final,
        hand_error=hand_error,
        ik_error=reach.ik_error,
        region_gap=reach.region_gap,
        n_inside=reach.n_inside,
        limit_excess=excess,
        fallback=fallback,
        bc_residual=boundary_residual(grid, q, boundary._replace(duration=dur)),
        cost=cost,
        duration_asked=asked,
        duration_needed=needed,
        within_time=within_time,
        torque_margin=_margin(peak_tau, tau_lim),
        velocity_margin=_margin(peak_vel, vel_lim),
        joint_margin=jnp.min(room, axis=(1, 2)),
        worst_joint=j_idx.astype(jnp.int32),
        worst_kind=worst_kind,
        worst_value=worst_value,
        worst_time=jnp.asarray(grid.s, q.dtype)[t_idx] * dur,
        reachable=reach.reachable,
        ok=reach.reachable & finite & inside & within & within_time & jnp.isfinite(hand_error),
    )


def online_query(
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
    db: Database,
    targets,
    duration,
    q_start,
) -> OnlineResult:
    """The whole online query (steps 1-5) for ``targets (C, 3)``; pure (jit it at the top).

    ``duration (C,)`` [s] (NaN: the neighbours' mean), ``q_start (C, J)`` inside the limits.
    """
    lower = jnp.asarray(lower, jnp.asarray(db.q).dtype)
    upper = jnp.asarray(upper, lower.dtype)
    basis, boundary, reach = build_problem(
        dyn, db, targets, duration, q_start, lower, upper, basis_settings, settings
    )
    return finish_motion(dyn, grid, lower, upper, settings, basis, boundary, reach, targets)


def resolve_settings(basis_settings, settings):
    basis_settings = basis_settings or BasisSettings()
    settings = settings or OnlineSettings()
    if settings.min_neighbours > basis_settings.neighbours:
        raise UserError(
            f"online.min_neighbours: expected <= basis.neighbours ({basis_settings.neighbours}), "
            f"got {settings.min_neighbours}"
        )
    return basis_settings, settings


def joint_limits_f32(robot: Robot):
    return np.asarray(robot.lower, np.float32), np.asarray(robot.upper, np.float32)


def make_online_generator(
    robot: Robot,
    dyn: Dynamics,
    grid: TimeGrid,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
    fast_path: bool = True,
) -> Callable:
    """The jitted query ``generate(db, targets (C, 3), duration (C,), q_start (C, J))``.

    Returns `OnlineResult` (device arrays). ``db`` is an argument (not a constant) so one compiled
    function serves the learned and the human-only database alike; it recompiles only for a new
    C or database shape. ``fast_path``: compile through `model.dynamics.unfused_cpu_program` (faster
    on CPU; False: ``dyn`` as given, XLA's default options).
    """
    basis_settings, settings = resolve_settings(basis_settings, settings)
    lower, upper = joint_limits_f32(robot)
    dyn, options = unfused_cpu_program(dyn) if fast_path else (dyn, None)
    fn = functools.partial(online_query, dyn, grid, lower, upper, basis_settings, settings)
    return jax.jit(exact_matmuls(fn), compiler_options=options)


def online_database(db: Database) -> Database:
    """The database as device arrays (float32), ready to pass to a generator repeatedly."""
    return jax.tree_util.tree_map(jnp.asarray, db)


def check_query(robot: Robot, targets, duration=None, q_start=None):
    """Validate a user's query; returns ``targets (C, 3)``, ``duration (C,)``, ``q_start (C, J)``.

    ``duration``: None (natural), a number or ``(C,)`` [s] > 0. ``q_start``: None (``robot.rest``),
    ``(J,)`` or ``(C, J)`` inside the joint limits. Raises `UserError` naming the field.
    """
    from evojax_motion.compiler.basis import validate_targets

    targets = validate_targets(targets, "target")
    c, j = targets.shape[0], robot.n_joints
    if duration is None:
        dur = np.full(c, np.nan, np.float32)
    else:
        dur = np.broadcast_to(np.asarray(duration, np.float64), (c,)).copy()
        if not (np.isfinite(dur).all() and (dur > 0).all()):
            raise UserError(f"duration: expected a number > 0 [s], got {duration!r}")
        if (dur > MAX_DURATION).any():
            raise UserError(
                f"duration: expected at most {MAX_DURATION:g} s, got {float(dur.max()):g}"
            )
        dur = dur.astype(np.float32)
    if q_start is None:
        q0 = np.broadcast_to(np.asarray(robot.rest, np.float32), (c, j)).copy()
    else:
        q0 = np.asarray(q_start, np.float64)
        if q0.shape not in ((j,), (c, j)):
            raise UserError(f"start posture: expected {j} joint angles [rad], got {q0.shape}")
        q0 = np.broadcast_to(q0, (c, j))
        if not np.isfinite(q0).all():
            raise UserError("start posture: expected finite joint angles, got NaN/inf")
        outside = (q0 < robot.lower) | (q0 > robot.upper)
        if outside.any():
            row, col = np.argwhere(outside)[0]
            raise UserError(
                f"start posture: joint {robot.joint_names[col]!r} = {q0[row, col]:.4g} rad is "
                f"outside its limits [{robot.lower[col]:.4g}, {robot.upper[col]:.4g}]"
            )
        q0 = q0.astype(np.float32)
    return targets, dur, q0


def to_numpy(result: OnlineResult) -> OnlineResult:
    """Device arrays -> numpy (read-only, like `jax.device_get`'s).

    On accelerators one `jax.device_get` (it starts every field's copy before waiting on any);
    on CPU the arrays already sit in host memory and ``np.asarray`` per field skips that
    machinery, several times faster for a single query's 18 small fields.
    """
    if jax.default_backend() == "cpu":
        return jax.tree_util.tree_map(np.asarray, result)
    return OnlineResult(*jax.device_get(tuple(result)))


def check_points(check: Callable, db, points: np.ndarray, chunk: int) -> Reach:
    """`make_reach_checker`'s function over any number of points, in fixed-size chunks (one
    compiled shape)."""
    n = points.shape[0]
    pad = (-n) % chunk
    padded = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)]).astype(np.float32)
    parts = [jax.device_get(check(db, padded[i : i + chunk])) for i in range(0, n + pad, chunk)]
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n], *parts)


def nearest_reachable(
    check: Callable, db: Database, target, chunk: int = 64
) -> tuple[np.ndarray, float]:
    """A reachable point near ``target (3,)`` and its distance [m] (host-level, for messages and
    ``--nearest``).

    Candidates: where the IK puts the hand, and the farthest reachable point on the segment from
    the nearest reachable database condition toward the target (two rounds of ``chunk`` samples).
    Returns the candidate closest to the target (an upper bound of the true distance).
    Raises `UserError` when no database condition is reachable.
    """
    target = np.asarray(target, np.float32).reshape(3)
    cond = np.asarray(db.condition)[np.asarray(db.valid)]
    anchors = cond[check_points(check, db, cond, chunk).reachable]
    if anchors.shape[0] == 0:
        raise UserError("database: no valid primitive's condition is reachable; nothing is near")
    anchor = anchors[np.argmin(np.linalg.norm(anchors - target, axis=1))]
    lo, hi = 0.0, 1.0
    for _ in range(2):  # coarse, then fine between the last good and the first bad sample
        lam = np.linspace(lo, hi, chunk)
        pts = anchor + lam[:, None] * (target - anchor)
        ok = check_points(check, db, pts, chunk).reachable
        good = np.flatnonzero(ok)
        k = int(good.max()) if good.size else 0
        lo, hi = lam[k], lam[min(k + 1, chunk - 1)]
    best = anchor + lo * (target - anchor)
    cand = check_points(check, db, target[None], chunk)
    hand = check_points(check, db, np.asarray(cand.hand), chunk)
    if hand.reachable[0]:
        h = cand.hand[0]
        if np.linalg.norm(h - target) < np.linalg.norm(best - target):
            best = h
    return best.astype(np.float32), float(np.linalg.norm(best - target))


def final_hand(robot: Robot, q_final) -> np.ndarray:
    """Where the end effector is at the postures ``q_final (B, J)`` [rad]: ``(B, 3)`` [m].

    Host-side forward kinematics by C MuJoCo (float64) of exactly the postures written, independent
    of the traced dynamics that generated them.
    """
    import mujoco

    m = robot.mj_model
    d = mujoco.MjData(m)
    q_final = np.asarray(q_final, np.float64).reshape(-1, robot.n_joints)
    out = np.zeros((q_final.shape[0], 3))
    for i, q in enumerate(q_final):
        d.qpos[:] = m.qpos0
        d.qpos[robot.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        out[i] = d.site_xpos[robot.site_id]
    return out


@dataclass(frozen=True, eq=False)
class OnlineModel:
    """Everything a query needs, loaded once: the robot rebuilt from the database file, its
    dynamics, the database (numpy ``db`` and device ``db_device``), the time grid and settings.
    ``source``: the database file; ``settings_source``: the config the basis settings came from
    ("defaults" if none)."""

    robot: Robot
    dyn: Dynamics
    db: Database
    db_device: Database
    meta: object
    grid: TimeGrid
    basis_settings: BasisSettings
    settings: OnlineSettings
    source: str
    settings_source: str


def resolve_database_path(path) -> Path:
    """A database ``.npz``, or a run directory holding ``db_final.npz``."""
    path = Path(path)
    if path.is_dir():
        final = path / "db_final.npz"
        if not final.is_file():
            raise UserError(f"{path}: a directory without db_final.npz; expected a database .npz")
        return final
    return path


def load_online_model(
    path,
    backend: str = "rnea",
    settings: OnlineSettings | None = None,
    basis_settings: BasisSettings | None = None,
) -> OnlineModel:
    """Load a database file (or run directory) for online queries.

    The robot is rebuilt from the MJCF stored in the file. Basis settings: ``basis_settings`` if
    given, else the ``basis`` section of a ``config.yaml`` beside the file (a run directory's),
    else `BasisSettings` defaults. Raises `UserError` for unreadable files.
    """
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import robot_from_mjcf_text
    from evojax_motion.motion.database import load_database
    from evojax_motion.motion.timegrid import make_time_grid

    path = resolve_database_path(path)
    db, meta = load_database(path)
    robot = robot_from_mjcf_text(
        meta.robot_name, meta.mjcf, meta.joint_names, meta.site_name, source=f"{path} (robot)"
    )
    settings_source = "given"
    if basis_settings is None:
        cfg_path = path.parent / "config.yaml"
        if cfg_path.is_file():
            from evojax_motion.settings import load_config

            basis_settings, settings_source = load_config(cfg_path).basis, str(cfg_path)
        else:
            basis_settings, settings_source = BasisSettings(), "defaults"
    basis_settings, settings = resolve_settings(basis_settings, settings)
    return OnlineModel(
        robot=robot,
        dyn=make_dynamics(robot, backend=backend),
        db=db,
        db_device=online_database(db),
        meta=meta,
        grid=make_time_grid(db.q.shape[1]),
        basis_settings=basis_settings,
        settings=settings,
        source=str(path),
        settings_source=settings_source,
    )


def _limit_figure(robot: Robot, motion: OnlineResult, i: int, settings: OnlineSettings) -> str:
    """'joint 'elbow' needs 7.2 rad/s at t = 0.31 s into the motion; its limit is 6 rad/s (5.7
    usable with 5 % headroom)' for motion ``i`` (numpy) at its duration."""
    j, kind = int(motion.worst_joint[i]), int(motion.worst_kind[i])
    name = robot.joint_names[j]
    if kind == VELOCITY:
        what, unit, limit = "speed", "rad/s", float(robot.velocity_limit[j])
    else:
        what, unit, limit = "torque", "N m", float(robot.torque_limit[j])
    usable = (1.0 - settings.limit_headroom) * limit
    return (
        f"joint {name!r} needs {float(motion.worst_value[i]):.4g} {unit} of {what} at t = "
        f"{float(motion.worst_time[i]):.3f} s into the motion against a limit of {limit:.4g} "
        f"{unit} ({usable:.4g} usable with {settings.limit_headroom:.0%} headroom)"
    )


def explain_unusable(
    robot: Robot, motion: OnlineResult, i: int, settings: OnlineSettings, window: str = ""
) -> str:
    """Why motion ``i`` of a numpy `OnlineResult` is not usable, in one line (with the figures
    of the binding velocity or torque limit). ``window``: what bounds its duration, e.g.
    "between the reaction time and the ball's arrival" (default: `MAX_DURATION`)."""
    if bool(motion.ok[i]) or not bool(motion.reachable[i]):
        return "the motion is usable" if bool(motion.ok[i]) else "the target is not reachable"
    needed, dur = float(motion.duration_needed[i]), float(motion.duration[i])
    within = (
        motion.torque_margin[i] >= 0 and motion.velocity_margin[i] >= 0 and motion.within_time[i]
    )
    if within or not np.isfinite(motion.worst_value[i]):
        return "the generated motion is not usable (non-finite or outside the joint limits)"
    figure = _limit_figure(robot, motion, i, settings)
    if not np.isfinite(needed):
        return (
            f"no motion within the velocity and torque limits: even in {dur:.3f} s (the longest "
            f"allowed{', ' + window if window else ''}) {figure}"
        )
    return (
        f"the motion needs {needed:.3f} s to stay within the velocity and torque limits but only "
        f"{dur:.3f} s are available{' ' + window if window else ''}: in {dur:.3f} s {figure}"
    )


def describe_limits(robot: Robot, motion: OnlineResult, i: int) -> dict[str, str]:
    """Summary rows of motion ``i`` (numpy): its time scaling and its limit margins."""
    asked, dur = float(motion.duration_asked[i]), float(motion.duration[i])
    rows = {}
    if dur > asked:
        j, kind = int(motion.worst_joint[i]), int(motion.worst_kind[i])
        which = "speed" if kind == VELOCITY else "torque"
        rows["time scaling"] = (
            f"stretched from {asked:.3f} s to {dur:.3f} s ({which} limit of joint "
            f"{robot.joint_names[j]!r})"
        )
    room = float(motion.joint_margin[i])
    rows["limit margins"] = (
        f"torque {float(motion.torque_margin[i]):.3f}, speed "
        f"{float(motion.velocity_margin[i]):.3f} (1 - peak/limit), joint range "
        + (f"{room:.3f} rad" if np.isfinite(room) else "unlimited")
    )
    return rows


def limit_meta(motion: OnlineResult, i: int) -> dict:
    """The margins and the time scaling of motion ``i`` (numpy) for a trajectory file's meta."""
    room = float(motion.joint_margin[i])
    return {
        "duration_asked": float(motion.duration_asked[i]),
        "time_scaled": bool(float(motion.duration[i]) > float(motion.duration_asked[i])),
        "torque_margin": float(motion.torque_margin[i]),
        "velocity_margin": float(motion.velocity_margin[i]),
        "joint_limit_margin": room if np.isfinite(room) else None,
    }
