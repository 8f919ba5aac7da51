"""Recursive Newton-Euler inverse dynamics compiled from a MuJoCo model (the fast backend).

Implements the torque model of the paper's cost (Park et al. 2008, eq. 5),
``tau = M(q) qdd + C(q, qd) qd + g(q)``, for the robot's controlled hinge/slide joints, plus the
joint-space terms that MuJoCo's ``mj_inverse`` adds, so that both backends return its
``qfrc_inverse``: ``armature * qdd + damping * qd + stiffness * (q - qpos_spring)`` (all zero
in the shipped models).

Compilation (numpy, once per model). The kinematic tree is read from ``mjModel`` and reduced to
one rigid *segment* per controlled joint: everything rigidly attached to a joint's output frame
(its body, welded children, bodies whose joints are not controlled and so are held at
``qpos0``) is merged into one mass, centre of mass and inertia, and every constant transform
between two controlled joints is folded into the next joint's transform. Joint ``j`` then
moves its segment relative to its parent segment by ``M_j = C0_j + s_j C1_j + c_j C2_j``, with
``s = sin(angle), c = 1 - cos(angle)`` for a hinge (Rodrigues about an axis through an anchor)
and ``s = displacement, c = 0`` for a slide. Bodies no controlled joint moves take their pose
from ``mj_kinematics`` at ``qpos0`` and carry no controlled joint's weight.

Evaluation (JAX, per sample). Forward kinematics is a chain of J 3x4 products (the only
sequential part). The rest is vectorised over the J segments in the world frame, with twists,
accelerations and wrenches taken at the world origin (Featherstone's spatial algebra):
    v = A (S qd),    a = A (S qdd + v_parent x S qd) - g,    f = I a + v x* I v,
    tau = S . (A^T f)
where ``A[j, i] = 1`` if joint ``i`` is ``j`` or one of its ancestors: tree sums become one
constant product. All small products are written as broadcast multiply-sums, so XLA fuses them
and GPUs never route them through TF32 matmuls. About a hundred JAX ops per model, so compiling
a vmapped value-and-grad takes seconds.

Constraints, contacts, gravity compensation and fluid forces are not modelled (refused where
they would change ``qfrc_inverse`` and can be seen in the model).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.errors import UserError

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_LAST_COLUMN = np.array([0.0, 0.0, 0.0, 1.0], np.float32)  # weak enough: exact 0/1 in any dtype


class BackendFunctions(NamedTuple):
    """Pure single-sample functions (un-jitted) that a backend builds for `Dynamics`."""

    inverse: Callable  # (q (J,), qd (J,), qdd (J,)) -> tau (J,)
    site_pose: Callable  # q (J,) -> (pos (3,), rot (3, 3))
    body_positions: Callable  # q (J,) -> (nbody, 3), world body origins (xpos)


# -- compile time (numpy, float64) ------------------------------------------------------------


def _quat_mat(quat: np.ndarray) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform."""
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot, pos
    return t


def _generators(kind: int, axis: np.ndarray, anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G1, G2), 4x4: the joint's local transform is I + s G1 + c G2 (see module docstring)."""
    g1, g2 = np.zeros((4, 4)), np.zeros((4, 4))
    if kind == _HINGE:  # rotate about `axis` through `anchor`: x -> anchor + R (x - anchor)
        k = _skew(axis)
        g1[:3, :3], g1[:3, 3] = k, -k @ anchor
        g2[:3, :3], g2[:3, 3] = k @ k, -k @ k @ anchor
    else:
        g1[:3, 3] = axis
    return g1, g2


def _model_name(m: mujoco.MjModel) -> str:
    return m.names.split(b"\x00", 1)[0].decode()


def _check_supported(m: mujoco.MjModel, moving: np.ndarray) -> None:
    """Refuse model features whose forces `mj_inverse` would add but this RNEA does not."""
    where = f"model '{_model_name(m)}'"
    for b in np.nonzero(moving)[0]:
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if m.jnt_type[j] not in (_HINGE, _SLIDE):
                name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise UserError(
                    f"{where}: joint '{name}': expected hinge or slide joints below the "
                    "controlled joints (ball and free joints are not supported by 'rnea')"
                )
    if np.any(m.body_gravcomp[moving] != 0):
        raise UserError(f"{where}: body gravcomp: expected 0 (not supported by 'rnea')")
    if m.opt.density != 0 or m.opt.viscosity != 0:
        raise UserError(f"{where}: option density/viscosity: expected 0 (no fluid forces)")
    if m.ntendon and (np.any(m.tendon_stiffness != 0) or np.any(m.tendon_damping != 0)):
        raise UserError(f"{where}: tendon stiffness/damping: expected 0 (not supported by 'rnea')")


