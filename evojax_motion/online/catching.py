"""Catching a thrown ball: where and when to catch it, and the arm's motion (paper sec. 4).

The paper assumes "the estimated falling point of a ball is given" (sec. 4); this module supplies
it from the ball's release position and velocity, then generates the catch with the online process
(sec. 3.2, `online`).

Ball. Ballistic flight under the robot model's gravity (``mjModel.opt.gravity``), optionally with
quadratic air drag ``a = g - k |v| v`` (``k = rho C_d A / (2 m)`` [1/m]; a baseball ~0.006, a
tennis ball ~0.01), integrated by RK4; without drag the closed form. The flight is examined at
``samples`` instants over ``horizon`` seconds; the ball is lost once it falls below the floor
(z < 0).

Catch point. A sample ``(t_i, p_i)`` can be the catch when
  - ``p_i`` is reachable (`online.reach.Reach`: inside the learned region and reached by the
  IK), and
  - the hand can get there in time: the motion starts after the ``reaction_time`` and may be at
    most ``speedup`` times faster than the natural (the neighbours' mean) duration ``D_nat``:
    ``time margin = (t_i - reaction_time) - D_nat(p_i) / speedup >= 0``.
Among those, the sample with the largest ``min(time margin / time_scale, depth / space_scale)``
is chosen (depth: how far ``p_i`` lies inside the learned region): a catch robust to both a late
start and an error in the predicted point. The motion ends at ``t_i`` with the hand at rest
there; its duration is ``min(t_i - reaction_time, D_nat)`` (an early arm waits rather than
moving slower than a human would), or longer where the velocity or torque limits ask for it
(`online` time scaling: the latest start that still ends at ``t_i``); a motion that would have to
start before the reaction time to stay within them is no catch (``motion.within_time`` False).
The search is staged so that one ball plans in a few milliseconds: every sample gets its nearest
database condition (one distance matrix), the `REGION_SAMPLES` most promising by that get the
neighbour search, and the `CANDIDATES` best of those the IK. `catch_query` generates the motion
of the best catch and, only when that motion is not usable (mostly: too fast for the limits),
those of `MOTION_OPTIONS` - 1 further ones, the latest catches first (the most time for the
arm), and keeps the best usable one.

The palm (`online.palm`: `palm_normal`, `catch_posture`). A hand catches with its palm: a
ball arriving at the back of the hand or at the fingertips bounces off (docs/simulation.md
measured this: with the position-only posture the palm faced away from the incoming ball in
most throws). Where the end-effector site lies on a surface of the hand's geometry, its outward
normal is the palm's, and the catch posture puts the point one ball radius in front of the palm
(``site + r n``) at the catch point, turning the palm toward the incoming ball in the null space
of that, then toward the human-like posture. The ball's centre then reaches the catch point as
its surface touches the palm at the site. The turn is added to the interpolated motion as a
rest-to-rest minimum-jerk offset (`generation.finish_motion`'s
``final_shift``), so the path stays the neighbours' interpolation plus a smooth turn.

A ball that offers no such sample cannot be caught; the plan says why, with the distance from the
ball's path to the reachable region and the time missing.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compiler.basis import Neighbours
from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import Database
from evojax_motion.motion.timegrid import TimeGrid
from evojax_motion.online.generation import (
    OnlineResult,
    finish_motion,
    kept_trace,
    problem_of,
    program_dynamics,
)
from evojax_motion.online.limits import joint_limits_f32
from evojax_motion.online.palm import catch_posture, palm_normal
from evojax_motion.online.reach import (
    Reach,
    final_posture,
    reach_of,
    region_query,
    resolve_settings,
)
from evojax_motion.settings.compiler import BasisSettings
from evojax_motion.settings.online import BALL_RADIUS, CatchSettings, OnlineSettings

REGION_SAMPLES = 32  # samples of the ball's path that get the neighbour search (`plan_catch`)
CANDIDATES = 16  # of those, samples that get the IK
MOTION_OPTIONS = 4  # catches of a ball whose motions are generated; the best usable one wins


class CatchPlan(NamedTuple):
    """Where and when to catch each of B balls (arrays ``(B,)`` unless noted).

    feasible: a catch exists; sample: index of the chosen ball sample (-1 if none);
    catch_time [s after release]; catch_point: (B, 3) [m]; ball_velocity: (B, 3) at the catch
    [m/s]; duration: of the arm's motion [s]; start_time: when it starts [s after release];
    time_margin [s]; depth [m] inside the learned region; score: the chosen
    ``min(margin / scale)``.
    When infeasible, why: closest_gap [m]: the smallest distance of the ball's path to the
    reachable set (max of the region gap and the IK miss); closest_time [s]: when it occurs;
    passes_region: the path crosses the reachable set at all (then the ball is only too fast);
    time_short [s]: the time missing at the reachable sample with the best time margin (0 if
    no sample is reachable); closest_index, late_index: those two samples (for ``--nearest``);
    natural_duration: (B, S) the neighbours' mean duration along the path [s];
    ball: (B, S, 3) the ball's positions at ``times (B, S)`` [s after release].
    """

    feasible: jnp.ndarray
    sample: jnp.ndarray
    catch_time: jnp.ndarray
    catch_point: jnp.ndarray
    ball_velocity: jnp.ndarray
    duration: jnp.ndarray
    start_time: jnp.ndarray
    time_margin: jnp.ndarray
    depth: jnp.ndarray
    score: jnp.ndarray
    closest_gap: jnp.ndarray
    closest_time: jnp.ndarray
    passes_region: jnp.ndarray
    time_short: jnp.ndarray
    closest_index: jnp.ndarray
    late_index: jnp.ndarray
    natural_duration: jnp.ndarray
    ball: jnp.ndarray
    times: jnp.ndarray
    palm_facing: jnp.ndarray


def ball_flight(p0, v0, times, gravity, drag: float, substeps: int):
    """Ball positions and velocities at ``times (S,)`` (increasing, from 0) after release.

    ``p0, v0, gravity (3,)``. Returns ``pos (S, 3)``, ``vel (S, 3)``. Closed form without drag,
    RK4 with ``substeps`` steps per interval with it.
    """
    t = times[:, None]
    if drag == 0.0:
        return p0 + v0 * t + 0.5 * gravity * t**2, v0 + gravity * t

    def accel(v):
        return gravity - drag * jnp.linalg.norm(v) * v

    def rk4(state, dt):
        def f(s):
            return jnp.stack([s[1], accel(s[1])])

        k1 = f(state)
        k2 = f(state + 0.5 * dt * k1)
        k3 = f(state + 0.5 * dt * k2)
        k4 = f(state + dt * k3)
        return state + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

    def interval(state, dt):
        h = dt / substeps
        state = jax.lax.fori_loop(0, substeps, lambda _, s: rk4(s, h), state)
        return state, state

    start = jnp.stack([p0, v0])
    _, states = jax.lax.scan(interval, start, jnp.diff(times))
    states = jnp.concatenate([start[None], states], axis=0)
    return states[:, 0], states[:, 1]


def plan_catch(
    dyn: Dynamics,
    lower,
    upper,
    gravity,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
    catch: CatchSettings,
    db: Database,
    p0,
    v0,
    options: int = 1,
) -> tuple[CatchPlan, Reach, Neighbours]:
    """Choose the catch of each ball ``p0, v0 (B, 3)`` (module docstring). Pure, jittable.

    ``options`` > 1: the ``options`` best catches of each ball, best first, as a plan of
    ``B * options`` rows (ball-major; a row with ``feasible`` False where a ball has fewer).
    Returns ``(plan, reach, neighbours)``: the `CatchPlan` and, per row, steps 1-2 at its catch
    point (done while choosing; `catch_query` builds the motions on them).
    """
    dtype = jnp.asarray(db.q).dtype
    p0, v0 = jnp.asarray(p0, dtype), jnp.asarray(v0, dtype)
    b, s = p0.shape[0], catch.samples
    times = jnp.linspace(0.0, catch.horizon, s, dtype=dtype)
    flight = functools.partial(
        ball_flight, times=times, gravity=gravity, drag=catch.drag, substeps=catch.substeps
    )
    pos, vel = jax.vmap(flight)(p0, v0)  # (B, S, 3)
    # The ball is lost once it has touched the floor (no bounces).
    alive = jnp.cumprod(pos[..., 2] >= 0.0, axis=1).astype(bool)
    available = times[None, :] - catch.reaction_time
    # Stage 0, every sample: the nearest valid condition (a lower bound of the region's gap)
    # and a guess of the score with the database's mean duration; the REGION_SAMPLES best go on.
    cond, valid = jnp.asarray(db.condition, dtype), jnp.asarray(db.valid)
    # |p - c|^2 by one matrix product (a few mm of rounding at the radius: only a ranking here)
    d2 = (
        jnp.sum(pos**2, axis=-1)[..., None]
        + jnp.sum(cond**2, axis=-1)
        - 2.0 * jnp.einsum("bsk,nk->bsn", pos, cond)
    )  # (B, S, N)
    nearest = jnp.sqrt(jnp.maximum(jnp.min(jnp.where(valid, d2, jnp.inf), axis=-1), 0.0))
    gap0 = jnp.maximum(nearest - basis_settings.radius, 0.0)
    mean_duration = jnp.sum(jnp.where(valid, db.duration, 0.0)) / jnp.maximum(jnp.sum(valid), 1)
    guess = jnp.minimum(
        (available - mean_duration / catch.speedup) / catch.time_scale,
        (basis_settings.radius - nearest) / catch.space_scale,
    )
    key0 = jnp.where(gap0 <= 0.0, guess, -1e9 - jnp.minimum(gap0, 1e3))
    r = min(REGION_SAMPLES, s)
    _, sub = jax.lax.top_k(jnp.where(alive, key0, -jnp.inf), r)  # (B, R) sample indices

    def of_sub(a):  # (B, S, ...) -> (B, R, ...)
        return jnp.take_along_axis(a, sub.reshape(sub.shape + (1,) * (a.ndim - 2)), axis=1)

    # Stage 1 (the learned region, the natural duration) at those samples.
    depth, region_gap, d_nat, n_inside, nb = region_query(
        db, of_sub(pos).reshape(b * r, 3), basis_settings, settings
    )
    depth, region_gap, d_nat, n_inside = (
        x.reshape(b, r) for x in (depth, region_gap, d_nat, n_inside)
    )
    alive_r, t_r = of_sub(alive), times[sub]
    available_r = t_r - catch.reaction_time
    margin = available_r - d_nat / catch.speedup
    inside = alive_r & (region_gap <= 0.0)
    timely = inside & (margin >= 0.0) & jnp.isfinite(margin)
    score = jnp.minimum(margin / catch.time_scale, depth / catch.space_scale)
    # Stage 2 (the IK) only at the CANDIDATES best of them: in time and inside the region by
    # score, then inside but late by time margin, then the rest by their gap to the region.
    key = jnp.where(
        timely,
        score,
        jnp.where(inside, -1e6 + jnp.clip(margin, -1e3, 0.0), -1e9 - jnp.minimum(region_gap, 1e3)),
    )
    m = min(CANDIDATES, r)
    _, cand = jax.lax.top_k(jnp.where(alive_r, key, -jnp.inf), m)  # (B, M) indices into R
    flat = (jnp.arange(b)[:, None] * r + cand).reshape(-1)
    nb_c = jax.tree_util.tree_map(lambda x: x[flat], nb)
    points = of_sub(pos).reshape(b * r, 3)[flat]
    ik = final_posture(dyn, db, points, nb_c, lower, upper, settings)
    ik_error = ik.pos_error.reshape(b, m)

    def cand_of(a):
        return jnp.take_along_axis(a, cand, axis=1)

    reach_c = cand_of(inside) & (ik_error <= settings.reach_tolerance)
    ok_c = reach_c & cand_of(timely)
    score_c = jnp.where(ok_c, cand_of(score), -jnp.inf)
    sample_c = jnp.take_along_axis(sub, cand, axis=1)  # (B, M) sample indices
    k = min(options, m)
    # Options: the best score first, then the latest catches (the most time for the arm).
    first = jnp.argmax(score_c, axis=1)
    later = jnp.where(ok_c, sample_c.astype(dtype), -jnp.inf)
    later = later.at[jnp.arange(b), first].set(jnp.inf)
    _, best = jax.lax.top_k(later, k)  # (B, K) indices into M
    feasible = jnp.take_along_axis(ok_c, best, axis=1)
    pick = jnp.where(feasible, best, 0)

    option_rows = (jnp.arange(b)[:, None] * m + pick).reshape(-1)  # (B * K,) into B * M

    def at_rows(a):  # (B * M, ...) -> (B * K, ...) at the options
        return a[option_rows]

    def at(a):  # (B, M) -> (B * K,) at the options
        return at_rows(a.reshape(-1))

    idx = jnp.where(feasible.reshape(-1), at(sample_c), 0)
    # Why not: the path's closest approach to the reachable set (the region's gap; the IK's miss
    # too at the candidates; the nearest condition's gap elsewhere, a lower bound), and the time
    # short at the reachable candidate latest to be late.
    rows = jnp.arange(b)[:, None]
    gap = gap0.at[rows, sub].set(region_gap)
    gap = gap.at[rows, sample_c].max(ik_error)
    gap = jnp.where(alive, gap, jnp.inf)
    closest = jnp.argmin(gap, axis=1)
    short = jnp.where(reach_c & jnp.isfinite(cand_of(margin)), -cand_of(margin), jnp.inf)
    late = jnp.take_along_axis(sample_c, jnp.argmin(short, axis=1)[:, None], axis=1)[:, 0]
    time_short = jnp.min(short, axis=1)
    natural = jnp.full((b, s), jnp.nan, dtype).at[rows, sub].set(d_nat)
    t_c = times[idx]
    duration = jnp.minimum(t_c - catch.reaction_time, at(cand_of(d_nat)))
    feasible = feasible.reshape(-1)

    def per_option(a):  # (B, ...) -> (B * K, ...)
        return jnp.repeat(a, k, axis=0)

    ik_k = jax.tree_util.tree_map(at_rows, ik)
    reach = reach_of(
        dyn, at(cand_of(depth)), at(cand_of(region_gap)), at(cand_of(d_nat)),
        at(cand_of(n_inside)), ik_k, settings,
    )  # fmt: skip
    b_rows = jnp.arange(b * k)
    plan = CatchPlan(
        feasible=feasible,
        sample=jnp.where(feasible, idx, -1).astype(jnp.int32),
        catch_time=t_c,
        catch_point=per_option(pos)[b_rows, idx],
        ball_velocity=per_option(vel)[b_rows, idx],
        duration=duration,
        start_time=t_c - duration,
        time_margin=at(cand_of(margin)),
        depth=at(cand_of(depth)),
        score=jnp.where(feasible, at(score_c), -jnp.inf),
        closest_gap=per_option(jnp.take_along_axis(gap, closest[:, None], axis=1)[:, 0]),
        closest_time=per_option(times[closest]),
        passes_region=per_option(jnp.any(reach_c, axis=1)),
        time_short=per_option(
            jnp.where(jnp.isfinite(time_short), jnp.maximum(time_short, 0.0), 0.0)
        ),
        closest_index=per_option(closest.astype(jnp.int32)),
        late_index=per_option(late.astype(jnp.int32)),
        natural_duration=per_option(natural),
        ball=per_option(pos),
        times=jnp.broadcast_to(times, (b * k, s)),
        palm_facing=jnp.full(b * k, jnp.nan, dtype),
    )
    return plan, reach, jax.tree_util.tree_map(at_rows, nb_c)


class Catch(NamedTuple):
    """A plan and its motion: ``plan`` (`CatchPlan`; ``duration`` and ``start_time`` are the
    motion's, after time scaling), ``motion`` (`online.generation.OnlineResult`, with ``t`` in
    seconds after
    release). ``motion.ok`` and ``plan.feasible`` both matter."""

    plan: CatchPlan
    motion: OnlineResult


def catch_query(
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    gravity,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
    catch: CatchSettings,
    db: Database,
    p0,
    v0,
    q_start,
    palm=None,
) -> Catch:
    """Plan the catch of balls ``p0, v0 (B, 3)`` and generate the arms' motions from
    ``q_start (B, J)``. Pure (jit it at the top)."""
    lower = jnp.asarray(lower, jnp.asarray(db.q).dtype)
    upper = jnp.asarray(upper, lower.dtype)
    b = jnp.shape(p0)[0]
    chosen = plan_catch(
        dyn, lower, upper, gravity, basis_settings, settings, catch, db, p0, v0, MOTION_OPTIONS
    )
    k = chosen[0].feasible.shape[0] // b  # fewer options where the path has fewer candidates
    q_start = jnp.asarray(q_start)
    motions = functools.partial(_catch_motions, dyn, grid, lower, upper, settings, catch, db, palm)
    options = chosen[0].feasible.reshape(b, k)

    @jax.jit  # traced once: for the loop's state (`eval_shape`) and in the loop's body
    def option(i):  # the motions of every ball's option i
        plan, reach, nb = jax.tree_util.tree_map(lambda a: a[jnp.arange(b) * k + i], chosen)
        return motions(plan, reach, nb, q_start)

    def more(state):  # another option is left for a ball whose motion is not usable yet
        i, best = state
        waiting = ~best.motion.ok & jnp.any(options & (jnp.arange(k) >= i), axis=1)
        return (i == 0) | ((i < k) & jnp.any(waiting))

    def next_option(state):
        i, best = state
        new = option(i)
        take = (i == 0) | (~best.motion.ok & new.motion.ok)  # (B,)

        def choose(x, y):
            return jnp.where(take.reshape(take.shape + (1,) * (x.ndim - 1)), x, y)

        return i + 1, jax.tree_util.tree_map(choose, new, best)

    # One option after the other (one compiled motion generation): most balls' best option is
    # usable and costs one; the others only while a ball has no usable motion yet.
    first = jnp.asarray(0)
    shapes = jax.eval_shape(option, first)
    empty = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
    return jax.lax.while_loop(more, next_option, (first, empty))[1]


def _catch_motions(
    dyn, grid, lower, upper, settings, catch, db, palm, plan: CatchPlan, reach, nb, q_start
) -> Catch:
    """The motions of the catches ``plan`` (one per row; ``reach``, ``nb``: steps 1-2 at their
    catch points) from ``q_start`` (`catch_query`)."""
    basis, boundary, reach = problem_of(db, reach, nb, plan.duration, q_start, settings)
    target = plan.catch_point
    if palm is not None:  # the palm faces the ball and holds it: `catch_posture`
        speed = jnp.linalg.norm(plan.ball_velocity, axis=1, keepdims=True)
        facing = -plan.ball_velocity / jnp.maximum(speed, 1e-9)
        qf, target, cosine = catch_posture(
            dyn, reach.q_final, reach.q_final, plan.catch_point, facing, palm, BALL_RADIUS,
            lower, upper,
        )  # fmt: skip
        shift = qf - reach.q_final
        reach = reach._replace(q_final=qf)
        plan = plan._replace(palm_facing=cosine)
    else:
        shift = None
    available = plan.catch_time - catch.reaction_time
    motion = finish_motion(
        dyn, grid, lower, upper, settings, basis, boundary, reach, target, available, shift
    )
    # Time scaling may have slowed the motion down: it starts earlier, still ending at the catch.
    start = plan.catch_time - motion.duration
    plan = plan._replace(duration=motion.duration, start_time=start)
    motion = motion._replace(t=motion.t + start[:, None], ok=motion.ok & plan.feasible)
    return Catch(plan, motion)


def make_catcher(
    robot: Robot,
    dyn: Dynamics,
    grid: TimeGrid,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
    catch: CatchSettings | None = None,
    one_shot: bool = False,
    cache_parts: Any = None,
):
    """Jitted ``catcher(db, p0 (B, 3), v0 (B, 3), q_start (B, J)) -> Catch``. ``one_shot``: for
    a ball or two (the command line): compiled faster, run slower (`compile_options.ONE_SHOT`:
    on 2 CPU cores 10.3 -> 3.9 s to compile, 1.6 -> 3.4 ms a ball; on accelerators the vector
    RNEA layout: `online.generation.program_dynamics`). ``cache_parts``: as
    `online.generation.make_online_generator`'s (the catch settings are added here)."""
    basis_settings, settings = resolve_settings(basis_settings, settings)
    gravity = np.asarray(robot.mj_model.opt.gravity, np.float32)
    lower, upper = joint_limits_f32(robot)
    dyn, options = program_dynamics(dyn, one_shot)
    catch = catch or CatchSettings()
    fn = functools.partial(
        catch_query, dyn, grid, lower, upper, gravity, basis_settings, settings, catch,
        palm=palm_normal(robot),
    )  # fmt: skip
    parts = None if cache_parts is None else {**cache_parts, "catch": repr(catch)}
    return kept_trace(fn, "online.catch", parts, options)


