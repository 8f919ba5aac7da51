"""Online generation (online/generation.py, reach.py, limits.py; cli/online.py): the query
against the compilers it chains, the joint-limit projection (property test), reachability, the
CLI's files and errors."""

from __future__ import annotations

import argparse
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from online_support import (
    BASIS,
    SETTINGS,
    cli_session,
    mj_inverse_torques,
    online_env,
    prepare_cli,
    query,
    reach_checker,
    run_cli,
    save_env_database,
)

from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import Boundary, basis_functions, compile_interpolation
from evojax_motion.errors import UserError
from evojax_motion.linalg.cholesky import spd_solve
from evojax_motion.online.generation import make_online_generator, to_numpy
from evojax_motion.online.limits import enforce_limits, minimum_jerk
from evojax_motion.online.reach import nearest_reachable
from evojax_motion.settings.online import OnlineSettings

TOL_HAND = 1e-3  # m: final hand error of a reachable target (the benchmark asks <= 5 mm p95)
TOL_Q = 1e-5  # rad: float32 agreement of two evaluations of the same trajectory
TOL_BC_Q = 1e-5  # rad: position boundary conditions after the limit projection
TOL_BC_QD = 0.02  # rad/s: end velocities may grow by the dropped (degenerate) velocity rows
TOL_TAU = 2e-3  # N m: float32 RNEA vs float64 mj_inverse on |tau| up to ~30 N m
TOL_SPD = 1e-5  # relative: unrolled Cholesky vs numpy
TOL_SPAN = 1e-4  # rad: least-squares residual of a trajectory in its PCA span (float32 data)
TOL_PROJ = 2e-3  # rad: our penalty projection's step vs SciPy's exact QP step (penalty slack)
TOL_JACOBI_Q = 1e-5  # rad: accelerator path (Jacobi PCA and BC solves) vs LAPACK, same query
TOL_JACOBI_COST = 1e-3  # relative: their eq. 5 costs (qdd amplifies the 1e-7 rad differences)
# the CPU fast path (scalar RNEA, XLA fusion emitters off) vs the default program, same query:
TOL_FAST_Q = 1e-5  # rad (float32 rounding of differently fused IK iterations)
TOL_FAST_COST = 1e-3  # relative
# the command line's generator through its kept (exported) trace vs the plain jit, same query:
# XLA fuses the exported program a little otherwise. Measured 7.5e-8 rad and 2.4e-4 N m (|tau| up
# to 9.8 N m) by default, 0 under --xla_cpu_max_isa=SSE4_2 (no FMA); about 10x that:
TOL_KEPT_Q = 1e-6  # rad
TOL_KEPT_TAU = 2e-3  # N m


@pytest.fixture(scope="module")
def env():
    return online_env()


@pytest.fixture(scope="module")
def near(env):
    """Eight targets 1-2 cm from database conditions, and their query result."""
    rng = np.random.default_rng(1)
    targets = env.db.condition[:8] + rng.normal(0, 0.01, (8, 3)).astype(np.float32)
    return targets, query(env, targets)


def test_settings_validation():
    with pytest.raises(ValueError, match=r"^limit_components: expected"):
        OnlineSettings(n_components=3, limit_components=2)
    with pytest.raises(ValueError, match=r"^reach_tolerance: expected"):
        OnlineSettings(reach_tolerance=0.0)


