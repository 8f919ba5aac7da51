"""The palm of a catching hand: which side of the hand receives the ball (`palm_normal`) and a
posture that holds the palm against the incoming ball at the catch point (`catch_posture`).

The paper's online process places the hand's catching point by position only (sec. 4); in
physics a ball reaching the back of the hand or the fingertips bounces off (docs/simulation.md,
"The palm meets the ball"). `catching.catch_query` uses these for every catch where the robot's
end-effector site lies on a surface of its hand.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.linalg.cholesky import spd_solve
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.ik import NULL_SPACE_MU
from evojax_motion.model.robot import Robot

PALM_TOLERANCE = 2e-3  # [m] the site lies on a geom's surface when this close to it
FACING_GOAL = 0.7  # the palm is turned toward the ball until n . facing reaches this
FACING_RAMP = 0.2  # the turning fades in over this much of n . facing below the goal
FACING_ITERS = 15  # damped least-squares iterations of `catch_posture`
FACING_DAMPING = 1e-2  # [m] lambda of those iterations (error-dependent on top, as `model.ik`)
FACING_STEP = 0.3  # [rad] largest joint step per iteration (trust region, as `model.ik`)
PREFERENCE_PULL = 0.5  # null-space pull toward the human-like posture per iteration


def _geom_distance(kind: int, size, x) -> float:
    """Signed distance [m] of ``x (3,)`` (geom frame) to a MuJoCo primitive's surface."""
    g = mujoco.mjtGeom
    if kind == g.mjGEOM_SPHERE:
        return float(np.linalg.norm(x) - size[0])
    if kind == g.mjGEOM_CAPSULE:
        z = np.clip(x[2], -size[1], size[1])
        return float(np.linalg.norm(x - np.array([0.0, 0.0, z])) - size[0])
    if kind == g.mjGEOM_ELLIPSOID:  # first-order distance: exact on the surface's normal
        k0 = float(np.linalg.norm(x / size[:3]))
        k1 = float(np.linalg.norm(x / size[:3] ** 2))
        return k0 * (k0 - 1.0) / max(k1, 1e-12)
    if kind in (g.mjGEOM_BOX, g.mjGEOM_CYLINDER):
        if kind == g.mjGEOM_BOX:
            q = np.abs(x) - size[:3]
        else:
            q = np.array([np.hypot(x[0], x[1]) - size[0], abs(x[2]) - size[1]])
        return float(np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0))
    return math.inf  # planes, meshes, height fields: not a hand's surface here


def palm_normal(robot: Robot) -> np.ndarray | None:
    """The outward normal, in the end-effector site's frame, of the hand surface the site lies
    on: ``(3,)`` unit vector, or None where the site is on no primitive geom of its body.

    The catching point of a hand (mahru_arm: the palm centre, on the palm face of the hand box)
    can only receive a ball from the side its surface faces: a ball arriving at the back of
    the hand or at the fingertips bounces off more than a ball's radius from it. Among the
    geoms of the site's body, the one whose surface passes within `PALM_TOLERANCE` of the site;
    the normal is the gradient of its signed distance there (central differences).
    """
    m = robot.mj_model
    site = robot.site_id
    body = int(m.site_bodyid[site])
    site_flat = np.zeros(9)
    mujoco.mju_quat2Mat(site_flat, m.site_quat[site])
    site_rot = site_flat.reshape(3, 3)
    best, normal = PALM_TOLERANCE, None
    for geom in np.flatnonzero(m.geom_bodyid == body):
        flat = np.zeros(9)
        mujoco.mju_quat2Mat(flat, m.geom_quat[geom])
        rot = flat.reshape(3, 3)
        x = rot.T @ (m.site_pos[site] - m.geom_pos[geom])
        kind, size = int(m.geom_type[geom]), np.asarray(m.geom_size[geom], np.float64)
        dist = _geom_distance(kind, size, x)
        if abs(dist) <= best:
            h = 1e-6
            grad = np.array(
                [
                    _geom_distance(kind, size, x + h * e) - _geom_distance(kind, size, x - h * e)
                    for e in np.eye(3)
                ]
            )
            if np.linalg.norm(grad) > 0:
                best = abs(dist)
                normal = site_rot.T @ (rot @ (grad / np.linalg.norm(grad)))
    return None if normal is None else normal.astype(np.float32)


