"""First-order solvers from optax, batched like the trust-region solver (`solvers.base`).

- `adam`: plain ``optax.adam`` for a fixed number of steps (the paper's projected-gradient
  baseline, kept for comparison);
- `lbfgs`: ``optax.lbfgs`` with its zoom line search, stopped on the gradient norm.

Each problem runs its own optax loop under ``vmap``. Masked coordinates get a zero gradient, so
they stay at their start.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax

from evojax_motion.solvers.base import SolverResult


def adam(
    fun: Callable, z0: jnp.ndarray, free: jnp.ndarray, max_iters: int, learning_rate: float
) -> SolverResult:
    """``max_iters`` steps of ``optax.adam(learning_rate)`` on B problems ``fun(z (n,), i) ->
    scalar`` from ``z0 (B, n)``, moving the ``free (B, n)`` coordinates (non-finite gradient
    entries count as zero). Never ``converged``."""
    opt = optax.adam(learning_rate)
    b = z0.shape[0]

    def one(z0, free, i):
        def body(_, carry):
            z, state = carry
            g = jax.grad(fun)(z, i)
            g = jnp.where(free & jnp.isfinite(g), g, 0.0)
            updates, state = opt.update(g, state, z)
            return optax.apply_updates(z, updates), state

        z, _ = jax.lax.fori_loop(0, max_iters, body, (z0, opt.init(z0)))
        return SolverResult(z, fun(z, i), jnp.asarray(max_iters, jnp.int32), jnp.asarray(False))

    return jax.vmap(one)(z0, free, jnp.arange(b))


def lbfgs(
    fun: Callable, z0: jnp.ndarray, free: jnp.ndarray, max_iters: int, tol: float
) -> SolverResult:
    """``optax.lbfgs`` with its zoom line search on B problems ``fun(z (n,), i) -> scalar`` from
    ``z0 (B, n)``, moving the ``free (B, n)`` coordinates; stops on the gradient norm (``<= tol
    * (1 + |f|)``, converged), a value that is not finite, or ``max_iters``."""
    opt = optax.lbfgs()
    b = z0.shape[0]

    def one(z0, free, i):
        def masked(z):
            # Masked coordinates do not move: the same function with a zero gradient there.
            return fun(jnp.where(free, z, 0.0), i)

        value_and_grad = optax.value_and_grad_from_state(masked)

        def cond(carry):
            _, _, it, done = carry
            return (~done) & (it < max_iters)

        def body(carry):
            z, state, it, _ = carry
            f, g = value_and_grad(z, state=state)
            updates, state = opt.update(g, state, z, value=f, grad=g, value_fn=masked)
            z = optax.apply_updates(z, updates)
            gnorm = optax.tree.norm(optax.tree.get(state, "grad"))
            done = (gnorm <= tol * (1.0 + jnp.abs(f))) | ~jnp.isfinite(f)
            return z, state, it + 1, done

        init = (z0, opt.init(z0), jnp.asarray(0, jnp.int32), jnp.asarray(False))
        z, _, it, done = jax.lax.while_loop(cond, body, init)
        return SolverResult(z, masked(z), it, done)

    return jax.vmap(one)(z0, free, jnp.arange(b))
