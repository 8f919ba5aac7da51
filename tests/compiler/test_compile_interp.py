"""Movement compiler via interpolation (eq. 1-2): exact BCs, minimum norm, held-out demos."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from evojax_motion.compiler.basis import Basis, pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import (
    MAX_PRIOR_SIGMA,
    RANK_RTOL,
    STRICT_RANK_RTOL,
    Boundary,
    basis_functions,
    coefficient_scale,
    compile_interpolation,
    trajectory,
    validate_boundary,
)
from evojax_motion.errors import UserError
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.compiler import BC_LEAK

T, J, K, C = 24, 3, 3, 6
TOL_BC_F32 = 1e-5  # rad, rad/s: BCs of a solvable system in float32
# Ill-conditioned systems (here up to cond ~1e5) need large coefficients: the BCs then hold to the
# float32 rounding of each sample's sum of terms, ``size_t = |mean_t| + sum_k |x_k f_k(t)|``, i.e.
# ROUNDING_EPS epsilons of size at the ends for q and of sum_t |d1_t| size_t / D for qd (the end
# stencil amplifies rounding by ~10 / h). The bound is max(TOL_BC_F32, that).
ROUNDING_EPS = 2.0
TOL_MIN_NORM = 1e-4  # relative: our coefficients vs numpy lstsq on the same scaled system
LOO_MEDIAN_DEG = 2.5  # deg: median RMS error reproducing held-out demonstrations (measured ~1.3)
LOO_MAX_DEG = 6.0  # deg: worst held-out demonstration


def random_basis(rng, c, t, j, k, rest_to_rest=False) -> Basis:
    """A basis of k orthonormal smooth components per joint (float32)."""
    s = np.linspace(0.0, 1.0, t)
    if rest_to_rest:  # zero end slopes: the velocity rows hold only finite-difference error
        # Degree <= 4 is differentiated exactly by the 4th-order stencils; minimum jerk (degree 5)
        # leaves ~3e-4 of the position rows at T = 24.
        funcs = [s**2 * (3 - 2 * s), 12 * (s**3 / 3 - s**4 / 4), s**3 * (10 - 15 * s + 6 * s**2)]
    else:
        funcs = [s, np.sin(np.pi * s), np.cos(2 * np.pi * s), s**3, np.sin(3 * np.pi * s)]
    funcs = np.stack(funcs)  # (M, T)
    comps = np.empty((c, k, t, j))
    for ci in range(c):
        for ji in range(j):
            mix = funcs.T @ rng.standard_normal((len(funcs), k))  # (T, k) random combinations
            qmat, _ = np.linalg.qr(mix)
            comps[ci, :, :, ji] = qmat.T
    mean = np.einsum("cjm,mt->ctj", rng.standard_normal((c, j, len(funcs))) * 0.3, funcs)
    var = rng.uniform(0.05, 2.0, (c, k, j))
    return Basis(
        mean=jnp.asarray(mean, jnp.float32),
        components=jnp.asarray(comps, jnp.float32),
        variance=jnp.asarray(var, jnp.float32),
        duration=jnp.ones(c, jnp.float32),
        n_neighbours=jnp.full(c, 10, jnp.int32),
    )


@pytest.fixture(scope="module")
def grid():
    return make_time_grid(T)


@pytest.fixture(scope="module")
def compiled(grid):
    return jax.jit(lambda b, bc: compile_interpolation(b, bc, grid, K))


@pytest.fixture(scope="module")
def compiled_strict(grid):
    """Rank decided at float32 noise level: every numerically solvable system is solved."""
    return jax.jit(lambda b, bc: compile_interpolation(b, bc, grid, K, STRICT_RANK_RTOL))


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**31 - 1),
    q_scale=st.floats(0.05, 1.0),
    v_scale=st.floats(0.0, 1.0),
    duration=st.floats(0.5, 2.0),
)
# Full rank at the default tolerance, yet coefficients ~100: a q error of 1.02e-5 rad, within the
# rounding bound (2e-5) but not within TOL_BC_F32 alone.
@example(seed=3669, q_scale=0.5, v_scale=0.5, duration=0.5)
def test_boundary_conditions_hold_when_solvable(
    compiled, compiled_strict, grid, seed, q_scale, v_scale, duration
):
    rng = np.random.default_rng(seed)
    basis = random_basis(rng, C, T, J, K)
    bc = Boundary(
        *(jnp.asarray(rng.uniform(-1, 1, (C, J)) * sc, jnp.float32)
          for sc in (q_scale, q_scale, v_scale, v_scale)),
        duration=jnp.full(C, duration, jnp.float32),
    )  # fmt: skip
    strict, default = compiled_strict(basis, bc), compiled(basis, bc)
    assume((np.asarray(strict.rank).min(axis=1) == 4).any())
    for out in (strict, default):  # each one's full-rank systems meet the bounds
        solved = np.asarray(out.rank).min(axis=1) == 4
        pos_err, pos_bound, vel_err, vel_bound = _bc_errors_and_bounds(out, basis, bc, grid)
        assert (pos_err[solved] <= pos_bound[solved]).all()
        assert (vel_err[solved] <= vel_bound[solved]).all()


def _bc_errors_and_bounds(out, basis, bc, grid):
    """``(pos_err, pos_bound, vel_err, vel_bound)``, each ``(C, J)``: the end errors of ``out``
    and max(TOL_BC_F32, the float32 rounding of its sums of terms) (see ROUNDING_EPS)."""
    q = np.asarray(out.q, np.float64)
    duration = np.asarray(bc.duration, np.float64)[:, None]
    funcs = np.asarray(basis_functions(basis, K), np.float64)  # (C, J, K+1, T)
    terms = np.abs(np.asarray(out.coeffs, np.float64))[..., None] * np.abs(funcs)
    size = np.abs(np.asarray(basis.mean, np.float64)).transpose(0, 2, 1) + terms.sum(axis=2)
    eps = ROUNDING_EPS * np.finfo(np.float32).eps
    pos_err = np.maximum(np.abs(q[:, 0] - bc.q0), np.abs(q[:, -1] - bc.qf))
    pos_bound = np.maximum(TOL_BC_F32, eps * np.maximum(size[..., 0], size[..., -1]))
    d1 = np.asarray(grid.d1, np.float64)[[0, -1]]
    vel = np.einsum("et,ctj->ecj", d1, q) / duration
    vel_err = np.maximum(np.abs(vel[0] - bc.qd0), np.abs(vel[1] - bc.qdf))
    vel_bound = eps * np.einsum("et,cjt->cje", np.abs(d1), size).max(axis=2) / duration
    return pos_err, pos_bound, vel_err, np.maximum(TOL_BC_F32, vel_bound)


def test_minimum_norm_in_degenerate_case(compiled, grid):
    rng = np.random.default_rng(1)
    basis = random_basis(rng, C, T, J, K, rest_to_rest=True)
    z = jnp.zeros((C, J), jnp.float32)
    bc = Boundary(
        q0=jnp.asarray(rng.uniform(-1, 1, (C, J)), jnp.float32),
        qf=jnp.asarray(rng.uniform(-1, 1, (C, J)), jnp.float32),
        qd0=z,
        qdf=z,
        duration=jnp.full(C, 0.8, jnp.float32),
    )
    out = compiled(basis, bc)
    assert (np.asarray(out.rank) == 2).all()  # the velocity rows carry only O(h^4) noise
    # numpy reference: the velocity rows are dropped, so the solution is the minimum-norm one of
    # the scaled position rows (lstsq with the same relative cutoff).
    funcs = np.asarray(basis_functions(basis, K), np.float64)  # (C, J, K+1, T)
    scale = np.asarray(coefficient_scale(basis, K), np.float64)
    d1 = np.asarray(grid.d1, np.float64)
    mean = np.asarray(basis.mean, np.float64)
    for c in range(C):
        for j in range(J):
            f = funcs[c, j]
            a = np.stack([f[:, 0], f[:, -1], f @ d1[0], f @ d1[-1]]) * scale[c, j]
            m = mean[c, :, j]
            b = np.array(
                [bc.q0[c, j] - m[0], bc.qf[c, j] - m[-1], -(d1[0] @ m), -(d1[-1] @ m)], np.float64
            )
            assert np.linalg.svd(a[2:], compute_uv=False)[0] < RANK_RTOL * np.linalg.norm(a[:2], 2)
            x, *_ = np.linalg.lstsq(a[:2], b[:2], rcond=RANK_RTOL)
            expect = x * scale[c, j]
            got = np.asarray(out.coeffs[c, j], np.float64)
            assert np.abs(got - expect).max() <= TOL_MIN_NORM * max(1.0, np.abs(expect).max())
    # The position BCs still hold exactly; the velocity ones up to the basis' own end slopes.
    np.testing.assert_allclose(np.asarray(out.q[:, 0]), np.asarray(bc.q0), atol=TOL_BC_F32)
    np.testing.assert_allclose(np.asarray(out.q[:, -1]), np.asarray(bc.qf), atol=TOL_BC_F32)


def test_bad_inputs_are_flagged_in_the_batch(compiled):
    rng = np.random.default_rng(2)
    basis = random_basis(rng, C, T, J, K)
    mean = np.asarray(basis.mean).copy()
    mean[1] = np.nan  # a condition without neighbours
    basis = basis._replace(mean=jnp.asarray(mean))
    q0 = rng.uniform(-1, 1, (C, J)).astype(np.float32)
    q0[2, 0] = np.nan
    z = jnp.zeros((C, J), jnp.float32)
    bc = Boundary(jnp.asarray(q0), jnp.asarray(q0 * 0.5), z, z, jnp.ones(C, jnp.float32))
    res = np.asarray(compiled(basis, bc).bc_residual)
    assert np.isnan(res[1]) and np.isnan(res[2])
    assert np.isfinite(res[[0, 3, 4, 5]]).all()


@pytest.mark.slow
def test_leave_one_out_reproduces_demonstrations():
    """Each held-out demonstration, rebuilt from its neighbours with its own BCs (rest to rest)."""
    from evojax_motion.demonstrations.synthetic import generate_demonstrations
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import load_robot
    from evojax_motion.settings.demonstrations import DemoSettings

    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot, "rnea")
    db, _ = generate_demonstrations(
        robot, dyn, DemoSettings(count=60, samples=T), jax.random.key(3)
    )
    n = 30
    q, cond, dur = jnp.asarray(db.q), jnp.asarray(db.condition), jnp.asarray(db.duration)
    held = np.arange(n)
    valid = jnp.asarray(~np.eye(q.shape[0], dtype=bool)[held])  # (n, N): all but the held-out one

    def neighbours(v, target):
        nb = select_neighbours(cond, v, target[None], 10, 0.15)
        return jax.tree_util.tree_map(lambda a: a[0], nb)

    @jax.jit  # one program (eagerly, each operation would compile on its own)
    def rebuild(valid):
        nb = jax.vmap(neighbours)(valid, cond[held])
        basis = pca_basis(q, dur, nb, K)
        z = jnp.zeros((n, q.shape[2]))
        bc = Boundary(q[held, 0], q[held, -1], z, z, dur[held])
        return nb, compile_interpolation(basis, bc, make_time_grid(T), K)

    nb, out = rebuild(valid)
    assert not ((np.asarray(nb.index) == held[:, None]) & np.asarray(nb.mask)).any()
    rms = np.degrees(np.sqrt(np.mean((np.asarray(out.q) - np.asarray(q[held])) ** 2, axis=(1, 2))))
    print(f"leave-one-out RMS error: median {np.median(rms):.2f} deg, max {rms.max():.2f} deg")
    assert np.median(rms) < LOO_MEDIAN_DEG
    assert rms.max() < LOO_MAX_DEG


def test_validate_boundary():
    z = np.zeros((2, 3))
    ok = validate_boundary(Boundary(z, z + 0.1, z, z, np.ones(2)), 3, -np.ones(3), np.ones(3))
    assert ok.q0.dtype == jnp.float32
    cases = [
        (Boundary(z[:, :2], z, z, z, np.ones(2)), r"boundary\.q0: expected shape \(2, 3\)"),
        (Boundary(z, z, z + np.nan, z, np.ones(2)), r"boundary\.qd0: expected finite"),
        (Boundary(z, z, z, z, np.array([1.0, 0.0])), r"boundary\.duration: expected durations > 0"),
        (Boundary(z, z + 2.0, z, z, np.ones(2)), r"boundary\.qf: expected joint angles within"),
    ]
    for bc, msg in cases:
        with pytest.raises(UserError, match=msg):
            validate_boundary(bc, 3, -np.ones(3), np.ones(3))


# The optimisation rule's BC solve with the two Gram passes against the one-sided Jacobi SVD
# (float32): coefficients relative to their largest, and the null spaces' projectors.
TOL_GRAM_SWITCH = 1e-5  # measured 1.2e-7 and 3.5e-7


def test_bc_solve_gives_the_same_problems_past_the_gram_switch(grid, monkeypatch):
    """`compiler.interpolation.GRAM_SVD_MIN_MATRICES`: the optimisation rule's BC solve (``leak``)
    as on
    accelerators, with `compiler.basis.small_right_svd`'s two Gram passes (threshold reached) and
    with the
    one-sided Jacobi SVD (not reached): the same ranks, free directions, coefficients and null
    spaces (their orthonormal bases may differ)."""
    import evojax_motion.compiler.basis as basis_module
    import evojax_motion.compiler.interpolation as ci

    monkeypatch.setattr(basis_module, "jacobi_backend", lambda: True)
    rng = np.random.default_rng(11)
    k = 5  # 6 functions, 4 BCs: free directions too
    basis = random_basis(rng, C, T, J, k)
    bc = Boundary(
        *(jnp.asarray(rng.uniform(-0.5, 0.5, (C, J)), jnp.float32) for _ in range(4)),
        duration=jnp.ones(C, jnp.float32),
    )
    out = {}
    for name, threshold in (("gram", 0), ("jacobi", 10**9)):
        monkeypatch.setattr(ci, "GRAM_SVD_MIN_MATRICES", threshold)
        out[name] = jax.jit(lambda b, c: ci.solve_boundary(b, c, grid, k, leak=BC_LEAK))(basis, bc)
    gram, ref = out["gram"], out["jacobi"]
    assert not np.array_equal(gram.null, ref.null)  # the two paths did run (rounding differs)
    np.testing.assert_array_equal(gram.rank, ref.rank)
    np.testing.assert_array_equal(gram.null_mask, ref.null_mask)
    assert 0 < int(np.asarray(ref.null_mask).sum()) < ref.null_mask.size  # both kinds occur
    scale = np.abs(np.asarray(ref.coeffs)).max()
    np.testing.assert_allclose(gram.coeffs, ref.coeffs, atol=TOL_GRAM_SWITCH * scale)
    for a, b in ((np.asarray(gram.null, np.float64), np.asarray(ref.null, np.float64)),):
        pa = np.einsum("cjik,cjlk->cjil", a, np.linalg.pinv(a).swapaxes(-1, -2))
        pb = np.einsum("cjik,cjlk->cjil", b, np.linalg.pinv(b).swapaxes(-1, -2))
        np.testing.assert_allclose(pa, pb, atol=TOL_GRAM_SWITCH)


def test_quintic_offsets_set_one_boundary_value_each():
    """`motion.profiles.quintic_hermite`: each of the four offsets has one end value or slope 1
    and the other three 0, and zero acceleration at both ends (float64 derivatives by jax)."""
    from evojax_motion.motion.profiles import quintic_hermite

    with jax.enable_x64(True):
        f = lambda w: jnp.stack(quintic_hermite(w))  # noqa: E731
        ends = jnp.array([0.0, 1.0], jnp.float64)
        val = np.asarray(jax.vmap(f)(ends))  # (2 ends, 4 offsets)
        slope = np.asarray(jax.vmap(jax.jacfwd(f))(ends))
        acc = np.asarray(jax.vmap(jax.jacfwd(jax.jacfwd(f)))(ends))
    np.testing.assert_allclose(np.concatenate([val, slope]), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(acc, 0.0, atol=1e-12)


TOL_MEAN_PATH = 1e-5  # rad: float32 path against its float64 reference (sizes ~1 rad)
# rad/s: its BCs in float32, the end velocities being ~1 rad samples through the one-sided end
# stencil (~50 / D at T = 24): at most 1.1e-5 measured by default and with AVX2, 1.4e-5 with SSE4.2
TOL_BC_MEAN_PATH = 3e-5


def test_a_joint_beyond_its_demonstrations_follows_their_mean_motion(compiled, grid):
    """Demonstrations that hardly vary (prior variance 1e-6: a few trials of one person) and
    BCs well away from their ends: eq. 1-2 would need weights of thousands of standard
    deviations. Those joints follow the basis' mean motion moved onto the BCs by quintic
    offsets, checked against a float64 reference (the offsets written out here, solved on the
    grid's own BC rows); the BCs hold. Joints of an ordinary basis keep eq. 1 exactly."""
    rng = np.random.default_rng(4)
    basis = random_basis(rng, C, T, J, K)
    d1 = np.asarray(grid.d1, np.float64)[[0, -1]]
    mean = np.asarray(basis.mean, np.float64)  # (C, T, J)
    dur = 0.8
    own = [mean[:, 0], mean[:, -1], *np.einsum("et,ctj->ecj", d1, mean) / dur]  # its own BCs
    near = Boundary(  # the end postures 0.02 rad off the mean's
        *(jnp.asarray(a + rng.normal(0, 0.02, a.shape) * (i < 2), jnp.float32)
          for i, a in enumerate(own)),
        duration=jnp.full(C, dur, jnp.float32),
    )  # fmt: skip
    out = compiled(basis, near)
    assert not np.asarray(out.mean_path).any()
    np.testing.assert_array_equal(out.q, trajectory(basis, out.coeffs))

    bc = Boundary(
        *(jnp.asarray(rng.uniform(-1, 1, (C, J)) * sc, jnp.float32) for sc in (0.5, 0.5, 0.0, 0.0)),
        duration=jnp.full(C, dur, jnp.float32),
    )  # fmt: skip
    tight = basis._replace(variance=jnp.full_like(basis.variance, 1e-6))
    out = compiled(tight, bc)
    size = np.abs(np.asarray(out.coeffs)) / np.asarray(coefficient_scale(tight, K))
    far = size.max(axis=2) > MAX_PRIOR_SIGMA
    assert far.all()  # the case is meant: every joint left its demonstrations
    np.testing.assert_array_equal(out.mean_path, far)
    s = np.linspace(0.0, 1.0, T)
    offsets = np.stack(
        [1 - 10 * s**3 + 15 * s**4 - 6 * s**5, 10 * s**3 - 15 * s**4 + 6 * s**5,
         s - 6 * s**3 + 8 * s**4 - 3 * s**5, -4 * s**3 + 7 * s**4 - 3 * s**5]
    )  # fmt: skip
    rows = np.concatenate([offsets[:, [0, -1]].T, d1 @ offsets.T])
    gap = np.stack(
        [np.asarray(bc.q0) - mean[:, 0], np.asarray(bc.qf) - mean[:, -1],
         dur * np.asarray(bc.qd0) - np.einsum("t,ctj->cj", d1[0], mean),
         dur * np.asarray(bc.qdf) - np.einsum("t,ctj->cj", d1[1], mean)]
    )  # fmt: skip  # (4, C, J)
    expect = mean + np.einsum("ecj,et->ctj", np.linalg.solve(rows, gap.reshape(4, -1)).reshape(
        gap.shape), offsets)  # fmt: skip
    np.testing.assert_allclose(out.q, expect, atol=TOL_MEAN_PATH)
    assert (np.asarray(out.bc_residual) <= TOL_BC_MEAN_PATH).all()
