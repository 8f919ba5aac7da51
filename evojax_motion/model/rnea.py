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

Evaluation (JAX, per sample), in the world frame, with twists, accelerations and wrenches
taken at the world origin (Featherstone's spatial algebra):
    W_j = W_parent M_j,    v_j = v_parent + S_j qd_j,
    a_j = a_parent + S_j qdd_j + v_parent x (S_j qd_j)    (a_base = -g: gravity for all),
    f_j = I_j a_j + v_j x* I_j v_j,    tau_j = S_j . (f_j + sum of the children's wrenches),
with ``S_j`` the joint's motion subspace, read from ``W_j`` (a joint's axis and anchor do not
move under the joint itself). Two layouts of the same straight-line graph (`FORMS`), because
XLA's CPU and GPU compilers want different ones (figures in benchmarks/results/
dynamics_throughput_*.json):
  - ``"vector"`` (CPU default): arrays over the J segments; tree sums are products with the
    constant ancestor matrix ``A[j, i] = 1`` if ``i`` is ``j`` or an ancestor of it. About 300 ops,
    no gathers or scatters; a vmapped value-and-grad compiles in seconds.
  - ``"scalar"`` (GPU default): every component is a scalar and model constants are Python
    floats, so products with 0 and 1 vanish at trace time (an axis-aligned joint costs a fraction
    of a general one) and after vmap the pass is one elementwise kernel: ~1 kFLOP and ~0.1 kB per
    evaluation for a 7-DOF arm, 8x the vector form on an H100 (3x for value-and-grad).

Constraints, contacts, gravity compensation and fluid forces are not modelled (refused where
they would change ``qfrc_inverse`` and can be seen in the model).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax import lax

from evojax_motion.errors import UserError

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
FORMS = ("vector", "scalar")
# jit compiler options under which the scalar form is the fast one on CPU: XLA's CPU fusion
# emitters off (`default_form`), per compiled program rather than process-wide through XLA_FLAGS.
UNFUSED_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
_LAST_COLUMN = np.array([0.0, 0.0, 0.0, 1.0], np.float32)  # weak enough: exact 0/1 in any dtype


class BackendFunctions(NamedTuple):
    """Pure single-sample functions (un-jitted) that a backend builds for `Dynamics`."""

    inverse: Callable  # (q (J,), qd (J,), qdd (J,)) -> tau (J,)
    site_pose: Callable  # q (J,) -> (pos (3,), rot (3, 3))
    body_positions: Callable  # q (J,) -> (nbody, 3), world body origins (xpos)
    torques: Callable | None = None  # sequences of J scalars -> tuple of J torques (scalar form)


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


def _disabled(m: mujoco.MjModel, flag: str, older_name: str | None = None) -> bool:
    """Whether <flag> `flag` is disabled (MuJoCo < 3.3 had one "passive" flag for both)."""
    bit = getattr(mujoco.mjtDisableBit, flag, None)
    if bit is None and older_name is not None:
        bit = getattr(mujoco.mjtDisableBit, older_name)
    return bool(int(m.opt.disableflags) & int(bit))  # type: ignore[arg-type]


def _model_name(m: mujoco.MjModel) -> str:
    return m.names.split(b"\x00", 1)[0].decode()


def _check_supported(m: mujoco.MjModel, moving: np.ndarray) -> None:
    """Refuse model features whose forces `mj_inverse` would add but this RNEA does not."""
    where = f"model '{_model_name(m)}'"
    for b in map(int, np.nonzero(moving)[0]):
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
    for b in map(int, np.nonzero(moving)[0]):
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
    for b in map(int, np.nonzero(moving)[0]):
        s, rel = int(body_segment[b]), body_offset[b]
        mass[s] += m.body_mass[b]
        com[s] += m.body_mass[b] * (rel[:3, :3] @ m.body_ipos[b] + rel[:3, 3])
    com /= np.maximum(mass, 1e-300)[:, None]
    for b in map(int, np.nonzero(moving)[0]):
        s, rel = int(body_segment[b]), body_offset[b]
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


# -- run time (JAX) ---------------------------------------------------------------------------
# XLA on CPU runs dots well and the gradients of broadcasts, gathers and many small slices
# (reductions, scatters, pads) badly: products of two traced arrays are dots, products with a
# model constant are unrolled multiply-adds (no gradient flows into the constant), and the tree
# structure is a constant 0/1 matrix. Dots use HIGHEST precision: exact float32 on GPUs (no TF32).