def validate_ball(ball, where: str = "--ball") -> tuple[np.ndarray, np.ndarray]:
    """``(PX, PY, PZ, VX, VY, VZ)`` or ``(B, 6)`` -> ``p0, v0 (B, 3)`` float32; else `UserError`."""
    arr = np.asarray(ball, np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 6 or arr.shape[0] == 0:
        raise UserError(
            f"{where}: expected release position and velocity PX PY PZ VX VY VZ [m, m/s], "
            f"got shape {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise UserError(f"{where}: expected finite numbers, got NaN/inf")
    if (np.linalg.norm(arr[:, 3:], axis=1) > 100).any():
        raise UserError(f"{where}: expected a release speed <= 100 m/s")
    return arr[:, :3].astype(np.float32), arr[:, 3:].astype(np.float32)


def explain_plan(plan: CatchPlan, i: int = 0) -> str:
    """One line on ball ``i`` of a (numpy) plan: the catch and its margins, or why there is none."""
    if bool(plan.feasible[i]):
        p = np.round(np.asarray(plan.catch_point[i], float), 3).tolist()
        return (
            f"catch at t = {float(plan.catch_time[i]):.3f} s at {p} m; motion "
            f"{float(plan.start_time[i]):.3f} -> {float(plan.catch_time[i]):.3f} s; margins: "
            f"time {float(plan.time_margin[i]):.3f} s, depth {float(plan.depth[i]):.3f} m"
        )
    gap = float(plan.closest_gap[i])
    if not bool(plan.passes_region[i]):
        return (
            f"the ball cannot be caught: its path comes no closer than {gap:.3f} m to the "
            f"reachable region (at t = {float(plan.closest_time[i]):.3f} s)"
        )
    return (
        f"the ball cannot be caught: it passes through the reachable region too early; the arm "
        f"would need {float(plan.time_short[i]):.3f} s more"
    )
