"""Retargeting human key points to a robot by batched multi-target inverse kinematics.

Park et al. (2008, sec. 2, after Lim et al. 2005) obtain movement primitives by an
optimisation-based IK from motion-capture markers. Here, for a robot with key points (bodies or
its end-effector site, `RobotKeyPoints`) matched to human key points (shoulder, elbow, wrist,
hand):

1. Scaling (`scale_to_robot`): the human chain is rebuilt with the robot's segment lengths,
   keeping every segment's direction, ``x_k = x_(k-1) + L_robot,k * unit(h_k - h_(k-1))``; the root
   key point (shoulder) starts at the robot's and moves by the human's displacement times the
   ratio of arm lengths. Human segment lengths are medians over the trial's frames.
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
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.dynamics import Dynamics
from evojax_motion.errors import UserError
from evojax_motion.mocap.markers import KEYPOINT_CHAIN, TrialError
from evojax_motion.objective import torque_cost
from evojax_motion.timegrid import make_time_grid

LIMIT_EPS = 1e-6  # [rad] a joint this close to a limit counts as at the limit
MU_INIT, MU_DOWN, MU_UP, MU_MIN = 1e-3, 0.3, 10.0, 1e-9  # Levenberg-Marquardt damping schedule

# robot key point (``body:NAME`` / ``site:NAME``) -> human key point, per shipped robot
DEFAULT_KEYPOINT_MAPS: dict[str, dict[str, str]] = {
    "mahru_arm": {
        "body:upper_arm": "shoulder",
        "body:forearm": "elbow",
        "body:hand": "wrist",
        "site:hand": "hand",
    },
    "arm6": {
        "body:upper_link": "shoulder",
        "body:fore_link": "elbow",
        "body:wrist_head": "wrist",
        "site:tool": "hand",
    },
}


# IK weight per human key point, per shipped robot (others: 1). arm6 is not anthropomorphic (its
# upper link points up, elbow above the hand), so it follows the human wrist and hand only; its
# shoulder and elbow still set the scale of the chain.
DEFAULT_KEYPOINT_WEIGHTS: dict[str, dict[str, float]] = {
    "arm6": {"shoulder": 0.0, "elbow": 0.0},
}


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

    mapping None: `DEFAULT_KEYPOINT_MAPS` for a shipped robot, else a guess from joint names
    (the body of the first controlled joint named ``*shoulder*``, ``*elbow*``, ``*wrist*``; the
    end-effector site for the hand). Robot points: ``site:NAME`` (only the robot's end-effector
    site), ``body:NAME``, or a bare name (the site if it is the end-effector site, else a body).
    weights: human key point -> IK weight, over `DEFAULT_KEYPOINT_WEIGHTS` (default 1).
    """
    m = robot.mj_model
    if mapping is None:
        mapping = DEFAULT_KEYPOINT_MAPS.get(robot.name)
        if mapping is None or (
            robot.name in DEFAULT_KEYPOINT_MAPS
            and f"site:{robot.site_name}" not in DEFAULT_KEYPOINT_MAPS[robot.name]
        ):
            mapping = _guess_keypoints(robot)
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
    w = dict(DEFAULT_KEYPOINT_WEIGHTS.get(robot.name, {}))
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


def _guess_keypoints(robot) -> dict[str, str]:
    m = robot.mj_model
    out = {}
    for word in ("shoulder", "elbow", "wrist"):
        for jname, jid in zip(robot.joint_names, robot.joint_ids):
            if word in jname.lower():
                body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.jnt_bodyid[jid]))
                if f"body:{body}" not in out:
                    out[f"body:{body}"] = word
                break
    out[f"site:{robot.site_name}"] = "hand"
    return out


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
    """Human key points ``(F, K, 3)`` in the body frame (x forward, y left, z up; origin at the
    first key point in frame 0) -> robot targets ``(F, K, 3)`` in the robot's world frame.

    rest_points: ``(K, 3)`` robot key points at its rest posture (its root anchors the chain).
    """
    seg = np.diff(human, axis=1)  # (F, K-1, 3)
    length = np.linalg.norm(seg, axis=-1)
    if not (length > 1e-6).all():
        raise TrialError("two key points coincide: cannot tell a segment's direction")
    h_len = np.median(length, axis=0)
    r_len = robot_segment_lengths(rest_points)
    ratio = r_len.sum() / h_len.sum()
    root = rest_points[0] + ratio * (human[:, 0] - human[0, 0])
    steps = r_len[None, :, None] * seg / length[..., None]
    targets = np.concatenate([root[:, None], root[:, None] + np.cumsum(steps, axis=1)], axis=1)
    return Scaled(targets, h_len, r_len)


# ------------------------------------------------------------------------------------------ IK


@dataclass(frozen=True)
class IKSettings:
    """Regularisation and iteration counts of the key-point IK (static under jit).

    smooth: s [m^2/rad^2], pull toward the previous frame's posture (temporal smoothness).
    posture: r [m^2/rad^2], pull toward the rest posture (resolves redundancy).
    iters: LM iterations per frame. warmup: the first frame is solved ``warmup`` times in a row
      before the trial starts (``warmup * iters`` iterations from the rest posture).
    """

    smooth: float = 1e-3
    posture: float = 1e-5
    iters: int = 4
    warmup: int = 12

    def __post_init__(self):
        if self.smooth < 0 or self.posture < 0:
            raise UserError("smooth and posture weights must be >= 0")
        if self.iters < 1 or self.warmup < 1:
            raise UserError("iteration counts must be >= 1")


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