_HI = lax.Precision.HIGHEST


def _mv(a, x):
    """a: (..., 3, k), x: (..., k) -> a @ x: (..., 3)."""
    if isinstance(x, np.ndarray):
        return sum(a[..., i] * x[..., None, i] for i in range(a.shape[-1]))
    return jnp.einsum("...ik,...k->...i", a, x, precision=_HI)


def _mtv(a, x):
    """a: (..., 3, 3), x: (..., 3) -> a.T @ x."""
    return jnp.einsum("...ki,...k->...i", a, x, precision=_HI)


def _compose(a, b):
    """Rigid transforms as [R | o], (3, 4) each -> a @ b (with the implicit last row 0 0 0 1)."""
    if isinstance(b, np.ndarray):
        rot_b = sum(a[:, i, None] * b[None, i] for i in range(3))
    else:
        rot_b = jnp.matmul(a[:, :3], b, precision=_HI)
    return rot_b + a * _LAST_COLUMN


def _cross(a, b):
    """a, b: (..., 3) -> a x b."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _tree_sum(a, x):
    """a: (J, J) constant 0/1, x: (J, k) -> a @ x."""
    return jnp.matmul(a, x, precision=_HI)


def default_form() -> str:
    """The faster layout for the default JAX backend (see `make_rnea`).

    ``"scalar"`` on accelerators, and on CPU when XLA's CPU fusion emitters are switched off
    (``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``, where it is 2-5x the vector form);
    ``"vector"`` on CPU otherwise.
    """
    if jax.default_backend() != "cpu":
        return "scalar"
    flags = os.environ.get("XLA_FLAGS", "").replace("_", "-")
    return "scalar" if "--xla-cpu-use-fusion-emitters=false" in flags else "vector"


def make_rnea(robot: Any, dtype: Any = jnp.float32, form: str | None = None) -> BackendFunctions:
    """Compile `robot.mj_model` into RNEA and forward-kinematics functions.

    robot: needs `mj_model`, `joint_ids (J,)`, `site_id` (see `evojax_motion.model.robot.Robot`).
    dtype: float dtype of the constants and of the computation.
    form: how the same algorithm is laid out for XLA (equal results to rounding):
      ``"vector"``: arrays over the J segments, small dots; best on CPU, where XLA's fusion
        emitters handle the other form's gradient badly (100x slower to run, minutes to compile);
      ``"scalar"``: every component a scalar, products with model constants 0 and 1 resolved in
        Python, so after vmap the whole pass is one elementwise kernel; 3-8x faster on GPUs.
      None: `default_form()` for the default JAX backend at call time.
    """
    form = default_form() if form is None else form
    if form not in FORMS:
        raise UserError(f"form: expected one of {FORMS}, got {form!r}")
    m = robot.mj_model
    joint_ids = [int(j) for j in np.asarray(robot.joint_ids)]
    for j in joint_ids:
        if m.jnt_type[j] not in (_HINGE, _SLIDE):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise UserError(f"joints: '{name}': expected a hinge or slide joint")
    tree = _reduce_tree(m, joint_ids)
    gravity = np.zeros(3) if _disabled(m, "mjDSBL_GRAVITY") else m.opt.gravity.copy()
    site_id = int(robot.site_id)
    site_body = int(m.site_bodyid[site_id])
    site = _Site(
        segment=int(tree.body_segment[site_body]),  # -1: the site never moves
        offset=tree.body_offset[site_body]
        @ _transform(_quat_mat(m.site_quat[site_id]), m.site_pos[site_id]),
    )
    build = _vector_functions if form == "vector" else _scalar_functions
    rigid, site_pose, body_positions = build(tree, gravity, site, np.dtype(dtype))

    # Joint-space terms of qfrc_inverse: armature (in M) and minus the passive forces.
    dof_adr, qpos_adr = m.jnt_dofadr[joint_ids], m.jnt_qposadr[joint_ids]
    armature = m.dof_armature[dof_adr]
    damping = m.dof_damping[dof_adr] * (not _disabled(m, "mjDSBL_DAMPER", "mjDSBL_PASSIVE"))
    stiffness = m.jnt_stiffness[joint_ids] * (not _disabled(m, "mjDSBL_SPRING", "mjDSBL_PASSIVE"))
    passive = bool(np.any(armature) or np.any(damping) or np.any(stiffness))
    armature, damping, stiffness, qpos_spring = (
        np.asarray(x, dtype) for x in (armature, damping, stiffness, m.qpos_spring[qpos_adr])
    )

    def joint_space(q, qd, qdd, k=slice(None)):
        """The joint-space terms of joints ``k``: all (arrays ``(J,)``) or one (scalars)."""
        return armature[k] * qdd + damping[k] * qd + stiffness[k] * (q - qpos_spring[k])

    def inverse(q, qd, qdd):
        """q, qd, qdd: (J,) or sequences of J scalars -> tau (J,) = M qdd + C qd + g (+ armature,
        damping, stiffness). The scalar form is `torques`, stacked."""
        if form == "scalar":
            return jnp.stack(torques(q, qd, qdd))
        q, qd, qdd = (jnp.asarray(x, dtype) for x in (q, qd, qdd))
        tau = rigid(q, qd, qdd)
        return tau + joint_space(q, qd, qdd) if passive else tau

    def torques(q, qd, qdd):
        """The scalar form's torques unstacked: q, qd, qdd (J,) or sequences of J scalars (read
        as they are) -> a tuple of J scalars, as `inverse`. For a consumer that reduces them to
        one value per sample (the optimiser's search objective): stacked, XLA's CPU compiler
        evaluates each element of the stack on its own, the whole recursion once per joint."""
        q, qd, qdd = ([jnp.asarray(e, dtype) for e in x] for x in (q, qd, qdd))
        tau = rigid(q, qd, qdd)
        if passive:
            tau = tuple(t + joint_space(q[k], qd[k], qdd[k], k) for k, t in enumerate(tau))
        return tau

    return BackendFunctions(
        inverse=inverse,
        site_pose=site_pose,
        body_positions=body_positions,
        torques=torques if form == "scalar" else None,
    )


class _Site(NamedTuple):
    segment: int  # segment the site is attached to, -1 if it never moves
    offset: np.ndarray  # (4, 4) site frame in the segment frame (world frame if segment == -1)


def _vector_functions(tree: _Tree, gravity: np.ndarray, site: _Site, dtype: np.dtype):
    """The "vector" form: (rigid-body inverse, site_pose, body_positions)."""
    n = len(tree.order)

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
    identity = bool(np.all(tree.order == np.arange(n)))
    to_segments = c(np.eye(n)[tree.order])  # x_seg = to_segments @ x_robot
    # The base accelerates against gravity, so every segment feels it (no per-body term).
    root_acc = c(np.concatenate([np.zeros(3), -gravity]))
    site_rel = c(site.offset[:3])

    def permute(p, x):
        return x if identity else _tree_sum(p, x[:, None])[:, 0]

    def kinematics(q):
        """q: (J,) robot order -> segment frames W: (J, 3, 4) = [R | o] in the world frame."""
        angle = permute(to_segments, jnp.asarray(q, dtype)) - qpos0
        s = hinge * jnp.sin(angle) + slide * angle
        cc = hinge * (1.0 - jnp.cos(angle))
        local = c0 + s[:, None, None] * c1 + cc[:, None, None] * c2  # (J, 3, 4)
        frames: list[jnp.ndarray] = []
        for j in range(n):
            p = parents[j]
            frames.append(local[j] if p < 0 else _compose(frames[p], local[j]))
        return jnp.stack(frames)

    def rigid(q, qd, qdd):
        frames = kinematics(q)
        rot, org = frames[:, :, :3], frames[:, :, 3]
        # Joint motion subspaces S = (angular, linear at the origin), world frame: (J, 6).
        axis_w = _mv(rot, axis)
        anchor_w = _mv(rot, anchor) + org
        sw = hinge[:, None] * axis_w
        sv = hinge[:, None] * _cross(anchor_w, axis_w) + slide[:, None] * axis_w
        rate, accel = (permute(to_segments, x)[:, None] for x in (qd, qdd))
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
        return permute(to_segments.T, jnp.sum(sw * sub[:, :3] + sv * sub[:, 3:], axis=1))

    def site_pose(q):
        """q: (J,) -> site position (3,) and rotation matrix (3, 3), world frame."""
        pose = site_rel if site.segment < 0 else _compose(kinematics(q)[site.segment], site_rel)
        return jnp.asarray(pose[:, 3]), jnp.asarray(pose[:, :3])

    moving = np.nonzero(tree.body_segment >= 0)[0]
    body_seg = tree.body_segment[moving]
    body_org = c(tree.body_offset[moving, :3, 3])
    fixed_xpos = c(tree.body_offset[:, :3, 3])

    def body_positions(q):
        """q: (J,) -> (nbody, 3) world body origins (MuJoCo xpos), world body first."""
        w = kinematics(q)[body_seg]
        return jnp.asarray(fixed_xpos).at[moving].set(_mv(w[:, :, :3], body_org) + w[:, :, 3])

    return rigid, site_pose, body_positions


def _scalar_functions(tree: _Tree, gravity: np.ndarray, site: _Site, dtype: np.dtype):
    """The "scalar" form: (rigid-body inverse, site_pose, body_positions); the inverse returns a
    tuple of J torques (`make_rnea` stacks them where it returns an array).

    Same algorithm as `_vector_functions`, recursing over parents instead of using the ancestor
    matrix, on tuples of scalars: constants are Python floats (weakly typed, so they take the
    dtype of the traced values), and `_s_add`/`_s_mul` drop terms with a constant 0 or 1.
    """
    n = len(tree.order)
    local = [(_s_const(tree.c0[s]), _s_const(tree.c1[s]), _s_const(tree.c2[s])) for s in range(n)]
    axis, anchor = [_s_const(x) for x in tree.axis], [_s_const(x) for x in tree.anchor]
    com, inertia = [_s_const(x) for x in tree.com], [_s_const(x) for x in tree.inertia]
    root_acc = ((0.0, 0.0, 0.0), _s_const(-gravity))
    zero = (0.0, 0.0, 0.0)

    def frames_of(q):
        """q: (J,) -> per segment (R: 3x3, o: 3) world frame, as nested tuples of scalars."""
        q = [q[k] for k in range(n)]
        frames: list[tuple[Any, Any]] = []
        for s in range(n):
            angle = _s_sub(q[int(tree.order[s])], float(tree.qpos0[s]))
            sin: Any
            omc: Any
            if tree.hinge[s]:
                sin, omc = jnp.sin(angle), 1.0 - jnp.cos(angle)
            else:
                sin, omc = angle, 0.0
            c0, c1, c2 = local[s]
            mat = tuple(
                tuple(
                    _s_sum(c0[r][k], _s_mul(sin, c1[r][k]), _s_mul(omc, c2[r][k])) for k in range(4)
                )
                for r in range(3)
            )
            rot, org = tuple(row[:3] for row in mat), tuple(row[3] for row in mat)
            p = int(tree.parent[s])
            if p >= 0:
                rp, op = frames[p]
                rot, org = _s_mm(rp, rot), _s_vadd(_s_mv(rp, org), op)
            frames.append((rot, org))
        return frames

    def rigid(q, qd, qdd):
        frames = frames_of(q)
        qd, qdd = list(qd), list(qdd)
        motion: list[Any] = []
        vel: list[Any] = []
        acc: list[Any] = []
        wrench: list[Any] = []
        for s in range(n):
            rot, org = frames[s]
            k = int(tree.order[s])
            axis_w = _s_mv(rot, axis[s])
            if tree.hinge[s]:
                sw, sv = axis_w, _s_cross(_s_vadd(_s_mv(rot, anchor[s]), org), axis_w)
            else:
                sw, sv = zero, axis_w
            motion.append((sw, sv))
            p = int(tree.parent[s])
            (pw, pv), (pdw, pdv) = (vel[p], acc[p]) if p >= 0 else ((zero, zero), root_acc)
            xw, xv = _s_scale(qd[k], sw), _s_scale(qd[k], sv)
            w, v = _s_vadd(pw, xw), _s_vadd(pv, xv)
            # Joint axes move with the parent: d/dt (S qd) = S qdd + v_parent x (S qd).
            dw = _s_vsum(pdw, _s_scale(qdd[k], sw), _s_cross(pw, xw))
            dv = _s_vsum(pdv, _s_scale(qdd[k], sv), _s_cross(pw, xv), _s_cross(pv, xw))
            vel.append((w, v))
            acc.append((dw, dv))
            if tree.mass[s] == 0 and not np.any(tree.inertia[s]):
                wrench.append((zero, zero))
                continue
            com_w = _s_vadd(_s_mv(rot, com[s]), org)
            acom = _s_vsum(dv, _s_cross(dw, com_w), _s_cross(w, _s_vadd(v, _s_cross(w, com_w))))
            force = _s_scale(float(tree.mass[s]), acom)
            i_dw = _s_mv(rot, _s_mv(inertia[s], _s_mtv(rot, dw)))
            i_w = _s_mv(rot, _s_mv(inertia[s], _s_mtv(rot, w)))
            moment = _s_vsum(i_dw, _s_cross(w, i_w), _s_cross(com_w, force))
            wrench.append((force, moment))
        tau = [0.0] * n
        for s in reversed(range(n)):  # children come after parents: subtree sums in one sweep
            force, moment = wrench[s]
            sw, sv = motion[s]
            tau[int(tree.order[s])] = _s_add(_s_dot(sw, moment), _s_dot(sv, force))
            p = int(tree.parent[s])
            if p >= 0:
                pf, pm = wrench[p]
                wrench[p] = (_s_vadd(pf, force), _s_vadd(pm, moment))
        return tuple(jnp.asarray(t, dtype) for t in tau)

    def as_array(x):
        if isinstance(x, tuple):
            return jnp.stack([as_array(e) for e in x])
        return jnp.asarray(x, dtype)

    site_rel = _s_const(site.offset[:3])
    site_rot, site_org = tuple(row[:3] for row in site_rel), tuple(row[3] for row in site_rel)

    def site_pose(q):
        """q: (J,) -> site position (3,) and rotation matrix (3, 3), world frame."""
        if site.segment < 0:
            return as_array(site_org), as_array(site_rot)
        rot, org = frames_of(jnp.asarray(q, dtype))[site.segment]
        return as_array(_s_vadd(_s_mv(rot, site_org), org)), as_array(_s_mm(rot, site_rot))

    def body_positions(q):
        """q: (J,) -> (nbody, 3) world body origins (MuJoCo xpos), world body first."""
        frames = frames_of(jnp.asarray(q, dtype))
        rows = []
        for seg, off in zip(tree.body_segment, tree.body_offset):
            pos = _s_const(off[:3, 3])
            if seg >= 0:
                rot, org = frames[seg]
                pos = _s_vadd(_s_mv(rot, pos), org)
            rows.append(pos)
        return as_array(tuple(rows))

    # Thousands of scalar operations: traced once per program and argument dtype, not at
    # every call site (the optimiser's value, gradient and torque evaluations), then transformed
    # as one jaxpr by vmap and autodiff. XLA inlines the call; the compiled program is the same.
    return jax.jit(rigid), site_pose, body_positions


# -- scalar algebra for the "scalar" form: Python floats (model constants) and traced scalars --

_SNAP = 1e-14  # model constants this close to 0 (quaternion round-off) are exact zeros


def _s_const(x: np.ndarray):
    """A numpy vector or matrix as nested tuples of Python floats, round-off snapped to 0."""
    x = np.asarray(x, np.float64)
    if x.ndim == 1:
        return tuple(0.0 if abs(v) < _SNAP else float(v) for v in x)
    return tuple(_s_const(row) for row in x)


def _s_zero(x) -> bool:
    return isinstance(x, float) and x == 0.0


def _s_add(a, b):
    if _s_zero(a):
        return b
    if _s_zero(b):
        return a
    return a + b


def _s_sub(a, b):
    if _s_zero(b):
        return a
    if _s_zero(a):
        return -b
    return a - b


def _s_mul(a, b):
    for const, x in ((a, b), (b, a)):
        if isinstance(const, float):
            if const == 0.0:
                return 0.0
            if const == 1.0:
                return x
            if const == -1.0:
                return -x
    return a * b


def _s_sum(*terms):
    total = 0.0
    for t in terms:
        total = _s_add(total, t)
    return total


def _s_dot(u, v):
    return _s_sum(*(_s_mul(a, b) for a, b in zip(u, v)))


def _s_vadd(u, v):
    return tuple(_s_add(a, b) for a, b in zip(u, v))


def _s_vsum(*vs):
    return tuple(_s_sum(*parts) for parts in zip(*vs))


def _s_scale(s, v):
    return tuple(_s_mul(s, a) for a in v)


def _s_cross(u, v):
    return (
        _s_sub(_s_mul(u[1], v[2]), _s_mul(u[2], v[1])),
        _s_sub(_s_mul(u[2], v[0]), _s_mul(u[0], v[2])),
        _s_sub(_s_mul(u[0], v[1]), _s_mul(u[1], v[0])),
    )


def _s_mv(a, v):
    """a @ v, a given as rows."""
    return tuple(_s_dot(row, v) for row in a)


def _s_mtv(a, v):
    """a.T @ v."""
    return tuple(_s_dot(col, v) for col in zip(*a))


def _s_mm(a, b):
    cols = tuple(zip(*b))
    return tuple(tuple(_s_dot(row, col) for col in cols) for row in a)