def test_accelerator_path_matches_lapack(env, near, monkeypatch):
    """The elementwise Jacobi PCA and BC solves (what GPUs run) give the LAPACK path's motions,
    with the projection on (limits narrowed so that every motion needs it) and off."""
    import evojax_motion.compiler.basis as basis_module
    import evojax_motion.compiler.interpolation as interp_module
    from evojax_motion.linalg.precision import exact_matmuls
    from evojax_motion.online.generation import online_query, to_numpy
    from evojax_motion.online.limits import joint_limits_f32

    targets, _ = near
    lower, upper = joint_limits_f32(env.robot)
    c = targets.shape[0]
    rest = np.tile(np.asarray(env.robot.rest, np.float32), (c, 1))
    args = (env.db_device, targets, np.full(c, np.nan, np.float32), rest)

    def query(lo, hi, *a):  # the limits as arguments: one compile per path serves both
        return online_query(env.dyn, env.grid, lo, hi, BASIS, SETTINGS, *a)

    compiled = {}
    for jacobi in (False, True):
        for module in (basis_module, interp_module):
            monkeypatch.setattr(module, "jacobi_backend", lambda j=jacobi: j)
        compiled[jacobi] = jax.jit(exact_matmuls(query)).lower(lower, upper, *args).compile()
    for shrink in (1.0, 0.6):
        mid = 0.5 * (lower + upper)
        lo, hi = mid + shrink * (lower - mid), mid + shrink * (upper - mid)
        ref, new = (to_numpy(compiled[jacobi](lo, hi, *args)) for jacobi in (False, True))
        assert shrink == 1.0 or ref.limit_excess.min() > 0  # the projection ran
        np.testing.assert_array_equal(ref.ok, new.ok)
        np.testing.assert_allclose(new.q, ref.q, atol=TOL_JACOBI_Q)
        np.testing.assert_allclose(new.cost, ref.cost, rtol=TOL_JACOBI_COST)
        assert ((new.q >= lo) & (new.q <= hi)).all()


def test_cpu_fast_path_matches_the_default_program(env, near):
    """The generator users get (on CPU: `model.dynamics.unfused_cpu_program`) answers like the one
    compiled with XLA's default options and the default RNEA layout."""
    targets, ref = near
    plain = make_online_generator(env.robot, env.dyn, env.grid, BASIS, SETTINGS, fast_path=False)
    c = targets.shape[0]
    rest = np.tile(np.asarray(env.robot.rest, np.float32), (c, 1))
    got = to_numpy(plain(env.db_device, targets, np.full(c, np.nan, np.float32), rest))
    np.testing.assert_array_equal(got.ok, ref.ok)
    np.testing.assert_allclose(got.q, ref.q, atol=TOL_FAST_Q)
    np.testing.assert_allclose(got.tau, ref.tau, atol=TOL_TAU)
    np.testing.assert_allclose(got.cost, ref.cost, rtol=TOL_FAST_COST)


def test_one_shot_generator_runs_the_whole_query_only_for_targets_that_need_a_correction(
    env, near, monkeypatch
):
    """The command line's generator (``one_shot``) runs the query without its two corrections
    (joint-limit projection, time scaling) first. Where no target needs one it returns those
    motions, the whole query's (to float32 fusion), without tracing the whole query; where one
    does (a 1 ms motion, stretched) it returns the whole query's. The flag it decides on is set
    where eq. 1 leaves the joint limits (narrowed so that every motion does)."""
    from evojax_motion.linalg.precision import exact_matmuls
    from evojax_motion.online import generation
    from evojax_motion.online.limits import joint_limits_f32

    traced = []  # traces of the whole query
    query = generation.online_query

    def spy(*a, corrections=True):
        traced.extend([1] if corrections else [])
        return query(*a, corrections=corrections)

    monkeypatch.setattr(generation, "online_query", spy)
    gen = make_online_generator(env.robot, env.dyn, env.grid, BASIS, SETTINGS, one_shot=True)
    targets = near[0]
    c = targets.shape[0]
    rest = np.tile(np.asarray(env.robot.rest, np.float32), (c, 1))
    for duration in (np.nan, 0.001):
        args = (env.db_device, targets, np.full(c, duration, np.float32), rest)
        got = to_numpy(gen(*args))
        assert len(traced) == (0 if np.isnan(duration) else 1)
        ref = to_numpy(env.generate(*args))
        assert np.isnan(duration) or (ref.duration > 0.1).all()  # stretched
        np.testing.assert_array_equal(got.corrected, ~np.isnan(duration))
        np.testing.assert_array_equal(got.ok, ref.ok)
        np.testing.assert_allclose(got.duration, ref.duration, rtol=TOL_FAST_COST)
        np.testing.assert_allclose(got.q, ref.q, atol=TOL_FAST_Q)
        np.testing.assert_allclose(got.cost, ref.cost, rtol=TOL_FAST_COST)

    def uncorrected(lo, hi, *a):
        return query(env.dyn, env.grid, lo, hi, BASIS, SETTINGS, *a, corrections=False)

    lower, upper = joint_limits_f32(env.robot)
    mid = 0.5 * (lower + upper)
    run = jax.jit(exact_matmuls(uncorrected))
    args = (env.db_device, targets, np.full(c, np.nan, np.float32), rest)
    for shrink in (1.0, 0.6):
        res = to_numpy(run(mid + shrink * (lower - mid), mid + shrink * (upper - mid), *args))
        np.testing.assert_array_equal(res.corrected, res.limit_excess > 0)
        assert res.corrected.all() == (shrink < 1.0)