class _Tree(NamedTuple):
    """The model reduced to J segments, in topological order (parents first); float64."""

    order: np.ndarray  # (J,) robot joint index of each segment
    c0: np.ndarray  # (J, 3, 4) M_j = C0 + s C1 + c C2: segment j in its parent's frame
    c1: np.ndarray  # (J, 3, 4)
    c2: np.ndarray  # (J, 3, 4)
    parent: np.ndarray  # (J,) parent segment, -1 for a root (its C's are in the world frame)
    hinge: np.ndarray  # (J,) 1.0 hinge, 0.0 slide
    qpos0: np.ndarray  # (J,) joint angle/displacement = q - qpos0
    axis: np.ndarray  # (J, 3) joint axis in its segment frame (invariant under the joint)
    anchor: np.ndarray  # (J, 3) joint anchor in its segment frame (invariant for a hinge)
    ancestors: np.ndarray  # (J, J) A[j, i] = 1 if i == j or i is an ancestor of j
    mass: np.ndarray  # (J,) segment mass
    com: np.ndarray  # (J, 3) segment centre of mass, segment frame
    inertia: np.ndarray  # (J, 3, 3) segment inertia about its centre of mass, segment frame
    body_segment: np.ndarray  # (nbody,) segment a body is attached to, -1 if it never moves
    body_offset: np.ndarray  # (nbody, 4, 4) body frame in its segment frame (or world frame)


def _reduce_tree(m: mujoco.MjModel, joint_ids: list[int]) -> _Tree:
    ctrl = {j: k for k, j in enumerate(joint_ids)}
    # Bodies are stored parent-before-child, so one forward sweep sets `moving`.
    moving = np.zeros(m.nbody, bool)
    for b in range(1, m.nbody):
        adr, num = m.body_jntadr[b], m.body_jntnum[b]
        moving[b] = moving[m.body_parentid[b]] or any(j in ctrl for j in range(adr, adr + num))
    _check_supported(m, moving)

    d0 = mujoco.MjData(m)  # world poses of the never-moving bodies, at qpos0
    d0.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d0)

    # Walk the tree: `rel` = current frame in the frame of segment `seg` (world if seg == -1).
    seg_of_joint, parent, offset = [], [], []
    body_segment = np.full(m.nbody, -1)
    body_offset = np.zeros((m.nbody, 4, 4))
    for b in range(m.nbody):
        body_offset[b] = _transform(d0.xmat[b].reshape(3, 3), d0.xpos[b])
    for b in np.nonzero(moving)[0]:
        p = m.body_parentid[b]
        seg, rel = int(body_segment[p]), body_offset[p]
        rel = rel @ _transform(_quat_mat(m.body_quat[b]), m.body_pos[b])
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if j not in ctrl:
                continue  # held at qpos0: identity transform, at rest
            seg_of_joint.append(j)
            parent.append(seg)
            offset.append(rel)
            seg, rel = len(seg_of_joint) - 1, np.eye(4)
        body_segment[b], body_offset[b] = seg, rel

    n = len(seg_of_joint)
    order = np.asarray([ctrl[j] for j in seg_of_joint])
    c0, c1, c2 = np.zeros((n, 3, 4)), np.zeros((n, 3, 4)), np.zeros((n, 3, 4))
    axis, anchor = np.zeros((n, 3)), np.zeros((n, 3))
    for s, j in enumerate(seg_of_joint):
        axis[s] = m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j])
        anchor[s] = m.jnt_pos[j]
        g1, g2 = _generators(int(m.jnt_type[j]), axis[s], anchor[s])
        c0[s], c1[s], c2[s] = offset[s][:3], (offset[s] @ g1)[:3], (offset[s] @ g2)[:3]
    ancestors = np.zeros((n, n))
    for s in range(n):
        i = s
        while i >= 0:
            ancestors[s, i] = 1.0
            i = parent[i]

    # Merge the bodies of each segment: mass, centre of mass, inertia about it (parallel axis).
    mass, com, inertia = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3, 3))
    for b in np.nonzero(moving)[0]:
        s, rel = body_segment[b], body_offset[b]
        mass[s] += m.body_mass[b]
        com[s] += m.body_mass[b] * (rel[:3, :3] @ m.body_ipos[b] + rel[:3, 3])
    com /= np.maximum(mass, 1e-300)[:, None]
    for b in np.nonzero(moving)[0]:
        s, rel = body_segment[b], body_offset[b]
        rot = rel[:3, :3] @ _quat_mat(m.body_iquat[b])
        d = rel[:3, :3] @ m.body_ipos[b] + rel[:3, 3] - com[s]
        inertia[s] += rot @ np.diag(m.body_inertia[b]) @ rot.T
        inertia[s] += m.body_mass[b] * (d @ d * np.eye(3) - np.outer(d, d))

    return _Tree(
        order=order,
        c0=c0,
        c1=c1,
        c2=c2,
        parent=np.asarray(parent, int),
        hinge=np.asarray([float(m.jnt_type[j] == _HINGE) for j in seg_of_joint]),
        qpos0=np.asarray([m.qpos0[m.jnt_qposadr[j]] for j in seg_of_joint]),
        axis=axis,
        anchor=anchor,
        ancestors=ancestors,
        mass=mass,
        com=com,
        inertia=inertia,
        body_segment=body_segment,
        body_offset=body_offset,
    )


