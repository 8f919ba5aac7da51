"""Physics rollout of a planned motion in MuJoCo: can the robot execute it? (docs/simulation.md)

The online process (paper sec. 3.2) plans joint trajectories; the paper shows them as pictures
(sec. 4). Here a plan is executed in C MuJoCo (``mujoco.mj_step`` at the model's timestep and
integrator) by a tracking controller, optionally with the thrown ball of sec. 4 flying into the
robot, and the outcome is measured.

Controller (computed torque, at every step)::

    tau = clip(tau_ff + M(q) (kp e + kd de), -tau_max, tau_max),
    e = q_ref - q, de = qd_ref - qd, kp = (2 pi f)^2, kd = 2 zeta (2 pi f)

``tau_ff``: feed-forward, C MuJoCo's ``mj_inverse`` of the reference
(`model.robot.mj_inverse_torques`); ``M(q)``: the joint-space inertia matrix of the robot's joints
(``mj_fullM``) at the current state (``mj_step1``, control, ``mj_step2``), so that while no
torque is clipped every joint's error obeys ``e'' + kd e' + kp e = 0``, decoupled, with
natural frequency f and damping ratio zeta (`SimSettings`). Only the diagonal of M would not
do: on mahru_arm, whose elbow and wrist axes are parallel at rest, that feedback chattered from
step to step and saturated the shoulder within 50 ms (the coupled inertia makes the effective
gain several times the diagonal's). The torque goes in as ``qfrc_applied``; the model's own
actuators are switched off (``mjDSBL_ACTUATION``), and the clip is the robot's torque limit
(``Robot.torque_limit``: inf where none). Joints of the model that are not controlled are held
at ``qpos0`` by the same feedback without feed-forward or clip.

Reference: the plan's samples ``(t_i, q_i, qd_i, qdd_i)`` joined by quintic Hermite pieces
(``scipy.interpolate.BPoly.from_derivatives``: q, qd and qdd match at every sample), held at the
first posture before the motion and at the last after it.

Model: the robot's MJCF (`Robot.mjcf`) with constraints and contacts switched on (joint ranges
are hard stops, the ball bounces off the robot), and for a catch a free sphere (`SimSettings`
radius and mass; solid-sphere inertia) attached to the world by ``mujoco.MjSpec``, released with
the given position and velocity at t = 0. Every robot geom collides with the ball and with
nothing else (contype 0 / conaffinity 2 for the robot, 2 / 0 for the ball): the planner ignores
self-collisions, and this rollout measures tracking and catching, not those.

Catch criterion (one, physical; docs/simulation.md says why): the ball is caught when, at some
step, its centre lies within ``capture_radius`` of the end-effector site (the catching point)
while its speed relative to that point is at most ``2 capture_radius / grip_time``: a grip that
needs ``grip_time`` to close must close while the ball is within reach, and a ball crossing the
capture sphere faster leaves it before.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.model.robot import Robot, mj_inverse_torques
from evojax_motion.settings.online import SimSettings

BALL_BODY = "evojax_ball"
_ROBOT_AFFINITY, _BALL_TYPE = 0, 2  # contype / conaffinity bits: see the module docstring
_FREE_OR_BALL = (int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL))


class Plan(NamedTuple):
    """A planned motion: ``t (T,)`` increasing [s of simulated time], ``q, qd, qdd (T, J)``."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


class Ball(NamedTuple):
    """A ball released at t = 0 from ``p0 (3,)`` [m] with velocity ``v0 (3,)`` [m/s]."""

    p0: np.ndarray
    v0: np.ndarray


class Rollout(NamedTuple):
    """What the simulation recorded, one row per step (N steps of the model's timestep).

    time (N,) [s]; q, q_ref (N, J) [rad]; tau (N, J) applied [N m]; clipped (N, J): the command
    was at a torque limit; hand, hand_ref (N, 3) [m]: the catching point (end-effector site),
    simulated and of the reference; ball (N, 3) [m] (NaN without a ball); distance (N,) ball
    centre to the catching point [m]; relative_speed (N,) [m/s]; captured (N,): the catch
    criterion holds at that step.
    """

    time: np.ndarray
    q: np.ndarray
    q_ref: np.ndarray
    tau: np.ndarray
    clipped: np.ndarray
    hand: np.ndarray
    hand_ref: np.ndarray
    ball: np.ndarray
    distance: np.ndarray
    relative_speed: np.ndarray
    captured: np.ndarray


