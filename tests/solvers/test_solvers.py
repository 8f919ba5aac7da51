"""The solvers of `evojax_motion.solvers` on problems with known answers (float64): the trust-region
solver's Newton and BFGS assemblies on shifted Rosenbrock functions (both loops), the exact
trust-region step's optimality conditions, the damped BFGS update's secant condition, the
Gauss-Newton matrix of a linear residual and the optax wrappers on a quadratic."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from evojax_motion.linalg.jacobi import small_eigh
from evojax_motion.solvers.first_order import adam, lbfgs
from evojax_motion.solvers.quasi_newton import (
    ExactHessian,
    StructuredBFGS,
    bfgs_update,
    gauss_newton_matrix,
)
from evojax_motion.solvers.steps import EIG_FLOOR, ExactStep, SubspaceStep, trust_region_step
from evojax_motion.solvers.trust_region import trust_region

TOL_MIN = 1e-5  # float64: distance of the solver's end point to the known minimiser
STOP_TOL = 1e-14  # the solver's relative Newton-decrement test (|z - 1| ~ sqrt(2 tol f / 0.4))
TOL_LOOPS = 1e-12  # float64: the CPU loop vs the fixed-trip loop (the same iterates)
TOL_LINALG = 1e-10  # float64: closed forms and optimality conditions (relative)
# float64, relative to |g|: residual of (B + lam I) p = -g of the exact step off the hard case.
# Where |p| meets the radius to rounding, the step's hard-case completion still adds
# sqrt(r^2 - |p|^2) ~ sqrt(eps) r along the lowest eigenvector (measured 1.5e-8 |g|).
TOL_KKT = 1e-7
# Three starts in 3-D (where Rosenbrock's function has no other local minimum): the classic
# one, the origin, and one whose first coordinate is masked (free False) at its optimal value 1:
# the others still reach the minimiser, the masked one never moves.
STARTS = np.array([[-1.2, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, -0.5, 2.0]])
FREE = np.array([[True] * 3, [True] * 3, [False, True, True]])


def shifted_rosenbrock(z, i):
    """Rosenbrock's function of ``z (3,)`` plus 1 (so the relative stopping test ``decrement <=
    tol |f|`` can be met at the minimum ``z = 1``, f = 1); the same for every problem ``i``."""
    del i
    return 1.0 + jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


LAPACK_EIGH = functools.partial(small_eigh, jacobi=False)
JACOBI_EIGH = functools.partial(small_eigh, jacobi=True)
ASSEMBLIES = {
    "newton": lambda: (ExactHessian(), ExactStep(LAPACK_EIGH)),
    "newton_jacobi": lambda: (ExactHessian(), ExactStep(JACOBI_EIGH)),
    "newton_hessian_every_3": lambda: (ExactHessian(every=3), ExactStep(LAPACK_EIGH)),
    "bfgs": lambda: (StructuredBFGS(), SubspaceStep()),
}


@pytest.mark.shipped_level
@pytest.mark.parametrize("name", list(ASSEMBLIES))
def test_trust_region_finds_the_rosenbrock_minimum(name, x64):
    """Each assembly of the trust-region solver reaches the minimiser (1, 1, 1) from every start
    within `TOL_MIN` and says so (converged), the masked coordinate stays at its start, and the
    accelerators' fixed-trip loop ends on the CPU loop's iterates (`TOL_LOOPS`)."""
    model, descent = ASSEMBLIES[name]()
    budget = 200

    def solve(fixed):
        run = functools.partial(
            trust_region, shifted_rosenbrock, model=model, descent=descent, max_iters=budget,
            tol=STOP_TOL, fixed_trips=fixed,
        )  # fmt: skip
        return jax.jit(run)(jnp.asarray(STARTS), jnp.asarray(FREE))

    res = solve(False)
    z = np.asarray(res.z)
    np.testing.assert_allclose(z, 1.0, atol=TOL_MIN)
    np.testing.assert_allclose(np.asarray(res.f), 1.0, atol=TOL_MIN**2)
    assert np.asarray(res.converged).all()
    assert z[2, 0] == STARTS[2, 0]  # masked: exactly where it started
    iters = np.asarray(res.iterations)
    assert (iters < budget).all()
    fixed = solve(True)
    np.testing.assert_allclose(np.asarray(fixed.z), z, rtol=0, atol=TOL_LOOPS)
    np.testing.assert_array_equal(np.asarray(fixed.iterations), iters)


def test_budget_stops_the_solver_unconverged(x64):
    """With a budget of 3 iterations no start reaches the minimum: it reports 3 iterations and
    not converged, and the value it returns is its point's."""
    model, descent = ASSEMBLIES["bfgs"]()
    res = trust_region(shifted_rosenbrock, jnp.asarray(STARTS), jnp.asarray(FREE), model,
                       descent, max_iters=3, tol=1e-12)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(res.iterations), 3)
    assert not np.asarray(res.converged).any()
    values = jax.vmap(shifted_rosenbrock)(res.z, jnp.arange(3))
    np.testing.assert_allclose(np.asarray(res.f), np.asarray(values), rtol=TOL_LINALG)


def _symmetric(rng, b, n, shift):
    a = rng.standard_normal((b, n, n))
    return 0.5 * (a + np.swapaxes(a, 1, 2)) + shift * np.eye(n)