def catch_posture(dyn: Dynamics, q_init, q_pref, point, facing, normal, radius, lower, upper):
    """Postures ``(B, J)`` that receive a ball centred at ``point (B, 3)`` on the palm, the
    palm turned toward ``facing (B, 3)`` (unit vectors: against the ball's velocity). Pure.

    Primary task: the point ``radius`` in front of the palm, ``site + radius n`` (``n``: the
    palm's outward normal ``normal (3,)``, site frame, in the world), at ``point``: a ball whose
    centre passes there touches the palm at the site, from whichever side of the palm normal it
    comes. Secondary, in the primary's null space: ``n`` toward ``facing`` while ``n . facing <
    FACING_GOAL``; then the pull toward ``q_pref (B, J)`` (the human-like posture) in what is
    left. Damped least squares from ``q_init (B, J)`` with the error-dependent damping and
    trust region of `model.ik`; joints a step would push across a limit are clamped on it and
    left out of the next solves. Returns ``(q, site target (B, 3), cosine (B,))``: where the
    site should be (``point - radius n``) and ``n . facing`` at ``q``.
    """
    normal = jnp.asarray(normal, q_init.dtype)
    dtype = q_init.dtype
    eye3, eye_j = jnp.eye(3, dtype=dtype), jnp.eye(q_init.shape[1], dtype=dtype)

    def features(q):
        pos, rot = dyn.site_pose(q)
        n = rot @ normal
        y = jnp.concatenate([pos + radius * n, n])
        return y, y

    def pinv_rows(a, lam2):  # a^T (a a^T + lam2 I)^-1: damped right pseudo-inverse (J, 3)
        gram = a @ a.T + lam2 * eye3
        return jnp.stack([a.T @ spd_solve(gram, e) for e in eye3], axis=1)

    def one(q0, qp, p, f):
        def step(q, jac, y, free):
            jp, jn = jac[:3] * free, jac[3:] * free
            e_p, n = p - y[:3], y[3:]
            cos = jnp.dot(n, f)
            gate = jnp.clip((FACING_GOAL - cos) / FACING_RAMP, 0.0, 1.0)
            e_n = gate * (f - n)
            lam2 = FACING_DAMPING**2 + 0.5 * jnp.sum(e_p**2)
            dq1 = pinv_rows(jp, lam2) @ e_p
            null = eye_j - pinv_rows(jp, NULL_SPACE_MU) @ jp  # projector onto jp's null space
            dq = dq1 + null @ (PREFERENCE_PULL * (qp - q) * free)
            jnp_ = jn @ null
            lam2n = FACING_DAMPING**2 + 0.5 * jnp.sum(e_n**2)
            dq = dq + null @ (pinv_rows(jnp_, lam2n) @ (e_n - jn @ dq))
            return dq

        def body(_, q):
            jac, y = jax.jacfwd(features, has_aux=True)(q)
            dq = step(q, jac, y, jnp.ones_like(q))
            blocked = (q + dq < lower) | (q + dq > upper)
            dq = step(q, jac, y, jnp.where(blocked, 0.0, 1.0))
            scale = jnp.minimum(1.0, FACING_STEP / (jnp.max(jnp.abs(dq)) + 1e-12))
            return jnp.clip(q + scale * dq, lower, upper)

        q = jax.lax.fori_loop(0, FACING_ITERS, body, jnp.clip(q0, lower, upper))
        n = features(q)[0][3:]
        return q, p - radius * n, jnp.dot(n, f)

    return jax.vmap(one)(q_init, q_pref, point, facing)
