"""Which points can be targets of the online query (`generation`, steps 1-2): the learned region
and the kinematics.

A point is reachable when at least ``min_neighbours`` valid primitives of the database lie within
``BasisSettings.radius`` of it (the learned region) and the human-like IK started from the nearest
neighbour's final posture reaches it within ``reach_tolerance`` (`reach_query`; `make_reach_checker`
jits it alone, cheap). `nearest_reachable` finds a reachable point near one that is not, for the
command line's messages and ``--nearest``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import one_shot
from evojax_motion.compiler.basis import select_neighbours
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.linalg.reductions import masked_row_mean
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.ik import solve_ik
from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import EVOLVED, Database
from evojax_motion.online.limits import joint_limits_f32
from evojax_motion.settings.compiler import BasisSettings
from evojax_motion.settings.online import OnlineSettings


class Reach(NamedTuple):
    """Whether points can be targets: the learned region and the kinematics. All ``(P,)``.

    depth: ``radius - d_m`` [m], d_m the distance to the ``min_neighbours``-th nearest valid
    condition: >= 0 inside the learned region; region_gap: ``max(-depth, 0)`` [m] (inf when the
    database has too few valid entries); ik_error: the human-like IK's miss [m];
    q_final: (P, J) its posture [rad]; hand: (P, 3) where it puts the hand [m];
    natural_duration: the neighbours' mean duration [s]; n_inside: valid primitives within the
    radius; reachable: region_gap == 0 and ik_error <= ``reach_tolerance``.
    """

    depth: jnp.ndarray
    region_gap: jnp.ndarray
    ik_error: jnp.ndarray
    q_final: jnp.ndarray
    hand: jnp.ndarray
    natural_duration: jnp.ndarray
    n_inside: jnp.ndarray
    reachable: jnp.ndarray


def region_query(db: Database, points, basis_settings: BasisSettings, settings: OnlineSettings):
    """Step 1 for ``points (P, 3)``: the neighbours and the learned region, without the IK.

    Returns ``(depth, region_gap, natural_duration, n_inside, neighbours)`` (`Reach`'s fields
    of those names, ``(P,)``; the `Neighbours` the motion is built on). Pure, jittable.
    """
    q_db = jnp.asarray(db.q)
    points = jnp.asarray(points, q_db.dtype)
    cond, valid = jnp.asarray(db.condition, q_db.dtype), jnp.asarray(db.valid)
    select = functools.partial(
        select_neighbours,
        k=basis_settings.neighbours,
        radius=basis_settings.radius,
        w_pos=basis_settings.w_pos,
    )
    region = select(cond, valid, points)  # the learned region: every valid primitive counts
    nb = region
    if settings.prefer_evolved:
        evolved = select(cond, valid & (jnp.asarray(db.origin) == EVOLVED), points)
        use = evolved.n_inside >= settings.min_neighbours  # (P,)
        nb = jax.tree_util.tree_map(
            lambda e, a: jnp.where(use.reshape(use.shape + (1,) * (e.ndim - 1)), e, a),
            evolved,
            region,
        )
    # The learned region: >= min_neighbours primitives within the radius. d_m is 1-Lipschitz in
    # the point, so the gap is a lower bound of the distance to the region (exact near a cluster).
    kth = region.distance[:, settings.min_neighbours - 1] / basis_settings.w_pos
    depth = jnp.where(jnp.isfinite(kth), basis_settings.radius - kth, -jnp.inf)
    gap = jnp.maximum(-depth, 0.0)
    dur = masked_row_mean(jnp.asarray(db.duration, q_db.dtype)[nb.index], nb.mask)
    natural = jnp.where(jnp.any(nb.mask, axis=1), dur, jnp.nan)
    return depth, gap, natural, region.n_inside, nb


def final_posture(dyn: Dynamics, db: Database, points, nb, lower, upper, settings: OnlineSettings):
    """Step 2 for ``points (P, 3)`` and their neighbours ``nb``: the human-like IK from the
    nearest neighbour's final posture, pulled toward the neighbours' mean final posture
    (`model.ik.IKResult`). Pure, jittable."""
    q_db = jnp.asarray(db.q)
    final = q_db[nb.index, -1]  # (P, k, J) the neighbours' final postures
    return solve_ik(
        dyn,
        jnp.asarray(points, q_db.dtype),
        final[:, 0],
        lower,
        upper,
        q_pref=masked_row_mean(final, nb.mask),
        iters=settings.ik_iters,
        tol=settings.reach_tolerance,
    )


def reach_query(
    dyn: Dynamics,
    db: Database,
    points,
    lower,
    upper,
    basis_settings: BasisSettings,
    settings: OnlineSettings,
):
    """Steps 1-2 for ``points (P, 3)``: neighbours and the final posture. Pure, jittable.

    ``db`` needs ``q (N, T, J)``, ``duration``, ``condition``, ``valid``. Returns
    ``(Reach, Neighbours)``.
    """
    depth, gap, natural, n_inside, nb = region_query(db, points, basis_settings, settings)
    ik = final_posture(dyn, db, points, nb, lower, upper, settings)
    return reach_of(dyn, depth, gap, natural, n_inside, ik, settings), nb


def reach_of(dyn: Dynamics, depth, region_gap, natural, n_inside, ik, settings: OnlineSettings):
    """`Reach` from `region_query`'s ``(P,)`` outputs and `final_posture`'s ``ik``. Pure."""
    return Reach(
        depth=depth,
        region_gap=region_gap,
        ik_error=ik.pos_error,
        q_final=ik.q,
        hand=jax.vmap(lambda q: dyn.site_pose(q)[0])(ik.q),
        natural_duration=natural,
        n_inside=n_inside,
        reachable=(region_gap <= 0.0) & (ik.pos_error <= settings.reach_tolerance),
    )


def resolve_settings(basis_settings, settings):
    basis_settings = basis_settings or BasisSettings()
    settings = settings or OnlineSettings()
    if settings.min_neighbours > basis_settings.neighbours:
        raise UserError(
            f"online.min_neighbours: expected <= basis.neighbours ({basis_settings.neighbours}), "
            f"got {settings.min_neighbours}"
        )
    return basis_settings, settings


def make_reach_checker(
    robot: Robot,
    dyn: Dynamics,
    basis_settings: BasisSettings | None = None,
    settings: OnlineSettings | None = None,
) -> Callable:
    """Jitted ``check(db, points (P, 3)) -> Reach``: cheap (no PCA, no dynamics; compiled as
    `compile_options.ONE_SHOT`: it serves the command line's messages)."""
    basis_settings, settings = resolve_settings(basis_settings, settings)
    lower, upper = joint_limits_f32(robot)

    @functools.partial(jax.jit, compiler_options=one_shot())
    @exact_matmuls
    def check(db, points):
        return reach_query(dyn, db, points, lower, upper, basis_settings, settings)[0]

    return check


def check_points(check: Callable, db, points: np.ndarray, chunk: int) -> Reach:
    """`make_reach_checker`'s function over any number of points, in fixed-size chunks (one
    compiled shape)."""
    n = points.shape[0]
    pad = (-n) % chunk
    padded = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)]).astype(np.float32)
    parts = [jax.device_get(check(db, padded[i : i + chunk])) for i in range(0, n + pad, chunk)]
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n], *parts)


