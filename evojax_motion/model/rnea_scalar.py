"""The RNEA's "scalar" form (`model.rnea.make_rnea`, ``form="scalar"``): the same algorithm as the
vector form on tuples of scalars, model constants as Python floats, so that products with a
constant 0 or 1 vanish at trace time and after vmap the pass is one elementwise kernel."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.model.rnea_tree import Site, Tree


def scalar_functions(tree: Tree, gravity: np.ndarray, site: Site, dtype: np.dtype):
    """The "scalar" form: (rigid-body inverse, site_pose, body_positions); the inverse returns a
    tuple of J torques (`make_rnea` stacks them where it returns an array).

    Same algorithm as the vector form (`model.rnea`), recursing over parents instead of using
    the ancestor matrix, on tuples of scalars: constants are Python floats (weakly typed, so
    they take the dtype of the traced values), and `_s_add`/`_s_mul` drop terms with a constant
    0 or 1.
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
