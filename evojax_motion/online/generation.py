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
   limits"): `limits.enforce_limits`;
5. ``qd, qdd`` from the time grid and ``tau`` by inverse dynamics (eq. 4), the eq. 5 cost;
6. velocity and torque limits by time scaling: `limits.shortest_duration`.

Everything is one jitted function over any number of targets (`make_online_generator`; pieces:
`reach.reach_query` = steps 1-2, `build_problem` + `finish_motion` = steps 1-5). Outside the learned
region (fewer than ``min_neighbours`` primitives within the radius) or out of the IK's reach a
target is flagged, with its distance; `reach.nearest_reachable` finds a reachable point near it.
Float32 matrix products are traced at full precision (`exact_matmuls`): GPUs default to TF32.

The joint limits (step 4) and the time scaling within the velocity and torque limits (step 6)
are explained in `limits`; what a user is told about a motion's limits, in `explain`. The
query's settings: `settings.online.OnlineSettings`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import one_shot as one_shot_options
from evojax_motion.compiler.basis import pca_basis
from evojax_motion.compiler.interpolation import (
    Boundary,
    boundary_residual,
    compile_interpolation,
)
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics, one_shot_layout, unfused_cpu_program
from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import Database
from evojax_motion.motion.objective import cost_from_torques
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.online.limits import (
    VELOCITY,
    enforce_limits,
    fit_speed,
    joint_limits_f32,
    minimum_jerk,
    peak_margin,
    shortest_duration,
    time_law,
    usable_limits,
)
from evojax_motion.online.reach import Reach, reach_query, resolve_settings
from evojax_motion.settings.compiler import BasisSettings
from evojax_motion.settings.online import MAX_DURATION, OnlineSettings


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
    and within the time allowed (a usable motion); corrected: (B,) eq. 1 left the joint limits
    or the usable velocity and torque limits at the asked duration, so step 4 or 6 changed the
    motion (or, in a query without its corrections, would have: `finish_motion`).
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
    corrected: jnp.ndarray


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
    reach, nb = reach_query(dyn, db, targets, lower, upper, basis_settings, settings)
    return problem_of(db, reach, nb, duration, q_start, settings)


def problem_of(db: Database, reach: Reach, nb, duration, q_start, settings: OnlineSettings):
    """`build_problem` for targets whose steps 1-2 are done: ``reach`` and its neighbours ``nb``
    (`online.reach.reach_query`; a catch plan computes them while choosing). Pure."""
    dtype = jnp.asarray(db.q).dtype
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
    final_shift=None,
    corrections: bool = True,
) -> OnlineResult:
    """Steps 3-6: interpolation (eq. 1-2), joint limits, derivatives, torques, time scaling.

    ``max_duration (C,)`` [s]: the time allowed (None: `MAX_DURATION`); a motion that needs
    longer to stay within the velocity and torque limits of ``dyn.robot`` is returned at
    ``max_duration`` with ``ok`` False. ``final_shift (C, J)`` [rad]: a change of the final
    posture added to the interpolated path as a rest-to-rest minimum-jerk offset (a catch turns
    the palm toward the ball, `catching.catch_posture`); None: none. ``corrections`` False
    (static): neither correction (steps 4 and 6) is traced; where the result's ``corrected`` is
    True, its motion is then not the query's. Pure.
    """
    q = compile_interpolation(basis, boundary, grid, settings.n_components).q
    if final_shift is not None:
        q = q + minimum_jerk(grid, jnp.zeros_like(final_shift), final_shift)
        boundary = boundary._replace(qf=boundary.qf + final_shift)
    q, excess, fallback = enforce_limits(
        basis, boundary, grid, q, lower, upper, settings, corrections
    )
    asked = boundary.duration
    top = jnp.full_like(asked, MAX_DURATION) if max_duration is None else max_duration
    top = jnp.asarray(top, q.dtype)
    vel_lim, tau_lim, vel_use, tau_use = (
        jnp.asarray(a, q.dtype) for a in usable_limits(dyn.robot, settings)
    )
    if max_duration is not None:  # a deadline: joints too fast for it straighten (`fit_speed`)
        q = fit_speed(grid, q, boundary.q0, boundary.qf, jnp.maximum(top, asked), vel_use)[0]
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

    def keep(_):
        return asked, asked, qd, qdd, tau

    # Most motions are within their limits: skip the work (a branch: C is a batch axis here).
    needed, dur, qd, qdd, tau = (
        jax.lax.cond(jnp.any(over), stretch, keep, None) if corrections else keep(None)
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
        torque_margin=peak_margin(peak_tau, tau_lim),
        velocity_margin=peak_margin(peak_vel, vel_lim),
        joint_margin=jnp.min(room, axis=(1, 2)),
        worst_joint=j_idx.astype(jnp.int32),
        worst_kind=worst_kind,
        worst_value=worst_value,
        worst_time=jnp.asarray(grid.s, q.dtype)[t_idx] * dur,
        reachable=reach.reachable,
        ok=reach.reachable & finite & inside & within & within_time & jnp.isfinite(hand_error),
        corrected=(excess > 0) | over,
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
    corrections: bool = True,
) -> OnlineResult:
    """The whole online query (steps 1-6) for ``targets (C, 3)``; pure (jit it at the top).

    ``duration (C,)`` [s] (NaN: the neighbours' mean), ``q_start (C, J)`` inside the limits.
    ``corrections``: as `finish_motion`'s (static).
    """
    lower = jnp.asarray(lower, jnp.asarray(db.q).dtype)
    upper = jnp.asarray(upper, lower.dtype)
    basis, boundary, reach = build_problem(
        dyn, db, targets, duration, q_start, lower, upper, basis_settings, settings
    )
    return finish_motion(
        dyn, grid, lower, upper, settings, basis, boundary, reach, targets,
        corrections=corrections,
    )  # fmt: skip