def reference(plan: Plan, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference ``q, qd, qdd (N, J)`` at ``times (N,)`` [s]: quintic Hermite pieces through
    the plan's samples, held at rest before and after it (module docstring)."""
    from scipy.interpolate import BPoly

    t = np.asarray(plan.t, np.float64)
    stack = np.stack([np.asarray(a, np.float64) for a in (plan.q, plan.qd, plan.qdd)], axis=1)
    poly = BPoly.from_derivatives(t, stack)  # stack: (T, 3, J), values and 2 derivatives
    times = np.asarray(times, np.float64)
    inside = (times >= t[0]) & (times <= t[-1])
    clamped = np.clip(times, t[0], t[-1])
    q = poly(clamped)
    qd = np.where(inside[:, None], poly.derivative(1)(clamped), 0.0)
    qdd = np.where(inside[:, None], poly.derivative(2)(clamped), 0.0)
    return q, qd, qdd


def simulation_model(robot: Robot, settings: SimSettings, ball: Ball | None) -> mujoco.MjModel:
    """The robot's model for the rollout: constraints and contacts on, actuators off, and the
    ball (a free sphere attached to the world) when given (module docstring)."""
    m0 = robot.mj_model
    controlled = set(int(j) for j in robot.joint_ids)
    for j in range(m0.njnt):
        if j not in controlled and int(m0.jnt_type[j]) in _FREE_OR_BALL:
            name = mujoco.mj_id2name(m0, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
            raise UserError(
                f"{robot.source or robot.name}: joint {name!r} is a free or ball joint; a "
                "simulation needs a fixed-base robot (every free or ball joint removed)"
            )
    spec = mujoco.MjSpec.from_string(robot.mjcf)
    for geom in spec.geoms:
        geom.contype, geom.conaffinity = _ROBOT_AFFINITY, _BALL_TYPE
    if ball is not None:
        r, mass = settings.ball_radius, settings.ball_mass
        body = spec.worldbody.add_body(
            name=BALL_BODY,
            pos=np.asarray(ball.p0, np.float64),
            mass=mass,
            inertia=[0.4 * mass * r * r] * 3,  # solid sphere
            explicitinertial=True,
        )
        body.add_freejoint()
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[r, 0.0, 0.0],
            contype=_BALL_TYPE,
            conaffinity=_ROBOT_AFFINITY,
            rgba=[1.0, 0.55, 0.0, 1.0],
        )
    try:
        m = spec.compile()
    except Exception as err:  # mujoco raises ValueError; its first line says what is wrong
        lines = str(err).strip().splitlines()
        raise UserError(
            f"{robot.source or robot.name}: the simulation model does not compile: "
            f"{lines[0] if lines else type(err).__name__}"
        ) from None
    off = mujoco.mjtDisableBit
    m.opt.disableflags &= ~(int(off.mjDSBL_CONSTRAINT) | int(off.mjDSBL_CONTACT))
    m.opt.disableflags |= int(off.mjDSBL_ACTUATION)
    return m


def simulate(
    robot: Robot,
    plan: Plan,
    settings: SimSettings | None = None,
    ball: Ball | None = None,
    t_end: float | None = None,
) -> Rollout:
    """Execute ``plan`` from rest at its first posture, t = 0 to ``t_end`` [s] (default: the
    plan's end plus ``settings.hold``), with ``ball`` released at t = 0 if given."""
    settings = settings or SimSettings()
    m = simulation_model(robot, settings, ball)
    d = mujoco.MjData(m)
    dt = float(m.opt.timestep)
    t_end = float(plan.t[-1]) + settings.hold if t_end is None else float(t_end)
    steps = max(1, math.ceil(t_end / dt - 1e-9))
    time = np.arange(steps) * dt
    q_ref, qd_ref, qdd_ref = reference(plan, time)
    tau_ff = mj_inverse_torques(robot, q_ref, qd_ref, qdd_ref)

    # Addresses in the simulation model (the ball's free joint may come after the robot's).
    name = robot.joint_names
    jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in name]
    qadr, vadr = m.jnt_qposadr[jid], m.jnt_dofadr[jid]
    others = [
        j for j in range(m.njnt) if j not in set(jid) and int(m.jnt_type[j]) not in _FREE_OR_BALL
    ]
    oq, ov = m.jnt_qposadr[others], m.jnt_dofadr[others]
    oq0 = m.qpos0[oq]
    dofs = np.concatenate([vadr, ov]).astype(int)  # the robot's dofs: controlled, then others
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, robot.site_name)
    limit = np.asarray(robot.torque_limit, np.float64)

    d.qpos[:] = m.qpos0
    d.qpos[qadr] = q_ref[0]
    if ball is not None:
        bj = m.body_jntadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, BALL_BODY)]
        ba, bv = int(m.jnt_qposadr[bj]), int(m.jnt_dofadr[bj])
        d.qpos[ba : ba + 3] = ball.p0
        d.qpos[ba + 3 : ba + 7] = (1.0, 0.0, 0.0, 0.0)
        d.qvel[bv : bv + 3] = ball.v0
    # mj_step1 / mj_step2: the control sees the kinematics and inertia of the current state
    # (MuJoCo does not split its RK4 integrator: there a forward pass, then the whole step).
    split = int(m.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_RK4)

    j = len(name)
    rec_q, rec_tau = np.zeros((steps, j)), np.zeros((steps, j))
    clipped = np.zeros((steps, j), bool)
    hand, ball_pos = np.zeros((steps, 3)), np.full((steps, 3), np.nan)
    rel = np.full(steps, np.nan)
    vel6, dense = np.zeros(6), np.zeros((m.nv, m.nv))
    for k in range(steps):
        (mujoco.mj_step1 if split else mujoco.mj_forward)(m, d)
        mujoco.mj_fullM(m, d, dense)
        e = np.concatenate([q_ref[k] - d.qpos[qadr], oq0 - d.qpos[oq]])
        de = np.concatenate([qd_ref[k] - d.qvel[vadr], -d.qvel[ov]])
        feedback = dense[np.ix_(dofs, dofs)] @ (settings.kp * e + settings.kd * de)
        command = tau_ff[k] + feedback[:j]
        tau = np.clip(command, -limit, limit)
        clipped[k] = np.abs(command) >= limit
        d.qfrc_applied[:] = 0.0
        d.qfrc_applied[vadr] = tau
        d.qfrc_applied[ov] = feedback[j:]
        rec_q[k], rec_tau[k], hand[k] = d.qpos[qadr], tau, d.site_xpos[site]
        if ball is not None:
            ball_pos[k] = d.qpos[ba : ba + 3]
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_SITE, site, vel6, 0)
            rel[k] = np.linalg.norm(d.qvel[bv : bv + 3] - vel6[3:])
        (mujoco.mj_step2 if split else mujoco.mj_step)(m, d)
    hand_ref = _site_positions(robot, q_ref)
    distance = np.linalg.norm(ball_pos - hand, axis=1)
    captured = (distance <= settings.capture_radius) & (rel <= settings.max_relative_speed)
    return Rollout(
        time=time,
        q=rec_q,
        q_ref=q_ref,
        tau=rec_tau,
        clipped=clipped,
        hand=hand,
        hand_ref=hand_ref,
        ball=ball_pos,
        distance=distance,
        relative_speed=rel,
        captured=captured,
    )


