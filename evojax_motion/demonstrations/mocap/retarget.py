"""Retargeting human key points to a robot by batched multi-target inverse kinematics.

Park et al. (2008, sec. 2, after Lim et al. 2005) obtain movement primitives by an
optimisation-based IK from motion-capture markers. Here, for a robot with key points (bodies or
its end-effector site, `RobotKeyPoints`) matched to human key points (shoulder, elbow, wrist,
hand):

0. Key points and weights (`robot_keypoints`) come from the robot's kinematic chain when not
   given (`guess_keypoints`): below the last body that carries another limb (a humanoid's
   chest), the shoulder is the first joint after a vertical base yaw, the wrist the last bending
   joint, the elbow the bending joint between them farthest from both, the hand the end
   effector.
   `default_weights`: every key point when the robot's upper arm can hang below its shoulder as
   a person's does (an anthropomorphic arm), else the hand only (the others still set the scale).
1. Scaling (`scale_to_robot`): the human key points, relative to the person's shoulder in a frame
   that moves with the person (`frames.body_frames`), are rebuilt with the robot's segment
   lengths keeping every segment's direction, ``x_k = x_(k-1) + L_robot,k * unit(h_k - h_(k-1))``,
   from the robot's shoulder; so the human arm's reach becomes the robot's. With another reference
   point, the shoulder moves by the human's displacement times the ratio of arm lengths. Human
   segment lengths are medians over the trial's frames. `lift_above_base`: when the shoulder is a
   reference only (weight 0), the targets are raised until the hand stays above the robot's base.
2. IK (`solve_keypoint_ik`): every frame minimises

       sum_k w_k^2 |p_k(q) - x_k|^2 + s |q - q_prev|^2 + r |q - q_rest|^2,  lower <= q <= upper

   by projected Levenberg-Marquardt (joints at a limit whose gradient points outward leave the
   step, the rest re-solve; the iterate is clipped into the box), warm-started from the previous
   frame's solution (a `lax.scan` over frames, `vmap` over trials, one jit for all of them). The
   first frame is solved from the rest posture, repeated a few times before the trial starts.
3. `segment_movement`: onset and offset where the hand speed crosses a fraction of its peak;
   `resample`: the segment to ``T`` samples by monotone cubic (PCHIP) interpolation, which never
   overshoots the data and so keeps the joint limits.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.demonstrations.mocap.markers import KEYPOINT_CHAIN, TrialError
from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.motion.objective import torque_cost
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.demonstrations import IKSettings

LIMIT_EPS = 1e-6  # [rad] a joint this close to a limit counts as at the limit
MU_INIT, MU_DOWN, MU_UP, MU_MIN = 1e-3, 0.3, 10.0, 1e-9  # Levenberg-Marquardt damping schedule

# guess_keypoints: a joint axis within this angle of the vertical is a base yaw; one within
# ROLL_DEG of its link a roll (not a bend); anchors closer than SAME_POINT_M are one point
VERTICAL_DEG, ROLL_DEG, SAME_POINT_M = 30.0, 60.0, 1e-3
# default_weights: the upper arm "can hang" when some posture points it within HANG_DEG of
# straight down; HANG_SAMPLES postures are tried (and the rest posture)
HANG_DEG, HANG_SAMPLES = 30.0, 4096
BASE_CLEARANCE = 0.05  # [m] lift_above_base keeps the hand targets this far above the base


class RobotKeyPoints(NamedTuple):
    """Robot points matched to human key points, proximal to distal.

    human: (K,) human key point names (a sub-sequence of `KEYPOINT_CHAIN`).
    robot: (K,) ``body:NAME`` or ``site:NAME``. body_ids: (K,) MuJoCo body id, or -1 for the site.
    weights: (K,) IK weight of each key point (0: used for scaling only, not matched).
    """

    human: tuple[str, ...]
    robot: tuple[str, ...]
    body_ids: tuple[int, ...]
    weights: tuple[float, ...]


def robot_keypoints(
    robot, mapping: Mapping[str, str] | None = None, weights: Mapping[str, float] | None = None
) -> RobotKeyPoints:
    """Resolve a key-point map (robot point -> human key point) and weights for ``robot``.

    mapping None: `guess_keypoints` (from the kinematic chain). Robot points: ``site:NAME`` (only
    the robot's end-effector site), ``body:NAME``, or a bare name (the site if it is the
    end-effector site, else a body). weights: human key point -> IK weight, over
    `default_weights` of the map.
    """
    m = robot.mj_model
    if mapping is None:
        mapping = guess_keypoints(robot)
    by_human = {}
    for ref, human in mapping.items():
        if human not in KEYPOINT_CHAIN:
            raise UserError(f"--keypoints {ref}={human}: expected a key point in {KEYPOINT_CHAIN}")
        if human in by_human:
            raise UserError(f"--keypoints: human key point {human!r} is mapped twice")
        by_human[human] = ref
    if "hand" not in by_human or len(by_human) < 2:
        raise UserError(
            f"robot {robot.name!r}: key points: need the hand and at least one more of "
            f"{KEYPOINT_CHAIN} (give --keypoints BODY=shoulder,...), got {dict(mapping)}"
        )
    humans, refs, ids = [], [], []
    for human in KEYPOINT_CHAIN:
        if human not in by_human:
            continue
        ref = by_human[human]
        kind, _, name = ref.partition(":") if ":" in ref else ("", "", ref)
        if kind == "site" or (not kind and name == robot.site_name):
            if name != robot.site_name:
                raise UserError(
                    f"--keypoints {ref}: only the end-effector site {robot.site_name!r} can be a "
                    "key point (use a body otherwise)"
                )
            humans.append(human)
            refs.append(f"site:{name}")
            ids.append(-1)
            continue
        if kind not in ("", "body"):
            raise UserError(f"--keypoints {ref}: expected body:NAME or site:NAME")
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if b < 0:
            bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(m.nbody)]
            raise UserError(
                f"--keypoints {ref}: robot {robot.name!r} has no body {name!r}; bodies: {bodies}"
            )
        humans.append(human)
        refs.append(f"body:{name}")
        ids.append(int(b))
    w = default_weights(robot, tuple(humans), tuple(ids))
    for key, value in (weights or {}).items():
        if key not in KEYPOINT_CHAIN or not (value >= 0 and np.isfinite(value)):
            raise UserError(
                f"--weights {key}={value}: expected a key point of {KEYPOINT_CHAIN} "
                "and a weight >= 0"
            )
        w[key] = float(value)
    kw = tuple(float(w.get(h, 1.0)) for h in humans)
    if sum(kw) <= 0:
        raise UserError("--weights: at least one key point needs a weight > 0")
    return RobotKeyPoints(tuple(humans), tuple(refs), tuple(ids), kw)


def _rest_kinematics(robot, q=None) -> mujoco.MjData:
    """C MuJoCo kinematics of ``robot`` at ``q`` (default: the rest posture)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[robot.qpos_adr] = robot.rest if q is None else q
    mujoco.mj_kinematics(m, d)
    return d


