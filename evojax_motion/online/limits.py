"""Limits of online motions (`generation`, steps 4 and 6): the joint limits by a null-space
projection of the interpolation (`enforce_limits`), the velocity and torque limits by time
scaling (`time_law`, `shortest_duration`) and the margins to them.

Joint limits. Per joint the BC system of eq. 2 is ``A x = b`` in the coefficients of eq. 1; with
``K_lim`` components (default 4, the optimisation compiler's basis) its solutions are
``x = x_ls + N z`` (``compiler.interpolation.solve_boundary``: ``N`` spans the null space, in
prior units of the neighbours' spread). Any z keeps the BCs, so limits are enforced by the smallest
such z:

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
e.g. gravity alone over a torque limit fails at any D. A motion with a deadline (a catch) first
blends each joint too fast for it toward its minimum-jerk path (`fit_speed`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.interpolation import Boundary, basis_functions, solve_boundary
from evojax_motion.linalg.cholesky import spd_solve
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.robot import Robot
from evojax_motion.motion import profiles
from evojax_motion.motion.profiles import rest_to_rest
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.settings.online import MAX_DURATION, OnlineSettings


def joint_limits_f32(robot: Robot):
    return np.asarray(robot.lower, np.float32), np.asarray(robot.upper, np.float32)


def minimum_jerk(grid: TimeGrid, q0, qf) -> jnp.ndarray:
    """Rest-to-rest minimum-jerk paths ``q0 (C, J) -> qf (C, J)``: ``(C, T, J)``.

    Monotone between q0 and qf, so inside any box that holds both ends.
    """
    return rest_to_rest(profiles.minimum_jerk(jnp.asarray(grid.s, q0.dtype)), q0, qf)


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
    corrections: bool = True,
):
    """Step 4: ``q (C, T, J)`` moved inside ``[lower, upper] (J,)`` keeping the BCs (see module).

    ``basis`` must hold ``settings.limit_components`` components. Returns ``(q (C, T, J),
    limit_excess (C,), fallback (C,))``: the largest violation of the input and whether the
    minimum-jerk blend was needed. ``corrections`` False (static): the projection is not traced and
    ``q`` comes back as given (a program for motions already inside: ``limit_excess`` > 0 says
    that one was not).
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

    def keep(q):
        return q, jnp.zeros(q.shape[0], bool)

    # Most motions are inside already: skip the work (a select, not a branch, under vmap).
    q, fallback = jax.lax.cond(jnp.any(outside), project, keep, q) if corrections else keep(q)
    return q, jnp.maximum(excess, 0.0), fallback


TORQUE, VELOCITY = 0, 1  # `generation.OnlineResult.worst_kind`


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


def peak_margin(peak, limit):
    """``min_j 1 - peak_j / limit_j`` over ``peak (C, J)``; 1 where no joint has a limit."""
    return jnp.min(jnp.where(jnp.isfinite(limit), 1.0 - peak / limit, 1.0), axis=1)


SPEED_BLENDS = (0.0, 0.25, 0.5, 0.75, 1.0)  # `fit_speed`'s candidate weights of minimum jerk
PLATEAU_RAMP = 0.3  # `plateau_path`'s share of the motion spent speeding up (and slowing down)


def plateau_path(grid: TimeGrid, q0, qf, ramp: float = PLATEAU_RAMP) -> jnp.ndarray:
    """Rest-to-rest paths ``q0 (C, J) -> qf (C, J)`` at a speed plateau (`motion.profiles.plateau`):
    ``(C, T, J)``. Peak speed ``1 / (1 - ramp)`` (1.43 at the default) times the mean, against
    1.875 for minimum jerk, at ``1.5 / (ramp (1 - ramp))`` (7.1) against 5.8 times the mean
    acceleration. Monotone between q0 and qf, so inside any box that holds both ends.
    """
    return rest_to_rest(profiles.plateau(jnp.asarray(grid.s, q0.dtype), ramp), q0, qf)


def fit_speed(grid: TimeGrid, q, q0, qf, duration, vel_usable):
    """Paths ``q (C, T, J)`` whose joints would be too fast at ``duration (C,)`` made slower,
    per joint: blended toward the rest-to-rest minimum-jerk path ``q0 -> qf (C, J)`` by the
    smallest weight of `SPEED_BLENDS` with ``|qd| <= vel_usable (J,)`` at that duration, else
    replaced by `plateau_path` (the candidates' lowest peak speed; kept also where it is still
    too fast). A joint fast enough keeps its path exactly; every candidate keeps the BCs and
    stays inside any box holding both paths. Returns ``(q, choice (C, J))``: the index into
    `SPEED_BLENDS`, or ``len(SPEED_BLENDS)`` for the plateau.
    """
    safe = minimum_jerk(grid, q0, qf)
    paths = [(1.0 - lam) * q + lam * safe if lam > 0 else q for lam in SPEED_BLENDS]
    paths.append(plateau_path(grid, q0, qf))
    ones = jnp.ones(q.shape[0], q.dtype)

    def peak(path):  # (C, J) largest speed of the path at the duration
        qd = derivatives(grid, path, ones)[0]
        return jnp.max(jnp.abs(qd), axis=1) / duration[:, None]

    fits = jnp.stack([peak(path) <= vel_usable for path in paths])  # (L, C, J)
    first = jnp.where(jnp.any(fits, axis=0), jnp.argmax(fits, axis=0), len(paths) - 1)
    chosen = jnp.take_along_axis(jnp.stack(paths), first[None, :, None, :], axis=0)[0]
    return chosen, first