def _site_positions(robot: Robot, q) -> np.ndarray:
    from evojax_motion.report.kinematics import site_positions

    return site_positions(robot, q)


class Summary(NamedTuple):
    """The rollout in figures (`summarise`). Errors over every step of the rollout.

    tracking_rms, tracking_max [rad]: joint error ``q - q_ref`` over all joints and steps;
    hand_rms_mm, hand_max_mm [mm]: the catching point's distance to where the reference puts it;
    at_torque_limit: fraction of steps with some joint's command at its torque limit;
    caught (None without a ball); capture_time [s], capture_distance [m],
    capture_relative_speed [m/s]: the first step the criterion holds (NaN if never);
    closest_distance [m], closest_time [s], closest_relative_speed [m/s]: the ball's closest
    approach to the catching point (NaN without a ball).
    """

    tracking_rms: float
    tracking_max: float
    hand_rms_mm: float
    hand_max_mm: float
    at_torque_limit: float
    caught: bool | None
    capture_time: float
    capture_distance: float
    capture_relative_speed: float
    closest_distance: float
    closest_time: float
    closest_relative_speed: float


def summarise(rollout: Rollout, with_ball: bool) -> Summary:
    """`Summary` of a `Rollout`."""
    err = rollout.q - rollout.q_ref
    hand = np.linalg.norm(rollout.hand - rollout.hand_ref, axis=1) * 1e3
    nan = float("nan")
    caught: bool | None = None
    capture = capture_d = capture_v = closest = closest_t = closest_v = nan
    if with_ball:
        caught = bool(rollout.captured.any())
        if caught:
            c = int(np.argmax(rollout.captured))
            capture, capture_d = float(rollout.time[c]), float(rollout.distance[c])
            capture_v = float(rollout.relative_speed[c])
        k = int(np.nanargmin(rollout.distance))
        closest, closest_t = float(rollout.distance[k]), float(rollout.time[k])
        closest_v = float(rollout.relative_speed[k])
    return Summary(
        tracking_rms=float(np.sqrt(np.mean(err**2))),
        tracking_max=float(np.max(np.abs(err))),
        hand_rms_mm=float(np.sqrt(np.mean(hand**2))),
        hand_max_mm=float(np.max(hand)),
        at_torque_limit=float(np.mean(rollout.clipped.any(axis=1))),
        caught=caught,
        capture_time=capture,
        capture_distance=capture_d,
        capture_relative_speed=capture_v,
        closest_distance=closest,
        closest_time=closest_t,
        closest_relative_speed=closest_v,
    )


def frame_indices(rollout: Rollout, fps: float) -> np.ndarray:
    """Step indices of an animation at ``fps`` frames per second over the rollout: ``(F,)``."""
    times = np.arange(0.0, float(rollout.time[-1]) + 1e-9, 1.0 / fps)
    return np.minimum(np.searchsorted(rollout.time, times), rollout.time.shape[0] - 1)