def guess_keypoints(robot) -> dict[str, str]:
    """Robot key points from the kinematic chain of the controlled hinges (at the rest posture).

    The arm starts below the deepest body of the chain that carries another limb (a joint in a
    branch off the chain: a humanoid's chest with the other arm, its pelvis with the legs), so a
    waist is not taken for the shoulder; where the hinges below it do not make an arm
    (`_arm_keypoints`), or nothing branches, the whole chain. Along it (`_arm_keypoints`): the
    shoulder is the body of the first hinge whose axis is more than `VERTICAL_DEG` from the
    vertical (a base yaw before it turns the whole arm), or of the first hinge; the wrist the
    body of the last *bending* hinge after it, whose axis is more than `ROLL_DEG` from the link
    that leads to it (rolls about a link move no point of the chain); the elbow the bending hinge
    between them farthest from both (the middle of the arm: not a second shoulder joint a few cm
    out, nor a first wrist joint); hinges at the same point as the previous one count as that
    point. hand: the end-effector site. Names do not matter: e.g. mahru_arm's upper_arm,
    forearm, hand and Kinova Gen3's joint_2, joint_4 and joint_6 bodies.
    """
    m = robot.mj_model
    d = _rest_kinematics(robot)
    hinges = [j for j in robot.joint_ids if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_HINGE)]
    out: dict[str, str] = {}
    for top in _branch_bodies(robot):
        below = [j for j in hinges if _is_below(m, int(m.jnt_bodyid[j]), top)]
        out = _arm_keypoints(m, d, below)
        if "wrist" in out.values():
            break
    else:
        out = _arm_keypoints(m, d, hinges)
    out[f"site:{robot.site_name}"] = "hand"
    return out


