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
start and an error in the predicted point. The motion ends at ``t_i`` with the hand at rest at
``p_i``; its duration is ``min(t_i - reaction_time, D_nat)`` (an early arm waits rather than
moving slower than a human would), or longer where the velocity or torque limits ask for it
(`online` time scaling: the latest start that still ends at ``t_i``); a motion that would have to
start before the reaction time to stay within them is no catch (``motion.within_time`` False).

A ball that offers no such sample cannot be caught; the plan says why, with the distance from the
ball's path to the reachable region and the time missing.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics, unfused_cpu_program
from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import Database
from evojax_motion.motion.timegrid import TimeGrid
from evojax_motion.online.generation import OnlineResult, build_problem, finish_motion
from evojax_motion.online.limits import joint_limits_f32
from evojax_motion.online.reach import reach_query, resolve_settings
from evojax_motion.settings.compiler import BasisSettings
from evojax_motion.settings.online import CatchSettings, OnlineSettings


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
) -> CatchPlan:
    """Choose the catch of each ball ``p0, v0 (B, 3)`` (module docstring). Pure, jittable."""
    dtype = jnp.asarray(db.q).dtype
    p0, v0 = jnp.asarray(p0, dtype), jnp.asarray(v0, dtype)
    b, s = p0.shape[0], catch.samples
    times = jnp.linspace(0.0, catch.horizon, s, dtype=dtype)
    flight = functools.partial(
        ball_flight, times=times, gravity=gravity, drag=catch.drag, substeps=catch.substeps
    )
    pos, vel = jax.vmap(flight)(p0, v0)  # (B, S, 3)
    reach, _ = reach_query(dyn, db, pos.reshape(b * s, 3), lower, upper, basis_settings, settings)
    depth = reach.depth.reshape(b, s)
    ik_error = reach.ik_error.reshape(b, s)
    reachable = reach.reachable.reshape(b, s)
    d_nat = reach.natural_duration.reshape(b, s)
    # The ball is lost once it has touched the floor (no bounces).
    alive = jnp.cumprod(pos[..., 2] >= 0.0, axis=1).astype(bool)
    available = times[None, :] - catch.reaction_time
    margin = available - d_nat / catch.speedup
    ok = alive & reachable & (margin >= 0.0) & jnp.isfinite(margin)
    score = jnp.minimum(margin / catch.time_scale, depth / catch.space_scale)
    score = jnp.where(ok, score, -jnp.inf)
    idx = jnp.argmax(score, axis=1)
    feasible = jnp.any(ok, axis=1)

    def at(a):
        return jnp.take_along_axis(a, idx[:, None], axis=1)[:, 0]

    t_c = times[idx]
    duration = jnp.minimum(at(available), at(d_nat))
    # Why not: the path's closest approach to the reachable set, and the time short there.
    gap = jnp.where(alive, jnp.maximum(jnp.maximum(-depth, 0.0), ik_error), jnp.inf)
    closest = jnp.argmin(gap, axis=1)
    short = jnp.where(alive & reachable & jnp.isfinite(margin), -margin, jnp.inf)
    time_short = jnp.min(short, axis=1)
    return CatchPlan(
        feasible=feasible,
        sample=jnp.where(feasible, idx, -1).astype(jnp.int32),
        catch_time=t_c,
        catch_point=jnp.take_along_axis(pos, idx[:, None, None], axis=1)[:, 0],
        ball_velocity=jnp.take_along_axis(vel, idx[:, None, None], axis=1)[:, 0],
        duration=duration,
        start_time=t_c - duration,
        time_margin=at(margin),
        depth=at(depth),
        score=at(score),
        closest_gap=jnp.take_along_axis(gap, closest[:, None], axis=1)[:, 0],
        closest_time=times[closest],
        passes_region=jnp.any(alive & reachable, axis=1),
        time_short=jnp.where(jnp.isfinite(time_short), jnp.maximum(time_short, 0.0), 0.0),
        closest_index=closest.astype(jnp.int32),
        late_index=jnp.argmin(short, axis=1).astype(jnp.int32),
        natural_duration=d_nat,
        ball=pos,
        times=jnp.broadcast_to(times, (b, s)),
    )


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
) -> Catch:
    """Plan the catch of balls ``p0, v0 (B, 3)`` and generate the arms' motions from
    ``q_start (B, J)``. Pure (jit it at the top)."""
    lower = jnp.asarray(lower, jnp.asarray(db.q).dtype)
    upper = jnp.asarray(upper, lower.dtype)
    plan = plan_catch(dyn, lower, upper, gravity, basis_settings, settings, catch, db, p0, v0)
    basis, boundary, reach = build_problem(
        dyn, db, plan.catch_point, plan.duration, q_start, lower, upper, basis_settings, settings
    )
    available = plan.catch_time - catch.reaction_time
    motion = finish_motion(
        dyn, grid, lower, upper, settings, basis, boundary, reach, plan.catch_point, available
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
):
    """Jitted ``catcher(db, p0 (B, 3), v0 (B, 3), q_start (B, J)) -> Catch``."""
    lower, upper, gravity, basis_settings, settings, catch = _static_args(
        robot, basis_settings, settings, catch
    )
    dyn, options = unfused_cpu_program(dyn)  # as `online.generation.make_online_generator`
    fn = functools.partial(
        catch_query, dyn, grid, lower, upper, gravity, basis_settings, settings, catch
    )
    return jax.jit(exact_matmuls(fn), compiler_options=options)


def _static_args(robot: Robot, basis_settings, settings, catch):
    """What catcher and planner close over: limits, gravity and the resolved settings."""
    basis_settings, settings = resolve_settings(basis_settings, settings)
    gravity = np.asarray(robot.mj_model.opt.gravity, np.float32)
    lower, upper = joint_limits_f32(robot)
    return lower, upper, gravity, basis_settings, settings, catch or CatchSettings()


def make_planner(
    robot: Robot,
    dyn: Dynamics,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
    catch: CatchSettings | None = None,
):
    """Jitted ``planner(db, p0 (B, 3), v0 (B, 3)) -> CatchPlan`` (no motion)."""
    lower, upper, gravity, basis_settings, settings, catch = _static_args(
        robot, basis_settings, settings, catch
    )
    fn = functools.partial(plan_catch, dyn, lower, upper, gravity, basis_settings, settings, catch)
    return jax.jit(exact_matmuls(fn))


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
