"""Recursive Newton-Euler inverse dynamics compiled from a MuJoCo model (the fast backend).

Implements the torque model of the paper's cost (Park et al. 2008, eq. 5):
``tau = M(q) qdd + C(q, qd) qd + g(q)`` for the robot's controlled hinge/slide joints, plus the
joint-space terms MuJoCo's ``mj_inverse`` adds so that both backends return its
``qfrc_inverse``: ``armature * qdd + damping * qd + stiffness * (q - qpos_spring)`` (all zero in
the shipped models).

The kinematic tree is read once from ``mjModel`` (body and joint frames, inertias, gravity, the
site) and unrolled in Python into one straight-line JAX graph per model: nbody is small, so XLA
sees a single fused computation with no gathers or loops. Quantities are expressed in the world
frame: twists and spatial accelerations are taken at the world origin (Featherstone's spatial
algebra), forces as (force, moment about the origin). This avoids per-body 6x6 transforms;
every 3x3 product is written elementwise, so GPUs never route it through TF32 matmuls.

Joints that the robot does not control are held at ``qpos0`` (identity transform, at rest).
Bodies that no controlled joint moves take their world pose from ``mj_kinematics`` at
``qpos0`` and drop out of the dynamics (no controlled joint carries their weight).
Constraints, contacts, gravity compensation and fluid forces are not modelled.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.errors import UserError

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)


class RneaFunctions(NamedTuple):
    """Pure single-sample functions (un-jitted) built by `make_rnea`."""

    inverse: Callable  # (q (J,), qd (J,), qdd (J,)) -> tau (J,)
    site_pose: Callable  # q (J,) -> (pos (3,), rot (3, 3))
    body_positions: Callable  # q (J,) -> (nbody, 3), world body origins (xpos)


class _Joint(NamedTuple):
    k: int  # index in the robot's joint list (tau[k])
    kind: int  # _HINGE | _SLIDE
    pos: np.ndarray  # (3,) anchor in the body frame
    axis: np.ndarray  # (3,) unit axis in the body frame
    skew: np.ndarray  # (3, 3) [axis]x, for the Rodrigues formula
    skew2: np.ndarray  # (3, 3) [axis]x^2
    qpos0: float


class _Body(NamedTuple):
    parent: int
    parent_moving: bool
    pos: np.ndarray  # (3,) origin in the parent frame, or world origin if parent is fixed
    rot: np.ndarray  # (3, 3) frame in the parent frame, or world frame if parent is fixed
    joints: tuple[_Joint, ...]  # controlled joints, in MuJoCo order
    mass: float
    has_inertia: bool
    ipos: np.ndarray  # (3,) centre of mass in the body frame
    irot: np.ndarray  # (3, 3) principal inertia frame in the body frame
    inertia: np.ndarray  # (3,) principal moments


# -- elementwise 3-vector / 3x3 algebra (no dot_general: exact float32 on GPUs, fuses on CPU) --


def _mv(a, x):
    """a: (3, 3), x: (3,) -> a @ x."""
    return jnp.sum(a * x[None, :], axis=-1)


def _mtv(a, x):
    """a: (3, 3), x: (3,) -> a.T @ x."""
    return jnp.sum(a * x[:, None], axis=0)


def _mm(a, b):
    """a, b: (3, 3) -> a @ b."""
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _cross(a, b):
    """a, b: (3,) -> a x b."""
    return jnp.stack(
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    )


def _dot(a, b):
    return jnp.sum(a * b)


def _quat_mat(quat: np.ndarray) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _check_supported(m: mujoco.MjModel, moving: np.ndarray) -> None:
    """Refuse model features whose forces `mj_inverse` would add but this RNEA does not."""
    model_name = m.names.split(b"\x00", 1)[0].decode()
    where = f"model '{model_name}'"
    for b in np.nonzero(moving)[0]:
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if m.jnt_type[j] not in (_HINGE, _SLIDE):
                name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise UserError(
                    f"{where}: joint '{name}': expected hinge or slide joints in the moving "
                    "tree (ball and free joints are not supported by the RNEA backend)"
                )
    if np.any(m.body_gravcomp[moving] != 0):
        raise UserError(f"{where}: body gravcomp: expected 0 (not supported by RNEA)")
    if m.opt.density != 0 or m.opt.viscosity != 0:
        raise UserError(f"{where}: option density/viscosity: expected 0 (no fluid forces)")
    if m.ntendon and (np.any(m.tendon_stiffness != 0) or np.any(m.tendon_damping != 0)):
        raise UserError(f"{where}: tendon stiffness/damping: expected 0 (not supported by RNEA)")


def make_rnea(robot: Any, dtype: Any = jnp.float32) -> RneaFunctions:
    """Compile `robot.mj_model` into RNEA and forward-kinematics functions.

    robot: needs `mj_model`, `joint_ids (J,)`, `site_id` (see `evojax_motion.robot.Robot`).
    dtype: float dtype of every constant and of the computation.
    """
    m = robot.mj_model
    dtype = np.dtype(dtype)
    joint_ids = [int(j) for j in np.asarray(robot.joint_ids)]
    ctrl = {j: k for k, j in enumerate(joint_ids)}
    n_joints = len(joint_ids)
    for j in joint_ids:
        if m.jnt_type[j] not in (_HINGE, _SLIDE):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise UserError(f"joints: '{name}': expected a hinge or slide joint")

    def c(x):  # constants live as numpy arrays of the requested dtype (folded into the graph)
        return np.asarray(x, dtype)

    # Bodies are stored parent-before-child, so one forward sweep sets `moving`.
    moving = np.zeros(m.nbody, bool)
    for b in range(1, m.nbody):
        adr, num = m.body_jntadr[b], m.body_jntnum[b]
        own = any(j in ctrl for j in range(adr, adr + num))
        moving[b] = own or moving[m.body_parentid[b]]
    _check_supported(m, moving)

    # World poses of the fixed bodies and sites, from MuJoCo itself at qpos0.
    d0 = mujoco.MjData(m)
    d0.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d0)
    fixed_xpos = d0.xpos.copy()
    fixed_xmat = d0.xmat.reshape(-1, 3, 3).copy()

    bodies: dict[int, _Body] = {}
    for b in np.nonzero(moving)[0]:
        p = int(m.body_parentid[b])
        rot = _quat_mat(m.body_quat[b])
        pos = m.body_pos[b].copy()
        if not moving[p]:  # fold the fixed parent's world pose into this body's constants
            pos = fixed_xpos[p] + fixed_xmat[p] @ pos
            rot = fixed_xmat[p] @ rot
        joints = []
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if j not in ctrl:
                continue  # held at qpos0: identity transform, at rest
            axis = m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j])
            skew = _skew(axis)
            joints.append(
                _Joint(
                    k=ctrl[j],
                    kind=int(m.jnt_type[j]),
                    pos=c(m.jnt_pos[j]),
                    axis=c(axis),
                    skew=c(skew),
                    skew2=c(skew @ skew),
                    qpos0=float(m.qpos0[m.jnt_qposadr[j]]),
                )
            )
        bodies[int(b)] = _Body(
            parent=p,
            parent_moving=bool(moving[p]),
            pos=c(pos),
            rot=c(rot),
            joints=tuple(joints),
            mass=float(m.body_mass[b]),
            has_inertia=bool(m.body_mass[b] > 0 or np.any(m.body_inertia[b] > 0)),
            ipos=c(m.body_ipos[b]),
            irot=c(_quat_mat(m.body_iquat[b])),
            inertia=c(m.body_inertia[b]),
        )
    order = sorted(bodies)

    disabled = int(m.opt.disableflags)
    gravity = m.opt.gravity.copy()
    if disabled & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY):
        gravity[:] = 0.0
    # Joint-space terms of qfrc_inverse (mass-matrix armature, minus the passive forces).
    dof_adr = np.asarray([m.jnt_dofadr[j] for j in joint_ids])
    qpos_adr = np.asarray([m.jnt_qposadr[j] for j in joint_ids])
    armature = m.dof_armature[dof_adr]
    damping = m.dof_damping[dof_adr]
    stiffness = m.jnt_stiffness[joint_ids]
    if disabled & int(mujoco.mjtDisableBit.mjDSBL_DAMPER):
        damping = np.zeros_like(damping)
    if disabled & int(mujoco.mjtDisableBit.mjDSBL_SPRING):
        stiffness = np.zeros_like(stiffness)
    qpos_spring = m.qpos_spring[qpos_adr]
    has_armature, has_damping, has_spring = (bool(np.any(x != 0)) for x in (armature, damping, stiffness))
    armature, damping, stiffness, qpos_spring = map(c, (armature, damping, stiffness, qpos_spring))
    root_acc = c(-gravity)  # base accelerates against gravity: every body feels g, no per-body term

    site_id = int(robot.site_id)
    site_body = int(m.site_bodyid[site_id])
    site_pos, site_rot = c(m.site_pos[site_id]), c(_quat_mat(m.site_quat[site_id]))
    fixed_site = (c(d0.site_xpos[site_id]), c(d0.site_xmat[site_id].reshape(3, 3)))

    def kinematics(q):
        """q: (J,) -> world frames {body: (R (3,3), o (3,))} and joint motions {k: (axis, anchor)}.

        Follows mj_kinematics: a body starts at parent pose * (body_pos, body_quat); each joint
        then rotates about (hinge) or translates along (slide) its axis through its anchor, both
        taken in the frame left by the previous joints of the same body.
        """
        frames, motions = {}, {}
        for b in order:
            body = bodies[b]
            if body.parent_moving:
                rp, op = frames[body.parent]
                rot, org = _mm(rp, body.rot), op + _mv(rp, body.pos)
            else:
                rot, org = body.rot, body.pos
            for jnt in body.joints:
                angle = q[jnt.k] - jnt.qpos0
                axis_w = _mv(rot, jnt.axis)
                anchor = org + _mv(rot, jnt.pos)
                motions[jnt.k] = (axis_w, anchor)
                if jnt.kind == _HINGE:
                    local = np.eye(3, dtype=dtype) + jnp.sin(angle) * jnt.skew
                    local = local + (1 - jnp.cos(angle)) * jnt.skew2
                    rot = _mm(rot, local)
                    org = anchor - _mv(rot, jnt.pos)
                else:
                    org = org + axis_w * angle
            frames[b] = (rot, org)
        return frames, motions

    def motion_subspace(kind, axis_w, anchor):
        """Joint twist per unit rate at the world origin: (angular (3,), linear (3,))."""
        if kind == _HINGE:
            return axis_w, _cross(anchor, axis_w)
        return jnp.zeros_like(axis_w), axis_w

    def inverse(q, qd, qdd):
        """q, qd, qdd: (J,) -> tau (J,) = M qdd + C qd + g (+ armature, damping, stiffness)."""
        q, qd, qdd = (jnp.asarray(x, dtype) for x in (q, qd, qdd))
        frames, motions = kinematics(q)
        zero = jnp.zeros(3, dtype)
        vel, acc, wrench = {}, {}, {}
        # Forward pass: twists (w, v0) and spatial accelerations (dw, dv0) at the world origin.
        for b in order:
            body = bodies[b]
            if body.parent_moving:
                (w, v), (dw, dv) = vel[body.parent], acc[body.parent]
            else:
                w, v, dw, dv = zero, zero, zero, root_acc
            for jnt in body.joints:
                sw, sv = motion_subspace(jnt.kind, *motions[jnt.k])
                # S is fixed in the frame moving with (w, v): dS/dt = (w, v) x S.
                dw = dw + sw * qdd[jnt.k] + _cross(w, sw) * qd[jnt.k]
                dv = dv + sv * qdd[jnt.k] + (_cross(w, sv) + _cross(v, sw)) * qd[jnt.k]
                w, v = w + sw * qd[jnt.k], v + sv * qd[jnt.k]
            vel[b], acc[b] = (w, v), (dw, dv)
            if not body.has_inertia:
                wrench[b] = (zero, zero)
                continue
            rot, org = frames[b]
            com = org + _mv(rot, body.ipos)
            irot = _mm(rot, body.irot)
            vcom = v + _cross(w, com)
            acom = dv + _cross(dw, com) + _cross(w, vcom)
            force = body.mass * acom
            # Newton-Euler about the centre of mass, I_c = irot diag(inertia) irot^T.
            i_dw = _mv(irot, body.inertia * _mtv(irot, dw))
            i_w = _mv(irot, body.inertia * _mtv(irot, w))
            moment = i_dw + _cross(w, i_w) + _cross(com, force)
            wrench[b] = (force, moment)
        # Backward pass: accumulate subtree wrenches; tau_k = S_k . f.
        tau = [None] * n_joints
        for b in reversed(order):
            body = bodies[b]
            force, moment = wrench[b]
            for jnt in body.joints:
                axis_w, anchor = motions[jnt.k]
                if jnt.kind == _HINGE:
                    tau[jnt.k] = _dot(axis_w, moment - _cross(anchor, force))
                else:
                    tau[jnt.k] = _dot(axis_w, force)
            if body.parent_moving:
                pf, pm = wrench[body.parent]
                wrench[body.parent] = (pf + force, pm + moment)
        tau = jnp.stack(tau)
        if has_armature:
            tau = tau + armature * qdd
        if has_damping:
            tau = tau + damping * qd
        if has_spring:
            tau = tau + stiffness * (q - qpos_spring)
        return tau

    def site_pose(q):
        """q: (J,) -> site position (3,) and rotation matrix (3, 3), world frame."""
        if site_body not in bodies:
            return jnp.asarray(fixed_site[0]), jnp.asarray(fixed_site[1])
        frames, _ = kinematics(jnp.asarray(q, dtype))
        rot, org = frames[site_body]
        return org + _mv(rot, site_pos), _mm(rot, site_rot)

    def body_positions(q):
        """q: (J,) -> (nbody, 3) world body origins (MuJoCo xpos), world body first."""
        frames, _ = kinematics(jnp.asarray(q, dtype))
        rows = [frames[b][1] if b in frames else c(fixed_xpos[b]) for b in range(m.nbody)]
        return jnp.stack([jnp.asarray(r, dtype) for r in rows])

    return RneaFunctions(inverse=inverse, site_pose=site_pose, body_positions=body_positions)