def _is_below(m: mujoco.MjModel, body: int, top: int) -> bool:
    """Whether ``body`` is a strict descendant of ``top``."""
    while body != 0:
        body = int(m.body_parentid[body])
        if body == top:
            return True
    return False


def _branch_bodies(robot) -> list[int]:
    """Bodies on the chain from the world to the end effector's body (that body excluded) with a
    child off the chain whose subtree holds a joint (another limb), deepest first."""
    m = robot.mj_model
    chain, b = [], int(m.body_parentid[int(m.site_bodyid[robot.site_id])])
    while b != 0:
        chain.append(b)
        b = int(m.body_parentid[b])
    on_chain = {*chain, int(m.site_bodyid[robot.site_id])}
    jointed = {int(m.jnt_bodyid[j]) for j in range(m.njnt)}
    limbs = {
        int(m.body_parentid[c])
        for c in range(1, m.nbody)
        if c not in on_chain and any(c == j or _is_below(m, j, c) for j in jointed)
    }
    return [b for b in chain if b in limbs]


def _arm_keypoints(m: mujoco.MjModel, d: mujoco.MjData, hinges: list[int]) -> dict[str, str]:
    """Shoulder, elbow and wrist bodies (``body:NAME`` -> key point) of the chain of ``hinges``
    (joint ids, root first) by the rule of `guess_keypoints`; fewer where it has fewer bends."""
    out: dict[str, str] = {}
    if not hinges:
        return out

    def body(j: int) -> str:
        return f"body:{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.jnt_bodyid[j]))}"

    vertical = np.cos(np.deg2rad(VERTICAL_DEG))
    first = next((k for k, j in enumerate(hinges) if abs(d.xaxis[j][2]) < vertical), 0)
    out[body(hinges[first])] = "shoulder"
    prev, link = d.xanchor[hinges[first]].copy(), None
    bends: list[int] = []
    for j in hinges[first + 1 :]:
        v = d.xanchor[j] - prev
        if np.linalg.norm(v) > SAME_POINT_M:
            link, prev = v / np.linalg.norm(v), d.xanchor[j].copy()
        elif link is None:
            continue  # at the shoulder: one of its axes
        elif bends and np.linalg.norm(d.xanchor[j] - d.xanchor[bends[-1]]) <= SAME_POINT_M:
            continue  # at the last bend's point
        if abs(d.xaxis[j] @ link) < np.cos(np.deg2rad(ROLL_DEG)):
            bends.append(j)
    bends = [j for j in bends if body(j) not in out]
    if not bends:
        return out
    wrist = bends[-1]
    between = bends[:-1]
    if not between:  # one bend: the elbow, no wrist
        out[body(wrist)] = "elbow"
        return out
    shoulder, end = d.xanchor[hinges[first]], d.xanchor[wrist]
    middle = [min(np.linalg.norm(d.xanchor[j] - shoulder), np.linalg.norm(d.xanchor[j] - end))
              for j in between]  # fmt: skip
    elbow = between[int(np.argmax(middle))]
    out[body(elbow)] = "elbow"
    if body(wrist) != body(elbow):
        out[body(wrist)] = "wrist"
    return out