def test_query_reaches_target_within_limits_and_bcs(env, near):
    targets, r = near
    assert r.ok.all() and r.reachable.all()
    assert r.hand_error.max() <= TOL_HAND
    lo, hi = env.robot.lower, env.robot.upper
    assert ((r.q >= lo) & (r.q <= hi)).all()
    np.testing.assert_allclose(
        r.q[:, 0], np.broadcast_to(env.robot.rest, r.q[:, 0].shape), atol=TOL_Q
    )
    np.testing.assert_allclose(r.q[:, -1], r.q_final, atol=TOL_Q)
    # default duration: the neighbours' mean; t runs over [0, D] on the grid
    nb = select_neighbours(
        jnp.asarray(env.db.condition), jnp.asarray(env.db.valid), jnp.asarray(targets), 8, 0.15
    )
    dur = np.asarray(env.db.duration)[np.asarray(nb.index)].mean(axis=1)
    np.testing.assert_allclose(r.duration, dur, rtol=1e-6)
    np.testing.assert_allclose(r.t, env.grid.s[None] * r.duration[:, None], rtol=1e-6)


def test_query_is_eq1_interpolation_when_inside(env, near):
    """Inside the limits the online motion is exactly the movement compiler via interpolation
    (eq. 1-2, three components) on the neighbours' basis with the online BCs."""
    targets, r = near
    assert (r.limit_excess == 0).all()
    q = _eq1(env, targets, r.q_final, r.duration)[1]
    np.testing.assert_allclose(r.q, np.asarray(q), atol=TOL_Q)


def _eq1(env, targets, q_final, duration):
    """Reference chain, jitted once (op-by-op dispatch compiles every op): neighbours, 4-component
    PCA, rest-to-rest BCs, eq. 1 with 3 components. Returns ``(basis, q, boundary)``."""

    @jax.jit
    def chain(targets, q_final, duration):
        nb = select_neighbours(env.db_device.condition, env.db_device.valid, targets, 8, 0.15)
        basis = pca_basis(env.db_device.q, env.db_device.duration, nb, 4)
        zeros = jnp.zeros_like(q_final)
        rest = jnp.broadcast_to(jnp.asarray(env.robot.rest, jnp.float32), zeros.shape)
        bc = Boundary(rest, q_final, zeros, zeros, duration)
        return basis, compile_interpolation(basis, bc, env.grid, n_components=3).q, bc

    return chain(jnp.asarray(targets), jnp.asarray(q_final), jnp.asarray(duration))


def test_torques_match_mj_inverse(env, near):
    _, r = near
    for i in (0, 5):
        ref = mj_inverse_torques(env.robot, r.q[i], r.qd[i], r.qdd[i])
        np.testing.assert_allclose(r.tau[i], ref, atol=TOL_TAU)


def test_duration_and_start_posture_are_honoured(env, near):
    targets, _ = near
    start = np.clip(env.robot.rest + 0.1, env.robot.lower, env.robot.upper)
    r = query(env, targets, duration=0.9, q_start=start)
    assert r.ok.all()
    np.testing.assert_allclose(r.duration, 0.9, rtol=1e-6)
    np.testing.assert_allclose(r.q[:, 0], np.broadcast_to(start, r.q[:, 0].shape), atol=TOL_Q)
    compiled = env.generate._cache_size()
    query(env, targets, duration=0.7, q_start=start)
    assert env.generate._cache_size() == compiled  # new values, same shapes: no recompilation