def nearest_reachable(
    check: Callable, db: Database, target, chunk: int = 64
) -> tuple[np.ndarray, float]:
    """A reachable point near ``target (3,)`` and its distance [m] (host-level, for messages and
    ``--nearest``).

    Candidates: where the IK puts the hand, and the farthest reachable point on the segment from
    the nearest reachable database condition toward the target (two rounds of ``chunk`` samples).
    Returns the candidate closest to the target (an upper bound of the true distance).
    Raises `UserError` when no database condition is reachable.
    """
    target = np.asarray(target, np.float32).reshape(3)
    cond = np.asarray(db.condition)[np.asarray(db.valid)]
    anchors = cond[check_points(check, db, cond, chunk).reachable]
    if anchors.shape[0] == 0:
        raise UserError("database: no valid primitive's condition is reachable; nothing is near")
    anchor = anchors[np.argmin(np.linalg.norm(anchors - target, axis=1))]
    lo, hi = 0.0, 1.0
    for _ in range(2):  # coarse, then fine between the last good and the first bad sample
        lam = np.linspace(lo, hi, chunk)
        pts = anchor + lam[:, None] * (target - anchor)
        ok = check_points(check, db, pts, chunk).reachable
        good = np.flatnonzero(ok)
        k = int(good.max()) if good.size else 0
        lo, hi = lam[k], lam[min(k + 1, chunk - 1)]
    best = anchor + lo * (target - anchor)
    cand = check_points(check, db, target[None], chunk)
    hand = check_points(check, db, np.asarray(cand.hand), chunk)
    if hand.reachable[0]:
        h = cand.hand[0]
        if np.linalg.norm(h - target) < np.linalg.norm(best - target):
            best = h
    return best.astype(np.float32), float(np.linalg.norm(best - target))