def upper_arm_can_hang(robot, shoulder_body: int, elbow_body: int) -> bool:
    """Whether some posture inside the limits points the robot's shoulder -> elbow key points
    within `HANG_DEG` of straight down, as a person's relaxed arm (the rest posture and
    `HANG_SAMPLES` postures drawn from `Robot.sample_postures`, fixed seed)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    postures = np.concatenate([robot.rest[None], robot.sample_postures(rng, HANG_SAMPLES)])
    cos_hang = np.cos(np.deg2rad(HANG_DEG))
    for q in postures:
        d.qpos[robot.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        arm = d.xpos[elbow_body] - d.xpos[shoulder_body]
        norm = np.linalg.norm(arm)
        if norm > SAME_POINT_M and -arm[2] / norm >= cos_hang:
            return True
    return False


def default_weights(robot, humans: Sequence[str], body_ids: Sequence[int]) -> dict[str, float]:
    """IK weight per human key point when ``--weights`` does not say: 1 for every key point of an
    arm whose upper arm can hang (`upper_arm_can_hang`: shoulder, elbow and the rest can take a
    person's postures), else 1 for the hand and 0 for the others (a table-top arm's shoulder
    cannot follow a person's: its elbow stays up; those points still set the scale).

    humans: (K,) human key points; body_ids: (K,) their robot bodies (-1: the site).
    """
    ids = dict(zip(humans, body_ids))
    shoulder, elbow = ids.get("shoulder", -1), ids.get("elbow", -1)
    if shoulder >= 0 and elbow >= 0 and upper_arm_can_hang(robot, shoulder, elbow):
        return {h: 1.0 for h in humans}
    return {h: (1.0 if h == "hand" else 0.0) for h in humans}


def base_height(robot) -> float:
    """[m] world height of the robot's base: the origin of the outermost body of its chain (the
    body attached to the world that carries the first controlled joint)."""
    m = robot.mj_model
    root = int(m.body_rootid[int(m.jnt_bodyid[robot.joint_ids[0]])])
    return float(_rest_kinematics(robot).xpos[root][2])


def parse_pairs(text: str, flag: str) -> dict[str, str]:
    """``"a=b,c=d"`` -> ``{"a": "b", "c": "d"}`` (``--keypoints``, ``--weights``)."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise UserError(f"{flag} {item!r}: expected NAME=VALUE")
        out[key.strip()] = value.strip()
    return out


def parse_weights(text: str) -> dict[str, float]:
    """``"shoulder=0,elbow=0.5"`` -> ``{"shoulder": 0.0, "elbow": 0.5}``."""
    out = {}
    for key, value in parse_pairs(text, "--weights").items():
        try:
            out[key] = float(value)
        except ValueError:
            raise UserError(f"--weights {key}={value}: expected a number") from None
    return out


def keypoint_positions(dyn: Dynamics, kp: RobotKeyPoints):
    """``q (J,) -> (K, 3)`` world positions of the robot key points (pure, un-jitted)."""
    body_ids = jnp.asarray([max(b, 0) for b in kp.body_ids])
    is_site = jnp.asarray([b < 0 for b in kp.body_ids])[:, None]

    def fn(q):
        bodies = dyn.body_positions(q)[body_ids]
        site = dyn.site_pose(q)[0]
        return jnp.where(is_site, site[None, :], bodies)

    return fn


# ------------------------------------------------------------------------------------- scaling


class Scaled(NamedTuple):
    targets: np.ndarray  # (F, K, 3) robot-frame targets [m]
    human_lengths: np.ndarray  # (K-1,) median human segment lengths [m]
    robot_lengths: np.ndarray  # (K-1,) robot segment lengths [m]