def test_neighbours_prefer_evolved_primitives(env, near):
    """With enough evolved (robot-optimised) primitives inside the radius, the basis is built
    from them alone: the motion equals the one from a database holding only those; the learned
    region (n_inside, the gap) still counts every valid primitive."""
    from evojax_motion.motion.database import EVOLVED
    from evojax_motion.online.generation import to_numpy

    targets, r_all = near
    origin = np.where(np.arange(len(env.db.valid)) % 2 == 0, EVOLVED, env.db.origin)
    mixed = env.db._replace(origin=origin.astype(np.int32))
    only = mixed._replace(valid=env.db.valid & (origin == EVOLVED))
    rest = np.tile(np.asarray(env.robot.rest, np.float32), (len(targets), 1))
    dur = np.full(len(targets), np.nan, np.float32)
    r_mixed = to_numpy(env.generate(jax.tree_util.tree_map(jnp.asarray, mixed), targets, dur, rest))
    r_only = to_numpy(env.generate(jax.tree_util.tree_map(jnp.asarray, only), targets, dur, rest))
    enough = r_only.n_inside >= SETTINGS.min_neighbours
    assert enough.sum() >= 4
    np.testing.assert_allclose(r_mixed.q[enough], r_only.q[enough], atol=TOL_Q)
    np.testing.assert_array_equal(r_mixed.n_inside, r_all.n_inside)
    assert not np.allclose(r_mixed.q[enough], r_all.q[enough], atol=1e-3)


def test_user_errors(env):
    with pytest.raises(UserError, match="duration: expected a number > 0"):
        query(env, env.db.condition[:1], duration=-1.0)
    with pytest.raises(UserError, match="start posture: joint 'shoulder_pitch'"):
        bad = np.array(env.robot.rest)
        bad[1] = env.robot.upper[1] + 0.5
        query(env, env.db.condition[:1], q_start=bad)
    with pytest.raises(UserError, match="target: expected finite"):
        query(env, [[np.nan, 0.0, 1.0]])


def test_unreachable_target_is_flagged_and_nearest_point_is_reachable(env):
    far = np.array([[1.5, -0.3, 1.4]], np.float32)
    r = query(env, far)
    assert not r.reachable[0] and not r.ok[0]
    assert r.region_gap[0] > 0.5  # metres outside the learned region
    point, dist = nearest_reachable(reach_checker(), env.db_device, far[0])
    r2 = query(env, point[None])
    assert r2.ok[0] and r2.hand_error[0] <= TOL_HAND
    cond = env.db.condition[env.db.valid]
    assert dist <= np.linalg.norm(cond - far, axis=1).min() + 1e-6  # no worse than a condition
    assert dist >= float(r.region_gap[0]) - 1e-6  # the gap is a lower bound


def test_spd_solve_matches_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 4):
        a = rng.normal(size=(n, n))
        h = np.eye(n) + 50.0 * a @ a.T
        b = rng.normal(size=n)
        x = np.asarray(jax.jit(spd_solve)(jnp.asarray(h, jnp.float32), jnp.asarray(b, jnp.float32)))
        ref = np.linalg.solve(h, b)
        assert np.abs(x - ref).max() <= TOL_SPD * np.abs(ref).max() * 10 * n


# ------------------------------------------------------------------------ joint-limit projection


@functools.cache
def _limit_problem():
    """Bases and BCs of 8 targets, eq. 1 motions, and a jitted `enforce_limits(q, lower, upper)`."""
    env = online_env()
    rng = np.random.default_rng(2)
    targets = env.db.condition[8:16] + rng.normal(0, 0.01, (8, 3)).astype(np.float32)
    r = query(env, targets)
    basis, q, bc = _eq1(env, targets, r.q_final, r.duration)

    @jax.jit
    def enforce(q, lower, upper):
        return enforce_limits(basis, bc, env.grid, q, lower, upper, SETTINGS)

    return env, basis, bc, np.asarray(q), enforce


