"""Batched inverse kinematics of the hand position: damped least squares + a null-space posture.

The paper turns motion-capture markers into joint trajectories with an optimisation-based IK
solver (sec. 2, after Lim et al. 2005); here IK turns synthetic hand paths into demonstrations
(`demos`) and target hand positions into final postures (`conditions`, online generation).

One iteration for one sample, with ``e = target - p(q)`` and ``Jac = dp/dq (3, J)`` (``jax.jacfwd``
of ``Dynamics.site_pose``):

    dq = Jac^T (Jac Jac^T + lambda^2 I)^-1 e                     damped least squares (Wampler 1986)
       + (I - Jac^T (Jac Jac^T + mu I)^-1 Jac) W (q_pref - q)    null-space term (Nakamura 1987)

with ``lambda^2 = damping^2 + |e|^2 / 2``: the error-dependent Levenberg-Marquardt damping of
Sugihara (2011) keeps steps bounded near singularities and makes unreachable targets converge to
the nearest reachable point, while near a solution it vanishes (fast convergence). The null-space
term, a secondary objective that leaves the hand in place to first order, pulls the redundant
joints toward a preferred (comfortable) posture ``q_pref`` with per-joint weights ``W``
(``w_pref``). Joint limits: the
joints whose step would leave ``[lower, upper]`` are clamped onto their limit and removed from the
Jacobian, and the free joints re-solve the remaining error (one pass of the clamping loop of
Baerlocher & Boulic 2004); a final clip keeps every iterate inside the box. Infinite limits (a
continuous joint) are never reached, so such a joint is never clamped and its angle is not
wrapped. Steps are scaled to at most ``max_step`` rad (a trust region).

Pure single-sample code inside: ``vmap`` over the batch, ``lax.fori_loop`` over a fixed iteration
count (deterministic, jit-friendly), ``lax.scan`` over a path's samples with warm starts.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics

DEFAULT_TOL = 1e-4  # [m] a solution "converged" when the hand is this close to its target
NULL_SPACE_MU = 1e-6  # [m^2] tiny regulariser of the null-space projector (keeps it a projector)
PIVOT_FLOOR = 1e-12  # [m^2] smallest squared Cholesky pivot of the 3x3 solves


class IKResult(NamedTuple):
    """Solutions. ``q (..., J)`` [rad], ``pos_error (...)`` [m], ``converged (...)`` bool.

    For ``solve_ik_trajectory`` ``q`` is ``(B, T, J)``, ``pos_error`` ``(B, T)`` and ``converged``
    ``(B,)`` (every sample of the path within ``tol``).
    """

    q: jnp.ndarray
    pos_error: jnp.ndarray
    converged: jnp.ndarray


def _hand_position_and_jacobian(dyn: Dynamics, q):
    """``p (3,)`` and ``dp/dq (3, J)`` of the end-effector site in one forward-mode pass."""

    def pos(q):
        p = dyn.site_pose(q)[0]
        return p, p

    jac, p = jax.jacfwd(pos, has_aux=True)(q)
    return p, jac


def _solve_spd3(a, b):
    """``a^-1 b`` for a symmetric positive definite ``a (3, 3)``, ``b (3,)``, by a closed-form
    Cholesky factorisation: elementwise code that XLA fuses (a batched LAPACK call per 3x3 system
    costs more than the arithmetic). Pivots are floored at ``PIVOT_FLOOR``: rounding must not
    turn a nearly singular (regularised) system into a NaN."""

    def root(x):
        return jnp.sqrt(jnp.maximum(x, PIVOT_FLOOR))

    l00 = root(a[0, 0])
    l10 = a[1, 0] / l00
    l20 = a[2, 0] / l00
    l11 = root(a[1, 1] - l10**2)
    l21 = (a[2, 1] - l20 * l10) / l11
    l22 = root(a[2, 2] - l20**2 - l21**2)
    y0 = b[0] / l00  # L y = b
    y1 = (b[1] - l10 * y0) / l11
    y2 = (b[2] - l20 * y0 - l21 * y1) / l22
    x2 = y2 / l22  # L^T x = y
    x1 = (y1 - l21 * x2) / l11
    x0 = (y0 - l10 * x1 - l20 * x2) / l00
    return jnp.stack([x0, x1, x2])


def _gram(jf):
    """``jf @ jf.T`` (3, 3), elementwise: tiny matmuls fuse instead of calling a GEMM."""
    return jnp.sum(jf[:, None, :] * jf[None, :, :], axis=-1)


def _task_step(jac, e, free, damping):
    """Damped least-squares step ``(J,)`` of the ``free`` (J,) {0,1} joints toward error ``e``."""
    jf = jac * free[None, :]
    # error-dependent damping (Sugihara 2011): fast near a solution, stable far from one
    lam2 = damping**2 + 0.5 * jnp.sum(e**2)
    y = _solve_spd3(_gram(jf) + lam2 * jnp.eye(3, dtype=jac.dtype), e)
    return jnp.sum(jf * y[:, None], axis=0)


def _null_step(jac, free, g):
    """``g`` projected on the null space of the ``free`` joints' Jacobian (other joints still).

    A near-exact pseudo-inverse (``mu``, not the task damping): the pull must not move the hand.
    """
    jf, gf = jac * free[None, :], g * free
    eye = jnp.eye(3, dtype=jac.dtype)
    y = _solve_spd3(_gram(jf) + NULL_SPACE_MU * eye, jnp.sum(jf * gf[None, :], axis=1))
    return gf - jnp.sum(jf * y[:, None], axis=0)


def _ik_iteration(dyn, q, target, q_pref, w_pref, lower, upper, damping, max_step):
    """One clamped damped-least-squares iteration for one sample. ``q (J,)`` -> ``q (J,)``."""
    p, jac = _hand_position_and_jacobian(dyn, q)
    e = target - p

    def outside(x):
        return (x < lower) | (x > upper)

    # Task first: joints the step would push across a limit go onto it and out of the Jacobian;
    # the others re-solve the error that remains after the clamped joints' motion.
    dq = _task_step(jac, e, jnp.ones_like(q), damping)
    blocked = outside(q + dq)
    dq_clamped = jnp.where(blocked, jnp.clip(q + dq, lower, upper) - q, 0.0)
    free = jnp.where(blocked, 0.0, 1.0)
    dq_task = dq_clamped + _task_step(jac, e - jnp.sum(jac * dq_clamped, axis=1), free, damping)
    # Then the preference, among the joints it would not push across a limit: a preference can
    # stop at a limit, but never take joints away from the task.
    g = w_pref * (q_pref - q)
    dq_null = _null_step(jac, free, g)
    free = jnp.where(outside(q + dq_task + dq_null), 0.0, free)
    dq = dq_task + _null_step(jac, free, g)
    # trust region: large steps far from the solution overshoot the linearisation
    scale = jnp.minimum(1.0, max_step / (jnp.max(jnp.abs(dq)) + 1e-12))
    return jnp.clip(q + scale * dq, lower, upper)


def _solve_one(dyn, target, q_init, q_pref, w_pref, lower, upper, iters, damping, max_step):
    """``iters`` iterations for one sample. -> ``(q (J,), pos_error ())``."""

    # A preference outside the box would keep pulling its joints onto their limits, where the
    # clamp takes them out of the task: the feasible preference is the nearest point inside.
    q_pref = jnp.clip(q_pref, lower, upper)

    def body(_, q):
        return _ik_iteration(dyn, q, target, q_pref, w_pref, lower, upper, damping, max_step)

    q = jax.lax.fori_loop(0, iters, body, jnp.clip(q_init, lower, upper))
    return q, jnp.linalg.norm(target - dyn.site_pose(q)[0])


def _broadcast(x, dtype, shape):
    return jnp.broadcast_to(jnp.asarray(x, dtype), shape)


@functools.partial(jax.jit, static_argnames=("dyn", "iters", "damping", "max_step", "tol"))
@exact_matmuls
def solve_ik(
    dyn: Dynamics,
    targets,
    q_init,
    lower,
    upper,
    *,
    q_pref=None,
    w_pref=0.5,
    iters: int = 50,
    damping: float = 1e-2,
    max_step: float = 0.3,
    tol: float = DEFAULT_TOL,
) -> IKResult:
    """Joint angles that put the site at ``targets``, one independent problem per row.

    Args:
      dyn: the robot's ``Dynamics`` (its ``site_pose`` is the forward kinematics).
      targets: ``(B, 3)`` site positions [m].
      q_init: ``(B, J)`` starting postures (clipped into the limits).
      lower, upper: ``(J,)`` or ``(B, J)`` joint limits [rad]; every iterate stays inside. A
        continuous joint has ``-inf``/``+inf`` (`Robot.lower`/`upper`): it is never clamped.
      q_pref: ``(J,)`` or ``(B, J)`` preferred posture of the null-space term (default ``q_init``:
        the solution stays near the start in the redundant directions).
      w_pref: scalar, ``(J,)`` or ``(B, J)`` null-space pull per iteration, each in (0, 1]. At
        convergence the posture minimises ``sum_j w_j (q_j - q_pref_j)^2`` among those that reach
        the target (locally); larger weights also converge faster.
      iters: fixed iteration count. damping: lambda [m] of the damped least squares.
      max_step: largest joint step per iteration [rad].
      tol: ``converged = pos_error <= tol`` [m]; an unreachable target ends with ``pos_error`` > tol
        (the hand as close as the limits allow).

    Returns ``IKResult(q (B, J), pos_error (B,), converged (B,))``.
    """
    q_init = jnp.asarray(q_init)
    dtype, shape = q_init.dtype, q_init.shape
    q_pref = q_init if q_pref is None else _broadcast(q_pref, dtype, shape)
    w_pref = _broadcast(w_pref, dtype, shape)
    lower, upper = _broadcast(lower, dtype, shape), _broadcast(upper, dtype, shape)

    def one(target, q0, qp, wp, lo, hi):
        return _solve_one(dyn, target, q0, qp, wp, lo, hi, iters, damping, max_step)

    q, err = jax.vmap(one)(jnp.asarray(targets, dtype), q_init, q_pref, w_pref, lower, upper)
    return IKResult(q, err, err <= tol)


@functools.partial(jax.jit, static_argnames=("dyn", "iters", "damping", "max_step", "tol"))
@exact_matmuls
def solve_ik_trajectory(
    dyn: Dynamics,
    hand_path,
    q_start,
    lower,
    upper,
    *,
    q_pref=None,
    w_pref=0.5,
    iters: int = 10,
    damping: float = 1e-2,
    max_step: float = 0.3,
    tol: float = DEFAULT_TOL,
) -> IKResult:
    """Joint trajectories along hand paths: every sample solved, warm-started from the previous one.

    A scan over the T samples (vmap over the B paths) starts sample t's iterations at sample t-1's
    solution, so consecutive postures stay on the same branch and joint trajectories are smooth.

    Args:
      hand_path: ``(B, T, 3)`` site positions [m].
      q_start: ``(B, J)`` posture before the first sample (usually ``p(q_start) = path[:, 0]``).
      q_pref: ``(J,)``, ``(B, J)`` or ``(B, T, J)`` (a time-varying preference) preferred postures;
        default ``q_start``.
      w_pref: scalar, ``(J,)`` or ``(B, J)`` null-space weights (see `solve_ik`).
      iters: iterations per sample (warm starts make a few enough). Others: see `solve_ik`.

    Returns ``IKResult(q (B, T, J), pos_error (B, T), converged (B,))``; ``converged`` when every
    sample of the path is within ``tol``.
    """
    q_start = jnp.asarray(q_start)
    dtype, (b, j) = q_start.dtype, q_start.shape
    t = hand_path.shape[1]
    q_pref = q_start if q_pref is None else jnp.asarray(q_pref, dtype)
    if q_pref.ndim == 2:  # (B, J): the same preference along each path
        q_pref = q_pref[:, None, :]
    q_pref = _broadcast(q_pref, dtype, (b, t, j))
    w_pref = _broadcast(w_pref, dtype, (b, j))
    lower, upper = jnp.asarray(lower, dtype), jnp.asarray(upper, dtype)

    def one_path(path, q0, prefs, wp):
        def step(q, inputs):
            target, qp = inputs
            q, err = _solve_one(dyn, target, q, qp, wp, lower, upper, iters, damping, max_step)
            return q, (q, err)

        _, (qs, errs) = jax.lax.scan(step, q0, (path, prefs))
        return qs, errs

    q, err = jax.vmap(one_path)(jnp.asarray(hand_path, dtype), q_start, q_pref, w_pref)
    return IKResult(q, err, jnp.all(err <= tol, axis=-1))