def robot_segment_lengths(rest_points: np.ndarray) -> np.ndarray:
    """(K-1,) distances between consecutive robot key points at the rest posture."""
    return np.linalg.norm(np.diff(rest_points, axis=0), axis=-1)


def scale_to_robot(human: np.ndarray, rest_points: np.ndarray) -> Scaled:
    """Human key points ``(F, K, 3)`` in a body frame (x forward, y left, z up; origin at the
    reference point, the shoulder by default) -> robot targets ``(F, K, 3)`` in the robot's world
    frame.

    rest_points: ``(K, 3)`` robot key points at its rest posture (its root anchors the chain: the
    human's root key point in frame 0 goes there and moves by its displacement times the ratio
    of arm lengths, not at all when it is the frame's origin).
    """
    seg = np.diff(human, axis=1)  # (F, K-1, 3)
    length = np.linalg.norm(seg, axis=-1)
    if not (length > 1e-6).all():
        f, k = np.argwhere(~(length > 1e-6))[0]
        raise TrialError(
            f"key points {k} and {k + 1} of the chain coincide at frame {f} "
            f"({1e3 * length[f, k]:.2f} mm apart): cannot tell the segment's direction"
        )
    h_len = np.median(length, axis=0)
    r_len = robot_segment_lengths(rest_points)
    ratio = r_len.sum() / h_len.sum()
    root = rest_points[0] + ratio * (human[:, 0] - human[0, 0])
    steps = r_len[None, :, None] * seg / length[..., None]
    targets = np.concatenate([root[:, None], root[:, None] + np.cumsum(steps, axis=1)], axis=1)
    return Scaled(targets, h_len, r_len)


def lift_above_base(
    targets: np.ndarray, base_z: float, clearance: float = BASE_CLEARANCE
) -> tuple[np.ndarray, float]:
    """``(targets + lift z, lift)``: targets ``(F, K, 3)`` raised by the least ``lift >= 0`` [m]
    that puts the hand (the last key point) at least ``clearance`` above ``base_z`` in every
    frame. A person's hand works below the shoulder; a table-top arm's works above its base."""
    lift = max(0.0, float(base_z + clearance - targets[:, -1, 2].min()))
    return targets + np.array([0.0, 0.0, lift]), lift


# ------------------------------------------------------------------------------------------ IK


def _lm(residual, q0, lower, upper, iters):
    """Projected Levenberg-Marquardt on ``0.5 |r(q)|^2`` in the box ``[lower, upper]``.

    residual: ``q -> (r (R,), aux)``. Each of the ``iters + 1`` rounds evaluates ``r``, its
    Jacobian and ``aux`` once, at the candidate: kept if it lowers the cost (the damping falls),
    else refused (the damping rises); then the next candidate is stepped from the kept point. One
    evaluation site keeps the compiled graph small. Returns ``(q, cost, aux)`` of the kept point.
    """

    def evaluate(q):
        r, aux = residual(q)
        return r, (r, aux)

    res_jac = jax.jacfwd(evaluate, has_aux=True)  # q -> (jac (R, J), (r, aux))

    def body(_, carry):
        q, r, jac, c, aux, q_cand, mu = carry
        jac_n, (r_n, aux_n) = res_jac(q_cand)
        c_n = 0.5 * r_n @ r_n
        better = c_n < c
        q, r, jac, c = (
            jnp.where(better, new, old)
            for new, old in ((q_cand, q), (r_n, r), (jac_n, jac), (c_n, c))
        )
        aux = jax.tree.map(lambda new, old: jnp.where(better, new, old), aux_n, aux)
        mu = jnp.where(better, jnp.maximum(mu * MU_DOWN, MU_MIN), mu * MU_UP)
        g = jac.T @ r
        a = jac.T @ jac
        # joints pinned at a limit with the gradient pushing out of the box leave the step
        free = ~(((q <= lower + LIMIT_EPS) & (g > 0)) | ((q >= upper - LIMIT_EPS) & (g < 0)))
        f = free.astype(q.dtype)
        a_f = a * f[:, None] * f[None, :] + jnp.diag(1.0 - f)
        step = -jnp.linalg.solve(a_f + jnp.diag(mu * (jnp.diagonal(a) + 1e-6)), f * g)
        return q, r, jac, c, aux, jnp.clip(q + step, lower, upper), mu

    q0 = jnp.clip(q0, lower, upper)
    r_shape, aux_shape = jax.eval_shape(residual, q0)
    zeros = functools.partial(jnp.zeros, dtype=q0.dtype)
    init = (
        q0,
        zeros(r_shape.shape),
        zeros((*r_shape.shape, q0.shape[0])),
        jnp.asarray(jnp.inf, q0.dtype),  # the first candidate (q0 itself) is always kept
        jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), aux_shape),
        q0,
        jnp.asarray(MU_INIT / MU_DOWN, q0.dtype),
    )
    q, _, _, c, aux, _, _ = jax.lax.fori_loop(0, iters + 1, body, init)
    return q, c, aux