def make_online_generator(
    robot: Robot,
    dyn: Dynamics,
    grid: TimeGrid,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
    fast_path: bool = True,
    one_shot: bool = False,
    cache_parts: Any = None,
) -> Callable:
    """The jitted query ``generate(db, targets (C, 3), duration (C,), q_start (C, J))``.

    Returns `OnlineResult` (device arrays). ``db`` is an argument (not a constant) so one compiled
    function serves the learned and the human-only database alike; it recompiles only for a new
    C or database shape. ``fast_path``: compile through `model.dynamics.unfused_cpu_program` (faster
    on CPU; False: ``dyn`` as given, XLA's default options). ``one_shot``: for a query or two
    (the command line), where compiling takes longer than running: compiled faster, run slower
    (`compile_options.ONE_SHOT`; on accelerators the vector RNEA layout,
    `model.dynamics.one_shot_layout`), and first without the two corrections (the joint-limit
    projection, the time scaling; `finish_motion`), which most motions do not need; only where
    a target needs one (``corrected``) is the whole query compiled and run (2 CPU cores, a cold
    `generate`: 3.9-4.5 s -> 2.9-3.3 s; CHANGELOG.md). ``cache_parts``: what the program
    depends on besides its arguments (JSON-able: the robot model's digest, the settings), to
    keep its trace across processes (`run.cache.traced_program`); None: traced in this process.
    """
    basis_settings, settings = resolve_settings(basis_settings, settings)
    lower, upper = joint_limits_f32(robot)
    dyn, options = program_dynamics(dyn, one_shot, fast_path)
    fixed = (dyn, grid, lower, upper, basis_settings, settings)
    fn = functools.partial(online_query, *fixed)
    whole = kept_trace(fn, "online.generate", cache_parts, options)
    if not one_shot:
        return whole
    fn = functools.partial(online_query, *fixed, corrections=False)
    uncorrected = kept_trace(fn, "online.generate.uncorrected", cache_parts, options)

    def generate(db, targets, duration, q_start) -> OnlineResult:
        result = uncorrected(db, targets, duration, q_start)
        return whole(db, targets, duration, q_start) if bool(result.corrected.any()) else result

    return generate


def program_dynamics(
    dyn: Dynamics, one_shot: bool, fast_path: bool = True
) -> tuple[Dynamics, dict | None]:
    """``(dynamics, jit compiler_options)`` of an online program (`make_online_generator`,
    `catching.make_catcher`): ``fast_path``, `model.dynamics.unfused_cpu_program`; ``one_shot``,
    `compile_options.ONE_SHOT` and `model.dynamics.one_shot_layout`."""
    dyn, options = unfused_cpu_program(dyn) if fast_path else (dyn, None)
    if not one_shot:
        return dyn, options
    return one_shot_layout(dyn), one_shot_options(options)


def kept_trace(fn: Callable, name: str, cache_parts: Any, options: dict | None) -> Callable:
    """The pure query ``fn`` jitted with ``options`` and exact float32 matrix products, or,
    where ``cache_parts`` is given, that program's `run.cache.traced_program` under ``name`` and
    those parts."""
    jitted = jax.jit(exact_matmuls(fn), compiler_options=options)
    if cache_parts is None:
        return jitted
    from evojax_motion.run.cache import traced_program

    return traced_program(jitted, {"program": name, **cache_parts}, options)


def program_parts(model: OnlineModel) -> dict:
    """What an online program of ``model`` depends on besides its arguments, for
    `kept_trace`: the robot (model digest, joints, site), the time grid's samples, the dynamics
    backend and the settings."""
    from evojax_motion.run.cache import model_digest

    robot = model.robot
    return {
        "model": model_digest(robot.mj_model),
        "joints": list(robot.joint_names),
        "site": robot.site_name,
        "samples": int(np.shape(model.grid.s)[0]),
        "dynamics": model.dyn.backend,
        "settings": repr((model.basis_settings, model.settings)),
    }


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
