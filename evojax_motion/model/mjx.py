"""MJX inverse dynamics and forward kinematics (the reference backend).

Torques for the paper's cost (Park et al. 2008, eq. 5) straight from ``mujoco.mjx.inverse``:
``qfrc_inverse = M(q) qdd + qfrc_bias(q, qd) - qfrc_passive - qfrc_constraint``, the same quantity
as C MuJoCo's ``mj_inverse``. With the shipped models (constraints disabled, no armature, damping
or stiffness) this is the rigid-body torque ``M qdd + C qd + g``. It is general (any MJCF MJX
accepts) but builds and factors the mass matrix on every call: `dynamics_rnea` is the fast path,
this one is the reference it is tested against.

`mujoco.mjx` is imported lazily (only when this backend is requested); its import may print
"Failed to import warp" on stdout, which is swallowed so CLI output stays clean.
"""

from __future__ import annotations

import contextlib
import copy
import io
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_motion.model.rnea import BackendFunctions


def _import_mjx():
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


def _cast_floats(tree, dtype):
    """Cast every floating leaf of an MJX Model/Data pytree to `dtype` (float32 or float64)."""

    def cast(x):
        if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating):
            return x.astype(dtype)
        return x

    return jax.tree.map(cast, tree)


def _without_meshes(m: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of ``m`` whose mesh geoms are spheres: the same ``qpos``, bodies, inertias and
    sites. Geoms matter for contacts only, which the dynamics leave out; MJX would otherwise
    prepare every mesh for collisions (seconds, and warnings, for a published arm's meshes)."""
    if not np.any(m.geom_type == int(mujoco.mjtGeom.mjGEOM_MESH)):
        return m
    m = copy.copy(m)
    mesh = m.geom_type == int(mujoco.mjtGeom.mjGEOM_MESH)
    m.geom_type[mesh] = int(mujoco.mjtGeom.mjGEOM_SPHERE)
    m.geom_dataid[mesh] = -1
    return m


def make_mjx(robot: Any, dtype: Any = jnp.float32) -> BackendFunctions:
    """Build MJX single-sample functions with the same signatures as `make_rnea`.

    robot: needs `mj_model`, `qpos_adr (J,)`, `dof_adr (J,)`, `site_id`.
    dtype: float32, or float64 (caller must have enabled jax x64, checked by `make_dynamics`).
    """
    mjx = _import_mjx()
    m = robot.mj_model
    model = _cast_floats(mjx.put_model(_without_meshes(m), impl="jax"), dtype)
    data0 = _cast_floats(mjx.make_data(model, impl="jax"), dtype)
    qpos_adr = np.asarray(robot.qpos_adr)
    dof_adr = np.asarray(robot.dof_adr)
    site_id = int(robot.site_id)
    qpos0 = jnp.asarray(m.qpos0, dtype)  # uncontrolled joints stay here, at rest
    zeros_v = jnp.zeros(m.nv, dtype)

    def with_state(q, qd=None, qdd=None):
        data = data0.replace(qpos=qpos0.at[qpos_adr].set(jnp.asarray(q, dtype)))
        if qd is not None:
            data = data.replace(
                qvel=zeros_v.at[dof_adr].set(jnp.asarray(qd, dtype)),
                qacc=zeros_v.at[dof_adr].set(jnp.asarray(qdd, dtype)),
            )
        return data

    def inverse(q, qd, qdd):
        """q, qd, qdd: (J,) (or sequences of J scalars) -> tau (J,), MJX qfrc_inverse of the
        controlled dofs."""
        q, qd, qdd = (jnp.asarray(x) for x in (q, qd, qdd))
        # MJX forms M and its products with matmuls: keep them out of TF32 on GPUs.
        with jax.default_matmul_precision("highest"):
            data = mjx.inverse(model, with_state(q, qd, qdd))
        return data.qfrc_inverse[dof_adr]

    def site_pose(q):
        """q: (J,) -> site position (3,) and rotation matrix (3, 3), world frame."""
        with jax.default_matmul_precision("highest"):
            data = mjx.kinematics(model, with_state(q))
        return data.site_xpos[site_id], data.site_xmat[site_id].reshape(3, 3)

    def body_positions(q):
        """q: (J,) -> (nbody, 3) world body origins (xpos)."""
        with jax.default_matmul_precision("highest"):
            data = mjx.kinematics(model, with_state(q))
        return data.xpos

    return BackendFunctions(inverse=inverse, site_pose=site_pose, body_positions=body_positions)