class IKOutput(NamedTuple):
    q: jnp.ndarray  # (B, F, J) [rad]
    error: jnp.ndarray  # (B, F, K) distance of each robot key point to its target [m]


@functools.partial(jax.jit, static_argnames=("dyn", "kp", "settings"))
def solve_keypoint_ik(
    dyn: Dynamics, kp: RobotKeyPoints, settings: IKSettings, targets, q_start, lower, upper, rest
) -> IKOutput:
    """Joint trajectories whose key points follow ``targets (B, F, K, 3)`` [m].

    q_start: ``(J,)`` posture the first frame's solve starts from (the rest posture: recordings
    start at rest). lower, upper: ``(J,)`` box; rest: ``(J,)`` posture of the ``posture`` term.
    One scan step per frame, warm-started from the previous one; the first frame is repeated
    ``settings.warmup`` times before the trial (same code path: one compiled LM loop).
    Returns `IKOutput` with ``q (B, F, J)``, ``error (B, F, K)``.
    """
    dtype = dyn.dtype
    targets = jnp.asarray(targets, dtype)
    q_start, lower, upper, rest = (jnp.asarray(x, dtype) for x in (q_start, lower, upper, rest))
    fk = keypoint_positions(dyn, kp)
    w = jnp.asarray(kp.weights, dtype)
    s_smooth = jnp.sqrt(jnp.asarray(settings.smooth, dtype))
    s_rest = jnp.sqrt(jnp.asarray(settings.posture, dtype))

    def step(q_prev, target):
        def residual(q):
            p = fk(q)
            r_kp = (w[:, None] * (p - target)).ravel()
            return jnp.concatenate([r_kp, s_smooth * (q - q_prev), s_rest * (q - rest)]), p

        q, _, p = _lm(residual, q_prev, lower, upper, settings.iters)
        return q, (q, jnp.linalg.norm(p - target, axis=-1))

    def one_trial(path):
        warm = jnp.broadcast_to(path[0], (settings.warmup, *path.shape[1:]))
        _, (q, err) = jax.lax.scan(step, q_start, jnp.concatenate([warm, path]))
        return q[settings.warmup :], err[settings.warmup :]

    q, err = jax.vmap(one_trial)(targets)
    return IKOutput(q, err)


# ------------------------------------------------------------------------- segmentation, resampling


class Segment(NamedTuple):
    onset: int  # first frame of the movement
    offset: int  # last frame of the movement
    peak_speed: float  # [m/s] of the hand
    rest_start: bool  # the speed was below threshold before the onset (else the file starts moving)
    rest_end: bool


