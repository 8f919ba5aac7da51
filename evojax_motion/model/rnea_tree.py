"""The kinematic tree of a MuJoCo model reduced to the RNEA's segments (numpy, float64, once per
model): one rigid segment per controlled joint, with every constant transform between two
controlled joints folded into the next joint's transform (`reduce_tree`), and the model features
the RNEA refuses (`check_supported`). The algorithm that evaluates the tree is `model.rnea`."""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.errors import UserError

HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)


def quat_mat(quat: np.ndarray) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform."""
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot, pos
    return t


def _generators(kind: int, axis: np.ndarray, anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G1, G2), 4x4: the joint's local transform is I + s G1 + c G2 (see module docstring)."""
    g1, g2 = np.zeros((4, 4)), np.zeros((4, 4))
    if kind == HINGE:  # rotate about `axis` through `anchor`: x -> anchor + R (x - anchor)
        k = _skew(axis)
        g1[:3, :3], g1[:3, 3] = k, -k @ anchor
        g2[:3, :3], g2[:3, 3] = k @ k, -k @ k @ anchor
    else:
        g1[:3, 3] = axis
    return g1, g2


def disabled(m: mujoco.MjModel, flag: str, older_name: str | None = None) -> bool:
    """Whether <flag> `flag` is disabled (MuJoCo < 3.3 had one "passive" flag for both)."""
    bit = getattr(mujoco.mjtDisableBit, flag, None)
    if bit is None and older_name is not None:
        bit = getattr(mujoco.mjtDisableBit, older_name)
    return bool(int(m.opt.disableflags) & int(bit))  # type: ignore[arg-type]


def model_name(m: mujoco.MjModel) -> str:
    return m.names.split(b"\x00", 1)[0].decode()


def check_supported(m: mujoco.MjModel, moving: np.ndarray) -> None:
    """Refuse model features whose forces `mj_inverse` would add but this RNEA does not."""
    where = f"model '{model_name(m)}'"
    for b in map(int, np.nonzero(moving)[0]):
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if m.jnt_type[j] not in (HINGE, SLIDE):
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


class Tree(NamedTuple):
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


def reduce_tree(m: mujoco.MjModel, joint_ids: list[int]) -> Tree:
    ctrl = {j: k for k, j in enumerate(joint_ids)}
    # Bodies are stored parent-before-child, so one forward sweep sets `moving`.
    moving = np.zeros(m.nbody, bool)
    for b in range(1, m.nbody):
        adr, num = m.body_jntadr[b], m.body_jntnum[b]
        moving[b] = moving[m.body_parentid[b]] or any(j in ctrl for j in range(adr, adr + num))
    check_supported(m, moving)

    d0 = mujoco.MjData(m)  # world poses of the never-moving bodies, at qpos0
    d0.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d0)

    # Walk the tree: `rel` = current frame in the frame of segment `seg` (world if seg == -1).
    seg_of_joint, parent, offset = [], [], []
    body_segment = np.full(m.nbody, -1)
    body_offset = np.zeros((m.nbody, 4, 4))
    for b in range(m.nbody):
        body_offset[b] = transform(d0.xmat[b].reshape(3, 3), d0.xpos[b])
    for b in map(int, np.nonzero(moving)[0]):
        p = m.body_parentid[b]
        seg, rel = int(body_segment[p]), body_offset[p]
        rel = rel @ transform(quat_mat(m.body_quat[b]), m.body_pos[b])
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
    for b in map(int, np.nonzero(moving)[0]):
        s, rel = int(body_segment[b]), body_offset[b]
        mass[s] += m.body_mass[b]
        com[s] += m.body_mass[b] * (rel[:3, :3] @ m.body_ipos[b] + rel[:3, 3])
    com /= np.maximum(mass, 1e-300)[:, None]
    for b in map(int, np.nonzero(moving)[0]):
        s, rel = int(body_segment[b]), body_offset[b]
        rot = rel[:3, :3] @ quat_mat(m.body_iquat[b])
        d = rel[:3, :3] @ m.body_ipos[b] + rel[:3, 3] - com[s]
        inertia[s] += rot @ np.diag(m.body_inertia[b]) @ rot.T
        inertia[s] += m.body_mass[b] * (d @ d * np.eye(3) - np.outer(d, d))

    return Tree(
        order=order,
        c0=c0,
        c1=c1,
        c2=c2,
        parent=np.asarray(parent, int),
        hinge=np.asarray([float(m.jnt_type[j] == HINGE) for j in seg_of_joint]),
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


class Site(NamedTuple):
    segment: int  # segment the site is attached to, -1 if it never moves
    offset: np.ndarray  # (4, 4) site frame in the segment frame (world frame if segment == -1)