def test_exact_step_meets_the_trust_region_optimality_conditions(x64):
    """`trust_region_step` (Moré-Sorensen) on indefinite and positive definite models: ``p``
    solves ``(B + lam I) p = -g`` with ``B + lam I`` positive semidefinite, ``lam >= 0`` and
    ``lam (radius - |p|) = 0`` (Nocedal & Wright, thm. 4.1), including the hard case (g
    orthogonal to the lowest eigenvector, where ``lam`` sits `EIG_FLOOR` of the largest
    eigenvalue above ``-e_min``); its predicted decrease is the model's."""
    rng = np.random.default_rng(0)
    b, n = 6, 5
    bm = _symmetric(rng, b, n, 0.0)
    bm[:2] = _symmetric(rng, 2, n, 6.0)  # positive definite
    g = rng.standard_normal((b, n))
    v = np.linalg.eigh(bm[5])[1]
    g[5] -= (g[5] @ v[:, 0]) * v[:, 0]  # hard case: no component along the lowest eigenvector
    radius = np.array([100.0, 0.05, 0.3, 1.0, 3.0, 10.0])  # row 0: the Newton step fits
    p, pred, decrement = (
        np.asarray(x) for x in trust_region_step(*map(jnp.asarray, (bm, g, radius)))
    )
    norms = np.linalg.norm(p, axis=1)
    bp = np.einsum("bij,bj->bi", bm, p)
    lam = -np.sum((g + bp) * p, axis=1) / norms**2
    resid = np.linalg.norm(bp + lam[:, None] * p + g, axis=1)
    e_all = np.linalg.eigvalsh(bm)
    floor = 2 * EIG_FLOOR * np.abs(e_all).max(axis=1) * norms
    assert (resid[:5] <= TOL_KKT * np.linalg.norm(g[:5], axis=1)).all()
    assert resid[5] <= floor[5]
    e_min = e_all[:, 0]
    assert (lam >= -TOL_LINALG).all() and (e_min + lam >= -1e-8).all()
    inside = norms < radius * (1 - 1e-9)
    assert inside[0] and np.abs(lam[inside]).max() <= 1e-8
    np.testing.assert_allclose(norms[~inside], radius[~inside], rtol=1e-7)
    np.testing.assert_allclose(pred, -(np.sum(g * p, 1) + 0.5 * np.sum(p * bp, 1)),
                               rtol=TOL_LINALG)  # fmt: skip
    newton = np.linalg.solve(bm[:2], g[:2, :, None])[..., 0]
    np.testing.assert_allclose(decrement[:2], 0.5 * np.sum(g[:2] * newton, 1), rtol=1e-8)
    assert np.isinf(decrement[2:]).all()  # indefinite: no Newton decrement


def test_bfgs_update_meets_the_secant_condition(x64):
    """`bfgs_update`: where accepted, the model meets the secant condition ``B s = y`` where
    Powell's damping leaves ``y`` as it is and stays symmetric; elsewhere it stays. A pair with
    ``s.y < 0`` is damped and keeps the model positive definite."""
    rng = np.random.default_rng(2)
    a = rng.standard_normal((4, 5, 5))
    bm = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(5)
    s = rng.standard_normal((4, 5))
    y = np.einsum("bij,bj->bi", bm, s) + 0.1 * rng.standard_normal((4, 5))
    y[1] = -y[1]
    assert s[1] @ y[1] < 0
    accept = np.array([True, True, False, True])
    new = np.asarray(bfgs_update(*map(jnp.asarray, (bm, s, y, accept))))
    for i in (0, 3):
        np.testing.assert_allclose(new[i] @ s[i], y[i], rtol=TOL_LINALG * 1e3)
    np.testing.assert_allclose(new, np.swapaxes(new, 1, 2), atol=TOL_LINALG)
    np.testing.assert_array_equal(new[2], bm[2])
    assert np.linalg.eigvalsh(new[1]).min() > 0  # damped: still positive definite
    sbs = s[1] @ bm[1] @ s[1]
    np.testing.assert_allclose(s[1] @ new[1] @ s[1], 0.2 * sbs + 0.0, rtol=1e-8)  # s.r = 0.2 sBs


def test_gauss_newton_matrix_of_a_linear_residual(x64):
    """`gauss_newton_matrix` of ``r(z) = A z - c`` (a (2, 3) array of residuals) is ``A^T A``
    per problem, at any point."""
    rng = np.random.default_rng(9)
    a = rng.standard_normal((3, 6, 4))
    c = rng.standard_normal((3, 6))

    def residual(z, a_b, c_b):
        return (a_b @ z - c_b).reshape(2, 3)

    gn = gauss_newton_matrix(residual, jnp.asarray(rng.standard_normal((3, 4))), a, c)
    np.testing.assert_allclose(np.asarray(gn), np.swapaxes(a, 1, 2) @ a, rtol=TOL_LINALG)


def test_first_order_wrappers_on_a_quadratic(x64):
    """`lbfgs` finds the minimiser of a convex quadratic and says so; `adam` moves towards it;
    both leave masked coordinates at their start."""
    rng = np.random.default_rng(1)
    a = rng.standard_normal((2, 3, 3))
    h = a @ np.swapaxes(a, 1, 2) + np.eye(3)
    target = rng.standard_normal((2, 3))
    free = jnp.asarray([[True, True, True], [True, False, True]])
    z0 = jnp.zeros((2, 3))

    def fun(z, i):
        d = z - jnp.asarray(target)[i]
        return 0.5 * d @ jnp.asarray(h)[i] @ d

    res = lbfgs(fun, z0, free, max_iters=100, tol=1e-10)
    assert np.asarray(res.converged).all()
    np.testing.assert_allclose(np.asarray(res.z)[0], target[0], atol=TOL_MIN)
    assert float(res.z[1, 1]) == 0.0
    steps = adam(fun, z0, free, max_iters=50, learning_rate=0.05)
    start = jax.vmap(fun)(z0, jnp.arange(2))
    assert (np.asarray(steps.f) < np.asarray(start)).all()
    assert float(steps.z[1, 1]) == 0.0