# -- run time (JAX): broadcast multiply-sums, fused by XLA, exact float32 on GPUs --------------


def _mv(a, x):
    """a: (..., 3, k), x: (..., k) -> a @ x: (..., 3)."""
    return jnp.sum(a * x[..., None, :], axis=-1)


def _mtv(a, x):
    """a: (..., 3, 3), x: (..., 3) -> a.T @ x."""
    return jnp.sum(a * x[..., :, None], axis=-2)


def _cross(a, b):
    """a, b: (..., 3) -> a x b."""
    return jnp.cross(a, b)


def _compose(a, b):
    """Rigid transforms as [R | o], (3, 4) each -> a @ b (with the implicit last row 0 0 0 1)."""
    return jnp.sum(a[:, :3, None] * b[None, :, :], axis=1) + a * _LAST_COLUMN


def _tree_sum(a, x):
    """a: (J, J) constant, x: (J, k) -> a @ x, as a fusible multiply-sum (no TF32)."""
    return jnp.sum(a[:, :, None] * x[None, :, :], axis=1)


def make_rnea(robot: Any, dtype: Any = jnp.float32) -> BackendFunctions:
    """Compile `robot.mj_model` into RNEA and forward-kinematics functions.

    robot: needs `mj_model`, `joint_ids (J,)`, `site_id` (see `evojax_motion.robot.Robot`).
    dtype: float dtype of the constants and of the computation.
    """
    m = robot.mj_model
    joint_ids = [int(j) for j in np.asarray(robot.joint_ids)]
    for j in joint_ids:
        if m.jnt_type[j] not in (_HINGE, _SLIDE):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise UserError(f"joints: '{name}': expected a hinge or slide joint")
    tree = _reduce_tree(m, joint_ids)
    n = len(joint_ids)
    order = tree.order  # segment s is robot joint order[s]

    def c(x):  # constants are numpy arrays of `dtype`, folded into the graph
        return np.asarray(x, dtype)

    c0, c1, c2 = c(tree.c0), c(tree.c1), c(tree.c2)
    hinge, slide, qpos0 = c(tree.hinge), c(1.0 - tree.hinge), c(tree.qpos0)
    axis, anchor = c(tree.axis), c(tree.anchor)
    ancestors, ancestors_t = c(tree.ancestors), c(tree.ancestors.T)
    mass, com, inertia = c(tree.mass)[:, None], c(tree.com), c(tree.inertia)
    parents = [int(p) for p in tree.parent]
    # Permutations and the parent lookup are constant 0/1 matrices: a gather's gradient is a
    # scatter, slow on CPU; a product's is a product.
    parent_of = c(np.eye(n + 1)[tree.parent][:, :n])  # row j: one-hot parent, zero for a root
    identity = bool(np.all(order == np.arange(n)))
    to_segments = c(np.eye(n)[order])  # x_seg = to_segments @ x_robot

    disabled = int(m.opt.disableflags)
    gravity = np.zeros(3) if disabled & mujoco.mjtDisableBit.mjDSBL_GRAVITY else m.opt.gravity
    # The base accelerates against gravity, so every segment feels it (no per-body term).
    root_acc = c(np.concatenate([np.zeros(3), -gravity]))
    # Joint-space terms of qfrc_inverse: armature (in M) and minus the passive forces.
    dof_adr, qpos_adr = m.jnt_dofadr[joint_ids], m.jnt_qposadr[joint_ids]
    armature = m.dof_armature[dof_adr]
    damping = m.dof_damping[dof_adr] * (not (disabled & mujoco.mjtDisableBit.mjDSBL_DAMPER))
    stiffness = m.jnt_stiffness[joint_ids] * (not (disabled & mujoco.mjtDisableBit.mjDSBL_SPRING))
    passive = bool(np.any(armature) or np.any(damping) or np.any(stiffness))
    armature, damping, stiffness = c(armature), c(damping), c(stiffness)
    qpos_spring = c(m.qpos_spring[qpos_adr])

    site_id = int(robot.site_id)
    site_body = int(m.site_bodyid[site_id])
    site_seg = int(tree.body_segment[site_body])  # -1: the site never moves
    site_offset = _transform(_quat_mat(m.site_quat[site_id]), m.site_pos[site_id])
    site_rel = c((tree.body_offset[site_body] @ site_offset)[:3])  # in its segment (or world)

    def _permute(p, x):
        return x if identity else _tree_sum(p, x[:, None])[:, 0]

    def kinematics(q):
        """q: (J,) robot order -> segment frames W: (J, 3, 4) = [R | o] in the world frame."""
        angle = _permute(to_segments, jnp.asarray(q, dtype)) - qpos0
        s = hinge * jnp.sin(angle) + slide * angle
        cc = hinge * (1.0 - jnp.cos(angle))
        local = c0 + s[:, None, None] * c1 + cc[:, None, None] * c2  # (J, 3, 4)
        frames = []
        for j in range(n):
            p = parents[j]
            frames.append(local[j] if p < 0 else _compose(frames[p], local[j]))
        return jnp.stack(frames)

    def inverse(q, qd, qdd):
        """q, qd, qdd: (J,) -> tau (J,) = M qdd + C qd + g (+ armature, damping, stiffness)."""
        q, qd, qdd = (jnp.asarray(x, dtype) for x in (q, qd, qdd))
        frames = kinematics(q)
        rot, org = frames[:, :, :3], frames[:, :, 3]
        # Joint motion subspaces S = (angular, linear at the origin), world frame: (J, 6).
        axis_w = _mv(rot, axis)
        anchor_w = _mv(rot, anchor) + org
        sw = hinge[:, None] * axis_w
        sv = hinge[:, None] * _cross(anchor_w, axis_w) + slide[:, None] * axis_w
        rate, accel = (_permute(to_segments, x)[:, None] for x in (qd, qdd))
        xw, xv = sw * rate, sv * rate  # joint twists
        vel = _tree_sum(ancestors, jnp.concatenate([xw, xv], axis=1))  # segment twists (J, 6)
        pvel = _tree_sum(parent_of, vel)
        pw, pv = pvel[:, :3], pvel[:, 3:]
        # Joint axes move with the parent: d/dt (S qd) = S qdd + v_parent x (S qd).
        bias = jnp.concatenate([_cross(pw, xw), _cross(pw, xv) + _cross(pv, xw)], axis=1)
        src = jnp.concatenate([sw * accel, sv * accel], axis=1) + bias
        acc = _tree_sum(ancestors, src) + root_acc
        w, v, dw, dv = vel[:, :3], vel[:, 3:], acc[:, :3], acc[:, 3:]
        # Newton-Euler per segment, about its centre of mass; moment taken about the origin.
        com_w = _mv(rot, com) + org
        acom = dv + _cross(dw, com_w) + _cross(w, v + _cross(w, com_w))
        force = mass * acom
        i_dw = _mv(rot, _mv(inertia, _mtv(rot, dw)))
        i_w = _mv(rot, _mv(inertia, _mtv(rot, w)))
        moment = i_dw + _cross(w, i_w) + _cross(com_w, force)
        sub = _tree_sum(ancestors_t, jnp.concatenate([moment, force], axis=1))  # subtree wrench
        tau = _permute(to_segments.T, jnp.sum(sw * sub[:, :3] + sv * sub[:, 3:], axis=1))
        if passive:
            tau = tau + armature * qdd + damping * qd + stiffness * (q - qpos_spring)
        return tau

    def site_pose(q):
        """q: (J,) -> site position (3,) and rotation matrix (3, 3), world frame."""
        pose = site_rel if site_seg < 0 else _compose(kinematics(q)[site_seg], site_rel)
        return jnp.asarray(pose[:, 3]), jnp.asarray(pose[:, :3])

    moving_bodies = np.nonzero(tree.body_segment >= 0)[0]
    body_seg = tree.body_segment[moving_bodies]
    body_org = c(tree.body_offset[moving_bodies, :3, 3])
    fixed_xpos = c(tree.body_offset[:, :3, 3])

    def body_positions(q):
        """q: (J,) -> (nbody, 3) world body origins (MuJoCo xpos), world body first."""
        w = kinematics(q)[body_seg]
        return (
            jnp.asarray(fixed_xpos).at[moving_bodies].set(_mv(w[:, :, :3], body_org) + w[:, :, 3])
        )

    return BackendFunctions(inverse=inverse, site_pose=site_pose, body_positions=body_positions)