def segment_movement(
    hand: np.ndarray, rate: float, threshold: float = 0.05, min_peak_speed: float = 0.05
) -> Segment:
    """Onset/offset of the main movement of ``hand (F, 3)`` [m] sampled at ``rate`` [Hz].

    The speed peak is found; the onset is the last frame before it, the offset the first after it,
    where the speed is at most ``threshold`` times the peak. Raises `TrialError` when the hand
    never moves faster than ``min_peak_speed`` [m/s].
    """
    speed = np.linalg.norm(np.gradient(hand, axis=0), axis=-1) * rate
    peak = int(np.argmax(speed))
    if speed[peak] < min_peak_speed:
        raise TrialError(
            f"no movement: hand speed peaks at {speed[peak]:.3f} m/s < {min_peak_speed} m/s"
        )
    below = speed <= threshold * speed[peak]
    before = np.flatnonzero(below[:peak])
    after = np.flatnonzero(below[peak:])
    onset = int(before[-1]) if before.size else 0
    offset = int(peak + after[0]) if after.size else len(speed) - 1
    return Segment(onset, offset, float(speed[peak]), bool(before.size), bool(after.size))


def resample(q: np.ndarray, samples: int) -> np.ndarray:
    """``q (F, J)`` -> ``(samples, J)`` at evenly spaced normalised times, PCHIP (no overshoot)."""
    from scipy.interpolate import PchipInterpolator

    f = q.shape[0]
    s_in = np.linspace(0.0, 1.0, f)
    s_out = np.linspace(0.0, 1.0, samples)
    if f == 1:
        return np.repeat(q, samples, axis=0)
    return PchipInterpolator(s_in, q, axis=0)(s_out)


def at_limit(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, tol: float = 1e-4) -> np.ndarray:
    """``(F, J)`` bool: joint at (within ``tol`` rad of) a limit, i.e. clipped by the IK."""
    return (q <= lower + tol) | (q >= upper - tol)


def conditions_and_costs(dyn: Dynamics, q, duration) -> tuple[np.ndarray, np.ndarray]:
    """Database fields of primitives ``q (N, T, J)``, ``duration (N,)`` [s]: the condition (site
    position at the last sample, ``(N, 3)`` [m]) and the torque cost of eq. 5 ``(N,)``."""
    q, duration = np.asarray(q), np.asarray(duration)
    n = q.shape[0]
    pad = max(8, 1 << (n - 1).bit_length()) - n  # few distinct batch sizes: few compilations
    q = np.concatenate([q, np.repeat(q[-1:], pad, axis=0)])
    duration = np.concatenate([duration, np.repeat(duration[-1:], pad)])
    grid = make_time_grid(q.shape[1], dtype=np.dtype(dyn.dtype))
    cond, cost = _conditions_and_costs(
        dyn, grid, jnp.asarray(q, dyn.dtype), jnp.asarray(duration, dyn.dtype)
    )
    return np.asarray(cond, np.float64)[:n], np.asarray(cost, np.float64)[:n]


@functools.partial(jax.jit, static_argnames=("dyn",))
def _conditions_and_costs(dyn, grid, q, duration):
    cond = jax.vmap(lambda x: dyn.site_pose(x)[0])(q[:, -1])
    cost = jax.vmap(functools.partial(torque_cost, dyn, grid))(q, duration)
    return cond, cost


@functools.partial(jax.jit, static_argnames=("dyn",))
def _site_paths(dyn, q):
    return jax.vmap(lambda x: dyn.site_pose(x)[0])(q)


def site_path(dyn: Dynamics, q: np.ndarray) -> np.ndarray:
    """``q (F, J)`` -> ``(F, 3)`` end-effector site positions [m]."""
    return np.asarray(_site_paths(dyn, jnp.asarray(q, dyn.dtype)), np.float64)


@functools.partial(jax.jit, static_argnames=("dyn", "kp"))
def _rest_keypoints(dyn, kp, q):
    return keypoint_positions(dyn, kp)(q)


def rest_keypoints(dyn: Dynamics, kp: RobotKeyPoints, q_rest: Sequence[float]) -> np.ndarray:
    """(K, 3) robot key points at the posture ``q_rest``."""
    return np.asarray(_rest_keypoints(dyn, kp, jnp.asarray(q_rest, dyn.dtype)), np.float64)
