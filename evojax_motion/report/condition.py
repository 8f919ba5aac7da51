"""One condition of a run, for the report's figures: its `Context` (robot, dynamics, time grid,
catch point, boundary conditions) and its motions by interpolation (eq. 1-2), by optimisation
(eq. 3-5) and by the online catch of a thrown ball (sec. 3.2)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from evojax_motion.compile_options import one_shot_jit
from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import compile_interpolation
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.motion.objective import trajectory_measures
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.report.run_folder import RunData
from evojax_motion.settings.online import BALL_RADIUS

INTERP_COMPONENTS = 3  # eq. 1: three principal components + a constant (as conditions.py)
# The thrown ball of catch.gif: released this far from the catch point [m] (in front, a little to
# the right), passing it THROW_SLACK [s] after a motion started at the reaction time would end.
THROW_OFFSET = np.array([1.5, -0.3, 0.0])
THROW_SLACK = 0.1


class Context(NamedTuple):
    """Shared objects for the figures of one condition (built once)."""

    robot: Any
    dyn: Any  # None without a config
    grid: Any
    n_human: int
    condition: int  # index in the condition set
    slot: int  # database row of its evolved primitive
    target: np.ndarray  # (3,) [m]
    duration: float  # [s]
    boundary: Any  # compile_interp.Boundary of one condition


def _pick_condition(data: RunData, requested: int | None, notes: list[str]) -> tuple[int, int]:
    """``(condition, slot)``: the requested one, or the first whose slot is filled in every
    database read. Raises `UserError` for an index out of range."""
    from evojax_motion.motion.database import count_human

    dbs = [x[0] for x in (data.db_gen1, data.db_final) if x is not None]
    ref = dbs[-1] if dbs else data.db_initial[0]
    n_human = count_human(ref)
    m = ref.q.shape[0] - n_human
    if m <= 0:
        raise UserError(f"{data.run_dir}: its databases hold no evolved slot (no condition)")
    c = requested
    if c is None and data.config is not None:
        c = data.config.train.plot_condition
    if c is None:  # as train.py: the condition whose cost fell most, the most telling Fig. 8
        c = 0
        if data.db_gen1 is not None and data.db_final is not None:
            first, last = data.db_gen1[0], data.db_final[0]
            both = np.asarray(first.valid[n_human:]) & np.asarray(last.valid[n_human:])
            if both.any():
                drop = np.where(both, first.cost[n_human:] - last.cost[n_human:], -np.inf)
                c = int(np.argmax(drop))
    if not 0 <= c < m:
        raise UserError(f"--condition: expected an index in 0..{m - 1}, got {c}")
    filled = np.ones(m, bool)
    for db in dbs:
        filled &= np.asarray(db.valid[n_human:])
    if dbs and not filled[c]:
        if not filled.any():
            notes.append("no condition has an evolved primitive in every database")
            return c, n_human + c
        new = int(np.flatnonzero(filled)[0])
        notes.append(f"condition {c} has no evolved primitive in every database; shown: {new}")
        c = new
    return c, n_human + c


def condition_context(
    data: RunData, requested: int | None = None, notes: list[str] | None = None
) -> Context:
    """The robot, dynamics (None without a config), time grid and one condition of a run.

    ``requested``: condition index (None: the config's ``train.plot_condition``); when its slot is
    empty in a database read, the first filled one is taken and ``notes`` says so. The boundary
    conditions are the evolved primitive's own end points (rest start, IK final posture, zero end
    velocities). Raises `UserError` for an index out of range.
    """
    import jax.numpy as jnp

    from evojax_motion.compiler.interpolation import Boundary
    from evojax_motion.motion.database import count_human
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.report.kinematics import robot_from_meta

    pair = data.db_final or data.db_gen1 or data.db_initial
    db, meta = pair
    robot = robot_from_meta(meta, source=f"{data.run_dir} (robot of the database)")
    dyn = None
    if data.config is not None:
        from evojax_motion.model.dynamics import make_dynamics

        dyn = make_dynamics(robot, backend=data.config.dynamics)
    c, slot = _pick_condition(data, requested, [] if notes is None else notes)
    q = np.asarray(db.q[slot], np.float32)
    j = q.shape[1]
    dur = float(db.duration[slot])
    if bool(db.valid[slot]):
        q0, qf = q[0], q[-1]
    else:  # an empty slot: rest to the IK posture is unknown; rest to rest keeps plots possible
        q0 = qf = np.asarray(robot.rest, np.float32)
    zeros = jnp.zeros((1, j), jnp.float32)
    boundary = Boundary(
        q0=jnp.asarray(q0[None]),
        qf=jnp.asarray(qf[None]),
        qd0=zeros,
        qdf=zeros,
        duration=jnp.asarray([dur], jnp.float32),
    )
    return Context(
        robot=robot,
        dyn=dyn,
        grid=make_time_grid(q.shape[0]),
        n_human=count_human(db),
        condition=c,
        slot=slot,
        target=np.asarray(db.condition[slot], np.float64),
        duration=dur,
        boundary=boundary,
    )


def _basis(condition, valid, q, duration, target, settings, n_components: int):
    nb = select_neighbours(
        condition, valid, target[None], settings.neighbours, settings.radius, settings.w_pos
    )
    return nb, pca_basis(q, duration, nb, n_components)


def _interpolation(basis, boundary, samples: int, n_components: int):
    grid = make_time_grid(samples)
    return compile_interpolation(basis, boundary, grid, n_components=n_components).q


def _measures(dyn, samples: int, q, duration):
    return trajectory_measures(dyn, make_time_grid(samples), q, duration)[:2]


# The report's small computations as jitted programs: run op by op, each of their hundreds of
# operations would be dispatched (and compiled) on its own, seconds per call.
_basis_program = one_shot_jit(exact_matmuls(_basis), static_argnums=(5, 6))
_interpolation_program = one_shot_jit(exact_matmuls(_interpolation), static_argnums=(2, 3))
_measures_program = one_shot_jit(exact_matmuls(_measures), static_argnums=(0, 1))


def neighbour_basis(db, target, basis_settings, n_components: int, exclude=None):
    """``(Neighbours, Basis)`` of one target on ``db`` (row ``exclude`` left out)."""
    valid = np.asarray(db.valid).copy()
    if exclude is not None:
        valid[exclude] = False
    return _basis_program()(
        np.asarray(db.condition, np.float32),
        valid,
        np.asarray(db.q, np.float32),
        np.asarray(db.duration, np.float32),
        np.asarray(target, np.float32),
        basis_settings,
        n_components,
    )


def interpolate(db, ctx: Context, basis_settings, exclude=None) -> np.ndarray:
    """Eq. 1-2 trajectory ``(T, J)`` of the condition on ``db``."""
    _, basis = neighbour_basis(db, ctx.target, basis_settings, INTERP_COMPONENTS, exclude)
    samples = ctx.grid.s.shape[0]
    q = _interpolation_program()(basis, ctx.boundary, samples, INTERP_COMPONENTS)
    return np.asarray(q[0])


def motion_cost(ctx: Context, q) -> tuple[float, float]:
    """Eq. 5 cost and torque sum [N m] of ``q (T, J)``."""
    q = np.asarray(q, np.float32)
    cost, tsum = _measures_program()(ctx.dyn, q.shape[0], q, np.float32(ctx.duration))
    return float(cost), float(tsum)


def optimise(data: RunData, ctx: Context) -> np.ndarray:
    """Eq. 3-5 trajectory ``(T, J)`` of the condition on the last database (leave-one-out)."""
    from evojax_motion.compiler.optimisation import make_optimisation_compiler

    cfg = data.config
    settings = cfg.compiler
    _, basis = neighbour_basis(
        data.db_final[0],
        ctx.target,
        cfg.basis,
        max(settings.n_components, INTERP_COMPONENTS),
        exclude=ctx.slot,
    )
    compile_opt = make_optimisation_compiler(
        ctx.dyn, ctx.grid, ctx.robot.lower, ctx.robot.upper, settings
    )
    out = compile_opt(basis, ctx.boundary)
    return np.asarray(out.q[0])


def _online_catch(data: RunData, ctx: Context):
    """The online query (`online.generation.make_online_generator`) for the condition's catch
    point."""
    from evojax_motion.online.generation import make_online_generator, online_database, to_numpy

    gen = make_online_generator(ctx.robot, ctx.dyn, ctx.grid, data.config.basis, one_shot=True)
    res = gen(
        online_database(data.db_final[0]),
        np.asarray(ctx.target, np.float32)[None],
        np.asarray([ctx.duration], np.float32),
        np.asarray(ctx.robot.rest, np.float32)[None],
    )
    return to_numpy(res)


def throw(target, duration: float, gravity, reaction_time: float):
    """The ball of ``catch.gif``: released `THROW_OFFSET` from ``target (3,)`` [m], passing it
    when a motion of ``duration`` [s] started after ``reaction_time`` [s] would end, plus
    `THROW_SLACK`. Returns the release point ``(3,)`` [m], velocity ``(3,)`` [m/s] and that
    passing time [s]."""
    target = np.asarray(target, float)
    t_pass = reaction_time + duration + THROW_SLACK
    p0 = target + THROW_OFFSET
    v0 = (target - p0 - 0.5 * np.asarray(gravity, float) * t_pass**2) / t_pass
    return p0, v0, t_pass


def catch_animation(data: RunData, ctx: Context, frames: int, notes: list[str]):
    """A ball thrown through the condition's catch point, caught on the last database.

    The ball is released `THROW_OFFSET` from the catch point, timed to pass it when a motion of
    the condition's duration started after the reaction time would end (+ `THROW_SLACK`);
    `online.catching.make_catcher` plans where and when to catch it and generates the motion.
    Should it
    find no catch, the online query to the catch point itself is shown, timed to the ball.
    Returns ``q (F, J)``, ``ball (F, 3)`` at ``frames`` instants and the real-time fps.
    """
    import jax

    from evojax_motion.online.catching import CatchSettings, explain_plan, make_catcher
    from evojax_motion.online.generation import online_database
    from evojax_motion.report import kinematics as kin

    settings = CatchSettings()
    gravity = np.asarray(ctx.robot.mj_model.opt.gravity, float)
    p0, v0, t_pass = throw(ctx.target, ctx.duration, gravity, settings.reaction_time)
    catcher = make_catcher(
        ctx.robot, ctx.dyn, ctx.grid, data.config.basis, None, settings, one_shot=True
    )
    rest = np.asarray(ctx.robot.rest, np.float32)[None]
    f32 = np.float32
    db = online_database(data.db_final[0])
    plan, motion = jax.device_get(catcher(db, p0[None].astype(f32), v0[None].astype(f32), rest))
    ball_t, ball = np.asarray(plan.times[0], float), np.asarray(plan.ball[0], float)
    release = f"ball released at {np.round(p0, 2).tolist()} m, {np.round(v0, 2).tolist()} m/s"
    if bool(plan.feasible[0]):
        t_motion, q, t_catch = motion.t[0], motion.q[0], float(plan.catch_time[0])
        notes.append(f"catch.gif: {release}; {explain_plan(plan, 0)}")
    else:
        online = _online_catch(data, ctx)
        t_catch = t_pass
        t_motion = online.t[0] + (t_pass - float(online.duration[0]))
        q = online.q[0]
        notes.append(
            f"catch.gif: {release}; no catch planned ({explain_plan(plan, 0)}); "
            "shown: the online query to the catch point"
        )
    t_end = 1.25 * t_catch  # hold the catch a moment
    times = np.linspace(0.0, t_end, frames)
    q_f, ball_f = kin.catch_frames(ctx.robot, t_motion, q, ball_t, ball, t_catch, times)
    return q_f, ball_f, frames / t_end


def catch_camera(robot, q, balls):
    """The camera of ``catch.gif``: the arm's motion ``q (F, J)`` and every ball position
    ``balls (F, 3)`` [m] in the picture (the ball never leaves the view), ball's radius included."""
    from evojax_motion.report import kinematics as kin

    balls = np.asarray(balls, float)
    # the ball's extent: its centre +- the radius along each axis
    offsets = BALL_RADIUS * np.concatenate([np.eye(3), -np.eye(3)])
    points = (balls[:, None, :] + offsets[None]).reshape(-1, 3)
    return kin.fit_camera(robot, [q], kin.VIEWS["catch"], points)