@settings(max_examples=25, deadline=None)
@given(
    below=st.lists(st.floats(0.0, 0.05), min_size=7, max_size=7),
    above=st.lists(st.floats(0.0, 0.05), min_size=7, max_size=7),
)
def test_limit_projection_keeps_limits_and_bcs(below, above):
    """Limits drawn just outside [min(q0, qf), max(q0, qf)] per joint, so the eq. 1 motions
    overshoot them: the result is inside (exactly), meets the same BCs, and joints that were
    inside are untouched."""
    env, _, bc, q, enforce = _limit_problem()
    q0, qf = np.asarray(bc.q0), np.asarray(bc.qf)
    lower = (np.minimum(q0, qf).min(axis=0) - np.asarray(below)).astype(np.float32)
    upper = (np.maximum(q0, qf).max(axis=0) + np.asarray(above)).astype(np.float32)
    out, excess, _ = jax.device_get(enforce(q, jnp.asarray(lower), jnp.asarray(upper)))
    assert ((out >= lower) & (out <= upper)).all()
    was_out = (q > upper) | (q < lower)
    worst = np.maximum(q - upper, lower - q).max(axis=(1, 2))
    np.testing.assert_allclose(excess, worst.clip(0), atol=1e-7)
    np.testing.assert_allclose(out[:, 0], q0, atol=TOL_BC_Q)
    np.testing.assert_allclose(out[:, -1], qf, atol=TOL_BC_Q)
    d1 = np.asarray(env.grid.d1)[[0, -1]]
    dur = np.asarray(bc.duration)[:, None, None]
    vel = np.einsum("et,ctj->cej", d1, out) / dur  # (C, 2, J) end velocities [rad/s]
    vel_ref = np.einsum("et,ctj->cej", d1, q) / dur
    assert (np.abs(vel) <= np.abs(vel_ref) + TOL_BC_QD).all()
    untouched = ~was_out.any(axis=1)  # (C, J)
    np.testing.assert_array_equal(
        out.transpose(0, 2, 1)[untouched], q.transpose(0, 2, 1)[untouched]
    )


def test_limit_projection_is_the_minimal_null_space_step():
    """Push every motion's shoulder pitch (joint 1) 0.2 rad over a limit along a BC null-space
    direction: the projection alone brings it back (no blend), the result stays in the span of
    the mean, the 4 components and the constant, and its step is SciPy's minimum-norm one."""
    from scipy.optimize import minimize

    from evojax_motion.compiler.interpolation import solve_boundary

    env, basis, bc, q, enforce = _limit_problem()
    j = 1
    funcs, null = jax.jit(
        lambda b, bc: (basis_functions(b, 4), solve_boundary(b, bc, env.grid, 4).null)
    )(basis, bc)
    funcs, null = np.asarray(funcs, np.float64), np.asarray(null, np.float64)  # (C, J, 5, T|4)
    g = np.einsum("cnt,cnk->ctk", funcs[:, j], null[:, j])  # (C, T, 4) null directions
    upper = np.asarray(env.robot.upper, np.float32).copy()
    upper[j] = q[:, :, j].max() + 0.05
    pushed = q.copy()
    for c in range(q.shape[0]):
        k = np.argmax(np.abs(g[c]).max(axis=0))
        d = g[c, :, k] * np.sign(g[c, np.argmax(np.abs(g[c, :, k])), k])
        alpha = (upper[j] + 0.2 - q[c, :, j].max()) / d.max()
        while (q[c, :, j] + alpha * d).max() < upper[j] + 0.2:
            alpha *= 1.2
        pushed[c, :, j] += alpha * d
    assert (pushed[:, :, j].max(axis=1) > upper[j] + 0.15).all()
    lower = np.asarray(env.robot.lower, np.float32)
    out, excess, fallback = jax.device_get(enforce(pushed, jnp.asarray(lower), jnp.asarray(upper)))
    assert (out <= upper).all() and (excess > 0.15).all() and not fallback.any()
    safe = np.asarray(minimum_jerk(env.grid, bc.q0, bc.qf))
    for c in range(q.shape[0]):
        span = np.concatenate([np.asarray(basis.mean)[c, None, :, j], funcs[c, j]]).T  # (T, 6)
        coef, *_ = np.linalg.lstsq(span, out[c, :, j], rcond=None)
        assert np.abs(span @ coef - out[c, :, j]).max() < TOL_SPAN
        a = pushed[c, :, j].astype(np.float64)
        hi = np.maximum(upper[j] - SETTINGS.limit_margin, safe[c, :, j])
        res = minimize(
            lambda z: 0.5 * z @ z,
            np.zeros(g.shape[2]),
            jac=lambda z: z,
            constraints=[
                {
                    "type": "ineq",
                    "fun": lambda z, c=c, a=a, hi=hi: hi - a - g[c] @ z,
                    "jac": lambda z, c=c: -g[c],
                }
            ],
            method="SLSQP",
            options={"ftol": 1e-12, "maxiter": 300},
        )
        assert res.success
        ours = np.linalg.lstsq(g[c], out[c, :, j] - a, rcond=None)[0]
        scipy_step = g[c] @ res.x
        np.testing.assert_allclose(g[c] @ ours, scipy_step, atol=TOL_PROJ)


