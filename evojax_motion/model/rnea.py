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
from evojax_motion.model.rnea_scalar import scalar_functions
from evojax_motion.model.rnea_tree import (
    HINGE,
    SLIDE,
    Site,
    Tree,
    disabled,
    quat_mat,
    reduce_tree,
    transform,
)

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
        if m.jnt_type[j] not in (HINGE, SLIDE):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise UserError(f"joints: '{name}': expected a hinge or slide joint")
    tree = reduce_tree(m, joint_ids)
    gravity = np.zeros(3) if disabled(m, "mjDSBL_GRAVITY") else m.opt.gravity.copy()
    site_id = int(robot.site_id)
    site_body = int(m.site_bodyid[site_id])
    site = Site(
        segment=int(tree.body_segment[site_body]),  # -1: the site never moves
        offset=tree.body_offset[site_body]
        @ transform(quat_mat(m.site_quat[site_id]), m.site_pos[site_id]),
    )
    build = _vector_functions if form == "vector" else scalar_functions
    rigid, site_pose, body_positions = build(tree, gravity, site, np.dtype(dtype))

    # Joint-space terms of qfrc_inverse: armature (in M) and minus the passive forces.
    dof_adr, qpos_adr = m.jnt_dofadr[joint_ids], m.jnt_qposadr[joint_ids]
    armature = m.dof_armature[dof_adr]
    damping = m.dof_damping[dof_adr] * (not disabled(m, "mjDSBL_DAMPER", "mjDSBL_PASSIVE"))
    stiffness = m.jnt_stiffness[joint_ids] * (not disabled(m, "mjDSBL_SPRING", "mjDSBL_PASSIVE"))
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


def _vector_functions(tree: Tree, gravity: np.ndarray, site: Site, dtype: np.dtype):
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
