"""Batched trust-region solver: which steps to take and how far to trust the model.

The solver minimises B problems ``fun(z (n,), i) -> scalar`` at once, each from its own start,
with a Hessian model and a descent passed in (`solvers.base`: the Newton method is
`quasi_newton.ExactHessian` with `steps.ExactStep`, the BFGS method `quasi_newton.StructuredBFGS`
with `steps.SubspaceStep`). Each iteration also tries 1/4 and 1/16 of the model's step (three
cheap values, `STEP_SCALES`) before it gives up on a direction: a step the model overrates is
shortened in the same iteration instead of costing one. A problem stops on the Newton decrement
(``decrement <= tol * |f|``), a radius below `RADIUS_MIN`, a start that is not finite, or the
budget; it stays where it is while the others go on.

Two loops give the same iterates: a ``while`` loop that ends when the batch is done (CPU), and a
loop of fixed trip count (accelerators, where a computed loop condition waits on the host every
iteration; ``fixed_trips``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from evojax_motion.solvers.base import (
    Batch,
    Descent,
    HessianModel,
    ModelInputs,
    SolverResult,
    make_batch,
)

# Trust region in z [the problems' units; the optimisation compiler's: rad RMS of q]: a first
# step may move q by 0.3 rad.
RADIUS_INIT, RADIUS_MIN, RADIUS_MAX = 0.3, 1e-7, 1e2
STEP_SCALES = (1.0, 0.25, 0.0625)  # fractions of the trust-region step tried in one iteration
# CPU loop: shorter step lengths are evaluated for the failing problems in groups of B / this.
LAZY_GROUPS = 4
RHO_ACCEPT, RHO_BAD, RHO_GOOD = 1e-4, 0.25, 0.75  # ratio of actual to predicted decrease


class TrustRegionState(NamedTuple):
    """The solver's loop state for B problems of n coordinates.

    z: (B, n) the current point; f: (B,) its value; g: (B, n) its gradient (zero on the masked
    coordinates and where not finite); bm: (B, n, n) the model's Hessian there; radius: (B,);
    zp: (B, n) the point proposed by the last step; accept: (B,) bool, a step length passed (zp
    is to be taken); it: () int32 proposals made; iters: (B,) int32 iterations per problem;
    done, conv: (B,) bool, stopped and converged; first: () bool, no point evaluated yet;
    pending: () bool, the CPU loop has another pass to run; model, descent: the strategies'
    own states.
    """

    z: jnp.ndarray
    f: jnp.ndarray
    g: jnp.ndarray
    bm: jnp.ndarray
    radius: jnp.ndarray
    zp: jnp.ndarray
    accept: jnp.ndarray
    it: jnp.ndarray
    iters: jnp.ndarray
    done: jnp.ndarray
    conv: jnp.ndarray
    first: jnp.ndarray
    pending: jnp.ndarray
    model: Any
    descent: Any


def _value_grad(batch: Batch, z: jnp.ndarray):
    """``(f (B,), g (B, n), ok (B,))`` at ``z (B, n)``: g zero off the free coordinates and where
    f or g is not finite (``ok`` False)."""
    f, g = jax.vmap(jax.value_and_grad(batch.fun))(z, batch.idx)
    ok = jnp.isfinite(f) & jnp.all(jnp.isfinite(g), axis=1)
    return f, jnp.where(batch.free & ok[:, None], g, 0.0), ok


def _acceptable(f_s: jnp.ndarray, f: jnp.ndarray, pred: jnp.ndarray):
    """Whether trial values ``f_s`` pass against the current ``f`` and the model's predicted
    decreases ``pred`` (same shape): ``(ok, rho)``, rho the ratio of actual to predicted."""
    rho = (f - f_s) / jnp.maximum(pred, jnp.finfo(f_s.dtype).tiny)
    return jnp.isfinite(f_s) & (f_s < f) & (rho > RHO_ACCEPT), rho


def _trial_values(batch: Batch, z, p, active, f, pred_full, lazy: bool) -> jnp.ndarray:
    """``(S, B)`` objective at ``z + scale * p`` for the `STEP_SCALES`. With ``lazy`` (the CPU
    loop) the shorter lengths are evaluated only for the problems whose full step fails
    (`_acceptable`, ``pred_full`` its predicted decrease), in groups of ``B / LAZY_GROUPS``; the
    others' are +inf, never used: the longest acceptable length is taken, so the iterates are
    those of evaluating all."""
    b = z.shape[0]
    scales = jnp.asarray(STEP_SCALES, z.dtype)
    values = jax.vmap(batch.fun)
    steps = scales[:, None, None] * jnp.where(active[:, None], p, 0.0)[None]
    if not lazy:
        return jax.vmap(lambda s: values(z + s, batch.idx))(steps)
    f_full = values(z + steps[0], batch.idx)
    fail = active & ~_acceptable(f_full, f, pred_full)[0]
    cap = max(1, b // LAZY_GROUPS)
    order = jnp.nonzero(fail, size=b + cap, fill_value=b)[0]  # b: no problem (dropped)

    def group(k, rest):
        sel = jax.lax.dynamic_slice(order, (k * cap,), (cap,))
        pick = jnp.minimum(sel, b - 1)
        short = jax.vmap(lambda s: values(z[pick] + s[pick], pick))(steps[1:])
        return rest.at[:, sel].set(short, mode="drop")

    groups = (jnp.sum(fail) + cap - 1) // cap
    rest = jnp.full((len(STEP_SCALES) - 1, b), jnp.inf, z.dtype)
    rest = jax.lax.fori_loop(0, groups, group, rest)
    return jnp.concatenate([f_full[None], rest])


def _new_radius(radius, step, accept, longest, scale, rho_full) -> jnp.ndarray:
    """The next radius ``(B,)`` from the step's length ``step (B,)``, whether a length passed,
    the index of the longest that did and its fraction ``scale`` of the step, and the full
    step's ratio ``rho_full``: a fraction of the step where it failed or was shortened, half of
    it where the model was poor, twice the radius where the model was good and the step reached
    the boundary."""
    return jnp.where(
        ~accept,
        0.5 * jnp.asarray(STEP_SCALES[-1], step.dtype) * step,
        jnp.where(
            longest > 0,
            scale * step,
            jnp.where(
                rho_full < RHO_BAD,
                0.5 * step,
                jnp.where((rho_full > RHO_GOOD) & (step > 0.9 * radius), 2 * radius, radius),
            ),
        ),
    )


def _finish(batch: Batch, model: HessianModel, descent: Descent, st: TrustRegionState):
    """Evaluate the proposed point ``zp``, accept or reject it, update the model there."""
    f_p, g_p, ok_p = _value_grad(batch, st.zp)
    accept = st.first | (st.accept & ok_p)
    z = jnp.where(accept[:, None], st.zp, st.z)
    f = jnp.where(accept, f_p, st.f)
    g = jnp.where(accept[:, None], g_p, st.g)
    inputs = ModelInputs(st.z, z, st.g, g, st.bm, accept, st.first, st.it)
    bm, model_state = model.update(batch, st.model, inputs)
    return st._replace(
        z=z,
        f=f,
        g=g,
        bm=bm,
        model=model_state,
        descent=descent.query(bm, g),
        done=jnp.where(st.first, ~ok_p, st.done),
        first=jnp.asarray(False),
    )


def _propose(
    batch: Batch, descent: Descent, tol: float, lazy: bool, st: TrustRegionState, go=None
) -> TrustRegionState:
    """The next trust-region step from ``z``: ``zp``, whether a step length passed, the radius,
    the stopping tests. ``go``: () bool, False to propose nothing (the last fixed-trip pass)."""
    z, f, g, bm, radius = st.z, st.f, st.g, st.bm, st.radius
    p, _, decrement = descent.step(bm, g, radius, st.descent)
    live = ~st.done if go is None else ~st.done & go
    conv_now = live & (decrement <= tol * jnp.abs(f))
    active = live & ~conv_now
    scales = jnp.asarray(STEP_SCALES, z.dtype)
    gp = jnp.sum(g * p, axis=1)
    pbp = jnp.einsum("bi,bij,bj->b", p, bm, p)
    pred = -(scales[:, None] * gp + 0.5 * scales[:, None] ** 2 * pbp)
    f_s = _trial_values(batch, z, p, active, f, pred[0], lazy)  # (S, B)
    ok_s, rho = _acceptable(f_s, f, pred)
    longest = jnp.argmax(ok_s, axis=0)  # index of the longest acceptable length
    accept = active & jnp.any(ok_s, axis=0)
    scale = scales[longest]
    step = jnp.linalg.norm(p, axis=1)
    radius_new = _new_radius(radius, step, accept, longest, scale, rho[0])
    radius_new = jnp.where(active, jnp.minimum(radius_new, RADIUS_MAX), radius)
    return st._replace(
        zp=jnp.where(accept[:, None], z + scale[:, None] * p, z),
        accept=accept,
        radius=radius_new,
        it=st.it + 1,
        iters=st.iters + active.astype(jnp.int32),
        done=st.done | conv_now | (radius_new < RADIUS_MIN),
        conv=st.conv | conv_now,
    )


def trust_region(
    fun: Callable,
    z0: jnp.ndarray,
    free: jnp.ndarray,
    model: HessianModel,
    descent: Descent,
    max_iters: int,
    tol: float,
    fixed_trips: bool = False,
) -> SolverResult:
    """Minimise B problems ``fun(z (n,), i) -> scalar`` (problem ``i`` of the batch) from ``z0
    (B, n)``, moving only the ``free (B, n)`` coordinates, by trust-region iterations of
    ``model`` and ``descent``: at most ``max_iters`` steps each, stopping where the Newton
    decrement falls below ``tol * |f|``. ``fixed_trips``: the accelerators' loop of fixed trip
    count instead of the CPU's ``while`` loop (the same iterates). Returns `SolverResult`.

    One pass of the loop evaluates the gradient at the point the previous pass proposed (``zp``;
    the first pass: z0), completes that iteration (acceptance, model update), then proposes the
    next step. The gradient and the exact Hessian are thus traced once each: at the start and
    inside the loop, they compiled twice (paper-scale step on 2 CPU cores: 14.7-16.4 s of XLA
    compile before, 12.2-13.3 s after). The iterates are those of the textbook order.
    """
    b, n = z0.shape
    dtype = z0.dtype
    batch = make_batch(fun, free, dtype)
    state = TrustRegionState(
        z=z0,
        f=jnp.zeros((b,), dtype),
        g=jnp.zeros_like(z0),
        bm=jnp.zeros((b, n, n), dtype),
        radius=jnp.full((b,), RADIUS_INIT, dtype),
        zp=z0,
        accept=jnp.zeros((b,), bool),
        it=jnp.asarray(0, jnp.int32),
        iters=jnp.zeros((b,), jnp.int32),
        done=jnp.zeros((b,), bool),
        conv=jnp.zeros((b,), bool),
        first=jnp.asarray(True),
        pending=jnp.asarray(True),
        model=model.init(batch, z0),
        descent=descent.init(z0),
    )
    finish = functools.partial(_finish, batch, model, descent)
    propose = functools.partial(_propose, batch, descent, tol, not fixed_trips)
    if fixed_trips:
        # max_iters proposals take max_iters + 1 passes. A problem that is done changes nothing
        # in a pass (it proposes its own point, which is not accepted), nor does the last pass
        # (it proposes nothing), so the passes need no test of their own.
        def one_pass(_, st: TrustRegionState) -> TrustRegionState:
            st = finish(st)
            return propose(st, st.it < max_iters)

        st = jax.lax.fori_loop(0, max_iters + 1, one_pass, state)
    else:

        def body(st: TrustRegionState) -> TrustRegionState:
            st = finish(st)
            go_on = (st.it < max_iters) & jnp.any(~st.done)
            st = jax.lax.cond(go_on, propose, lambda s: s, st)
            return st._replace(pending=go_on)

        st = jax.lax.while_loop(lambda s: s.pending, body, state)
    return SolverResult(z=st.z, f=st.f, iterations=st.iters, converged=st.conv)