# -------------------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def db_file(tmp_path_factory, env):
    return save_env_database(tmp_path_factory.mktemp("online"), env)


def test_cli_generate_csv_torques_equal_mj_inverse(env, db_file, tmp_path, capsys, monkeypatch):
    """``evojax-motion generate`` on the cached compilations (the loader has its own test)."""
    from evojax_motion.run.export import read_trajectory

    prepare_cli(monkeypatch, cli_session(env, db_file))
    target = [f"{v:.4f}" for v in env.db.condition[3] + 0.01]
    out = tmp_path / "traj.csv"
    assert run_cli(["generate", "--db", str(db_file), "--target", *target, "--out", str(out)]) == 0
    assert "written to" in capsys.readouterr().out
    data = read_trajectory(out)
    assert data.joint_names == env.robot.joint_names
    ref = mj_inverse_torques(env.robot, data.q, data.qd, data.qdd)
    np.testing.assert_allclose(data.tau, ref, atol=TOL_TAU)
    assert ((data.q >= env.robot.lower) & (data.q <= env.robot.upper)).all()
    # refuses to overwrite; an unreachable target: one line, distance, exit 2, nothing written
    assert run_cli(["generate", "--db", str(db_file), "--target", *target, "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().out
    far = tmp_path / "far.json"
    argv = ["generate", "--db", str(db_file), "--target", "1.5", "-0.3", "1.4", "--out", str(far)]
    assert run_cli(argv) == 2
    msg = capsys.readouterr().out
    assert "outside the reachable region" in msg and "m away" in msg and "--nearest" in msg
    assert not far.exists()
    assert run_cli([*argv, "--nearest"]) == 0
    assert "using it (--nearest)" in capsys.readouterr().out
    assert "NaN" not in far.read_text() and "nan" not in far.read_text()


def test_load_online_model_rebuilds_robot_and_settings(env, db_file, tmp_path):
    """The CLI's loader: robot from the MJCF stored in the file, arrays as saved, basis settings
    from a run directory's config.yaml (no compilation involved)."""
    import shutil

    from evojax_motion.online.generation import load_online_model

    model = load_online_model(db_file)
    assert model.robot.joint_names == env.robot.joint_names
    np.testing.assert_array_equal(model.robot.upper, env.robot.upper)
    np.testing.assert_array_equal(model.db.q, env.db.q)
    assert model.settings_source == "defaults" and model.grid.s.shape == (env.db.q.shape[1],)
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(db_file, run / "db_final.npz")
    (run / "config.yaml").write_text("basis:\n  radius: 0.2\n  neighbours: 6\n")
    model = load_online_model(run)
    assert model.basis_settings.radius == 0.2 and model.basis_settings.neighbours == 6
    with pytest.raises(UserError, match=r"without db_final\.npz"):
        load_online_model(tmp_path)


def test_cli_parser_shape():
    """The subcommands and their required options (cheap: no query runs)."""
    from evojax_motion.cli.online import add_online_parsers

    parser = argparse.ArgumentParser()
    add_online_parsers(parser.add_subparsers(dest="command"))
    args = parser.parse_args(
        ["generate", "--db", "x.npz", "--target", "1", "2", "3", "--out", "o.csv"]
    )
    assert args.target == [1.0, 2.0, 3.0] and args.duration is None and args.format is None
    args = parser.parse_args(
        ["catch", "--db", "x", "--ball", "1", "2", "3", "4", "5", "6", "--out", "o.npz"]
    )
    assert args.ball == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0] and args.drag == 0.0


@pytest.mark.slow
def test_cli_generate_end_to_end(env, db_file, tmp_path, capsys, monkeypatch):
    """The real command: loads the file, rebuilds the robot, compiles its own query."""
    from evojax_motion.cli import online as online_cli
    from evojax_motion.run.export import read_trajectory

    prepare_cli(monkeypatch)
    online_cli._session.cache_clear()
    target = [f"{v:.4f}" for v in env.db.condition[7] + 0.005]
    out = tmp_path / "traj.npz"
    argv = ["generate", "--db", str(db_file), "--target", *target, "--duration", "0.8"]
    assert run_cli([*argv, "--out", str(out)]) == 0
    assert "0.800 s" in capsys.readouterr().out
    data = read_trajectory(out)
    np.testing.assert_allclose(data.t[-1], 0.8, rtol=1e-6)
    assert data.meta["hand_error"] <= TOL_HAND
    ref = mj_inverse_torques(env.robot, data.q, data.qd, data.qdd)
    np.testing.assert_allclose(data.tau, ref, atol=TOL_TAU)


_SPY_ON_PLATFORMS = """
import sys

import jax
from jax._src import xla_bridge

seen = []
update = jax.config.update


def spy(name, value):
    if name == "jax_platforms":
        seen.append((value, xla_bridge.backends_are_initialized()))
    update(name, value)


jax.config.update = spy
from evojax_motion.cli.entry import main

status = main(sys.argv[1:])
print("platforms:", seen, jax.default_backend(), status)
"""


@pytest.mark.slow
def test_queries_run_on_the_cpu_chosen_before_any_backend_starts(env, db_file, tmp_path):
    """``--device cpu`` (the default): the command line makes the host's CPU JAX's platform
    before anything starts a backend (else a GPU machine would still start CUDA and compile
    there); a fresh process, as a user's command is."""
    import os
    import subprocess
    import sys

    target = [f"{v:.4f}" for v in env.db.condition[3] + 0.01]
    argv = ["generate", "--db", str(db_file), "--target", *target, "--out", str(tmp_path / "a.csv")]
    environ = {**os.environ, "EVOJAX_MOTION_JAX_CACHE": str(tmp_path / "cache")}  # as users run
    environ.pop("JAX_PLATFORMS", None)
    run = subprocess.run(
        [sys.executable, "-c", _SPY_ON_PLATFORMS, *argv],
        capture_output=True, text=True, env=environ, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "platforms: [('cpu', False)] cpu 0" in run.stdout


def test_device_default_leaves_the_platform_to_jax(env, db_file, tmp_path, monkeypatch):
    """``--device default`` does not touch JAX's platform setting; it lets a GPU take memory as
    the queries need it (unless the environment says)."""
    from evojax_motion.run.memory import PREALLOCATE_ENV

    prepare_cli(monkeypatch, cli_session(env, db_file))
    monkeypatch.delenv(PREALLOCATE_ENV, raising=False)
    calls = []
    update = jax.config.update
    monkeypatch.setattr(jax.config, "update", lambda k, v: (calls.append(k), update(k, v)))
    target = [f"{v:.4f}" for v in env.db.condition[3] + 0.01]
    out = str(tmp_path / "a.csv")
    argv = ["generate", "--db", str(db_file), "--target", *target, "--out", out]
    assert run_cli([*argv, "--device", "default"]) == 0
    assert "jax_platforms" not in calls and os.environ[PREALLOCATE_ENV] == "false"
    assert run_cli([*argv, "--force"]) == 0
    assert "jax_platforms" in calls


def test_a_kept_trace_gives_the_same_motion_and_is_keyed_by_what_it_closes_over(
    env, db_file, tmp_path, monkeypatch
):
    """The command line's generator keeps its trace (`kept_trace`): the plain jit's motion (to
    float32 fusion), one exported program on disk, read back by a new generator; the key moves
    with the settings the program closes over."""
    import dataclasses

    from evojax_motion.online.generation import (
        check_query,
        load_online_model,
        make_online_generator,
        program_parts,
        to_numpy,
    )
    from evojax_motion.run import cache

    monkeypatch.setattr(cache, "traced_cache_dir", lambda: tmp_path / "traced")
    model = load_online_model(db_file)
    fixed = (model.robot, model.dyn, model.grid, model.basis_settings, model.settings)
    parts = program_parts(model)
    query_args = (model.db_device, *check_query(model.robot, env.db.condition[3] + 0.01))
    plain = to_numpy(make_online_generator(*fixed, one_shot=True)(*query_args))
    for _ in range(2):  # exported, then read back
        kept = make_online_generator(*fixed, one_shot=True, cache_parts=parts)
        got = to_numpy(kept(*query_args))
        np.testing.assert_allclose(got.q, plain.q, rtol=0, atol=TOL_KEPT_Q)
        np.testing.assert_allclose(got.tau, plain.tau, rtol=0, atol=TOL_KEPT_TAU)
        assert len(list((tmp_path / "traced").glob("*"))) == 1
    other = dataclasses.replace(model.settings, ik_iters=model.settings.ik_iters + 1)
    assert program_parts(dataclasses.replace(model, settings=other)) != parts
