"""Ball catching (catching.py): the ball's flight against references, the catch plan's
feasibility and margins, the generated catch, and the ``catch`` command's refusals."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from online_support import (
    catcher,
    cli_session,
    online_env,
    prepare_cli,
    run_cli,
    save_env_database,
)

from evojax_motion.errors import UserError
from evojax_motion.model.robot import robot_from_mjcf_text
from evojax_motion.online.catching import ball_flight, explain_plan, validate_ball
from evojax_motion.online.generation import final_hand
from evojax_motion.online.palm import palm_normal
from evojax_motion.settings.online import BALL_RADIUS, CatchSettings

TOL_FLIGHT = 1e-4  # m: float32 ballistic positions over 1.5 s (|p| ~ 3 m)
TOL_DRAG = 1e-4  # m: RK4 (4 substeps of 10 ms) vs SciPy's DOP853 at 1e-10
TOL_HAND = 1e-3  # m: hand at the catch point at the end of the motion
TOL_CLI_HAND = 5e-3  # m: the catch command's default --tolerance (5 mm)
PALM_FACING_MIN = 0.5  # cosine of the palm normal and the incoming ball: the palm side
GRAVITY = np.array([0.0, 0.0, -9.81], np.float32)


def throw_through(point, t_hit, p0):
    """Release velocity of a vacuum throw from ``p0`` that passes ``point`` at ``t_hit``."""
    return (np.asarray(point) - p0 - 0.5 * GRAVITY * t_hit**2) / t_hit


def _run(p0, v0):
    """One ball (always B = 1: one compilation for every test)."""
    env = online_env()
    fn = catcher()[1]
    p0, v0 = np.atleast_2d(p0).astype(np.float32), np.atleast_2d(v0).astype(np.float32)
    q0 = np.asarray(env.robot.rest, np.float32)[None]
    return jax.device_get(fn(env.db_device, p0, v0, q0))


def test_vacuum_flight_is_the_closed_form():
    times = np.linspace(0.0, 1.5, 16, dtype=np.float32)
    p0, v0 = np.array([3.0, 0.2, 1.5], np.float32), np.array([-4.0, 0.1, 3.0], np.float32)
    pos, vel = ball_flight(p0, v0, times, GRAVITY, 0.0, 4)
    t = times[:, None].astype(np.float64)
    np.testing.assert_allclose(pos, p0 + v0 * t + 0.5 * GRAVITY * t**2, atol=TOL_FLIGHT)
    np.testing.assert_allclose(vel, v0 + GRAVITY * t, atol=TOL_FLIGHT)


def test_drag_flight_matches_scipy():
    from scipy.integrate import solve_ivp

    k = 0.01
    times = np.linspace(0.0, 1.5, 151, dtype=np.float32)
    p0, v0 = np.array([3.0, 0.2, 1.5]), np.array([-8.0, 0.5, 4.0])
    pos, _ = jax.jit(ball_flight, static_argnums=(4, 5))(
        p0.astype(np.float32), v0.astype(np.float32), times, GRAVITY, k, 4
    )

    def rhs(_, y):
        v = y[3:]
        return np.r_[v, GRAVITY - k * np.linalg.norm(v) * v]

    ref = solve_ivp(rhs, (0, 1.5), np.r_[p0, v0], t_eval=times, method="DOP853", rtol=1e-10,
                    atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(pos, ref.y[:3].T, atol=TOL_DRAG)
    vacuum, _ = ball_flight(p0.astype(np.float32), v0.astype(np.float32), times, GRAVITY, 0.0, 4)
    assert np.linalg.norm(vacuum[-1] - ref.y[:3, -1]) > 0.1  # drag matters over 1.5 s


def test_catchable_ball_is_caught_in_time_at_the_point():
    env, catch = online_env(), catcher()[0]
    point = env.db.condition[5]
    p0 = np.array([3.0, -0.2, 1.6], np.float32)
    v0 = throw_through(point, 0.8, p0)
    plan, motion = _run(p0, v0)
    assert plan.feasible[0] and motion.ok[0]
    # the catch point is on the ball's path, at the catch time
    pos, _ = ball_flight(p0, v0, np.float32([plan.catch_time[0]]), GRAVITY, 0.0, 1)
    np.testing.assert_allclose(plan.catch_point[0], np.asarray(pos)[0], atol=TOL_FLIGHT)
    # the hand gets there, at rest, exactly when the ball does, after the reaction time
    assert motion.hand_error[0] <= TOL_HAND
    np.testing.assert_allclose(motion.t[0, -1], plan.catch_time[0], atol=1e-5)
    assert motion.t[0, 0] >= catch.reaction_time - 1e-6
    assert plan.time_margin[0] >= 0 and plan.depth[0] >= 0
    natural = plan.natural_duration[0, plan.sample[0]]
    assert natural / catch.speedup - 1e-6 <= plan.duration[0] <= natural + 1e-6
    np.testing.assert_allclose(
        plan.time_margin[0], plan.catch_time[0] - catch.reaction_time - natural / catch.speedup,
        atol=1e-5,
    )  # fmt: skip
    lo, hi = env.robot.lower, env.robot.upper
    assert ((motion.q[0] >= lo) & (motion.q[0] <= hi)).all()
    assert "catch at t =" in explain_plan(plan, 0)
    # the palm faces the incoming ball, its centre one ball radius short of the catch point
    pos, rot = (np.asarray(a) for a in env.dyn.site_pose(motion.q[0, -1]))
    normal = rot @ palm_normal(env.robot)
    incoming = -plan.ball_velocity[0] / np.linalg.norm(plan.ball_velocity[0])
    assert normal @ incoming >= PALM_FACING_MIN
    np.testing.assert_allclose(plan.palm_facing[0], normal @ incoming, atol=1e-4)
    np.testing.assert_allclose(pos + BALL_RADIUS * normal, plan.catch_point[0], atol=TOL_HAND)


def test_palm_normal_is_the_palm_face_of_the_hand():
    """mahru_arm's site is the centre of the palm face (+y) of its hand box; a site off every
    geom surface has none."""
    env = online_env()
    np.testing.assert_allclose(palm_normal(env.robot), [0.0, 1.0, 0.0], atol=1e-6)
    xml = env.robot.mjcf.replace('<site name="hand" pos="0 0.015 -0.06"/>',
                                 '<site name="hand" pos="0 0.1 -0.06"/>')  # fmt: skip
    assert xml != env.robot.mjcf
    off = robot_from_mjcf_text("off", xml, env.robot.joint_names, env.robot.site_name)
    assert palm_normal(off) is None


def test_uncatchable_balls_say_why():
    env = online_env()
    point = env.db.condition[5]
    p0 = np.array([3.0, -0.2, 1.6], np.float32)
    far = (np.array([3.0, 3.0, 1.6], np.float32), throw_through([0.3, 3.0, 1.4], 0.8, p0))
    fast = (p0, throw_through(point, 0.12, p0))  # arrives before the arm could move
    plan, motion = _run(*far)
    assert not plan.feasible[0] and not motion.ok[0] and plan.sample[0] == -1
    assert not plan.passes_region[0] and plan.closest_gap[0] > 1.0
    assert "no closer than" in explain_plan(plan, 0)
    plan, motion = _run(*fast)
    assert not plan.feasible[0] and not motion.ok[0] and plan.sample[0] == -1
    assert plan.passes_region[0] and plan.time_short[0] > 0.1
    assert "too early" in explain_plan(plan, 0)


def test_ball_validation():
    p0, v0 = validate_ball([1, 2, 3, 4, 5, 6])
    assert p0.shape == (1, 3) and v0.tolist() == [[4.0, 5.0, 6.0]]
    with pytest.raises(UserError, match="--ball: expected release position"):
        validate_ball([1, 2, 3])
    with pytest.raises(UserError, match="--ball: expected finite"):
        validate_ball([1, 2, 3, np.inf, 0, 0])
    with pytest.raises(ValueError, match=r"^speedup: expected"):
        CatchSettings(speedup=0.5)


def test_cli_catch(tmp_path, capsys, monkeypatch):
    """``evojax-motion catch`` on the cached compilations (the loader: test_online)."""
    from evojax_motion.run.export import read_trajectory

    env = online_env()
    db = save_env_database(tmp_path, env)
    prepare_cli(monkeypatch, cli_session(env, db))
    p0 = np.array([3.0, -0.2, 1.6], np.float32)
    v0 = throw_through(env.db.condition[5], 0.8, p0)
    ball = [f"{x:.6f}" for x in np.r_[p0, v0]]
    out = tmp_path / "catch.npz"
    horizon = ["--horizon", "1.2"]  # the cached catcher's settings
    assert run_cli(["catch", "--db", str(db), "--ball", *ball, "--out", str(out), *horizon]) == 0
    assert "catch at t =" in capsys.readouterr().out
    data = read_trajectory(out)
    assert data.meta["caught"] and data.t[0] >= 0.1 - 1e-6
    # the written hand, by C MuJoCo's kinematics, at the ball (vacuum flight) at the catch time
    t_c = float(data.meta["catch_time"])
    assert abs(float(data.t[-1]) - t_c) <= 1e-4
    ball_at = p0 + v0 * t_c + 0.5 * GRAVITY * t_c**2
    hand = final_hand(env.robot, data.q[-1:])[0]
    # the palm's centre one ball radius short of the ball's: the ball touches the palm there
    assert abs(np.linalg.norm(hand - ball_at) - BALL_RADIUS) <= TOL_CLI_HAND
    tight = tmp_path / "tight.npz"
    argv = ["catch", "--db", str(db), "--ball", *ball, "--out", str(tight), *horizon]
    assert run_cli([*argv, "--tolerance", "1e-6"]) == 2
    msg = capsys.readouterr().out
    assert "the hand misses the target" in msg and "at the catch time" in msg and " mm" in msg
    assert not tight.exists()
    far = [f"{x:.6f}" for x in np.r_[3.0, 3.0, 1.6, -4.0, 0.0, 3.0]]
    out2 = tmp_path / "no.csv"
    assert run_cli(["catch", "--db", str(db), "--ball", *far, "--out", str(out2), *horizon]) == 2
    msg = capsys.readouterr().out
    assert msg.startswith("error: the ball cannot be caught") and "--nearest" in msg
    assert not out2.exists()
    argv = ["catch", "--db", str(db), "--ball", *far, "--out", str(out2), *horizon, "--nearest"]
    assert run_cli(argv) == 0
    msg = capsys.readouterr().out
    assert msg.startswith("note: the ball cannot be caught") and "moving to the reachable" in msg
    assert read_trajectory(out2).q.shape == data.q.shape


def test_fit_speed_straightens_only_the_joints_too_fast():
    """A deadline: the joint whose path is too fast blends toward minimum jerk until it fits; a
    joint fast enough keeps its path bit for bit; the BCs stay."""
    from evojax_motion.motion.timegrid import derivatives, make_time_grid
    from evojax_motion.online.limits import SPEED_BLENDS, fit_speed, minimum_jerk

    grid = make_time_grid(100)
    q0, qf = np.zeros((1, 2), np.float32), np.array([[1.0, 1.0]], np.float32)
    smooth = np.asarray(minimum_jerk(grid, q0, qf))
    s = np.asarray(grid.s, np.float32)[None, :, None]
    wiggle = smooth + 0.3 * np.sin(2 * np.pi * 3 * s) * np.sin(np.pi * s) ** 3  # fast joint
    q = np.concatenate([wiggle[..., :1], smooth[..., 1:]], axis=2)
    duration = np.array([1.0], np.float32)
    limit = np.array([3.0, 3.0], np.float32)  # minimum jerk peaks at 1.875 rad/s
    before = np.abs(np.asarray(derivatives(grid, q, duration)[0])).max(axis=1)[0]
    assert before[0] > limit[0] >= before[1]
    out, lam = (np.asarray(a) for a in fit_speed(grid, q, q0, qf, duration, limit))
    after = np.abs(np.asarray(derivatives(grid, out, duration)[0])).max(axis=1)[0]
    assert 0 < lam[0, 0] < len(SPEED_BLENDS) - 1 and lam[0, 1] == 0 and (after <= limit).all()
    np.testing.assert_array_equal(out[..., 1], q[..., 1])
    np.testing.assert_allclose(out[0, [0, -1]], np.r_[q0, qf], atol=1e-6)


def test_fit_speed_falls_back_to_the_plateau_path():
    """A limit that minimum jerk (peak 1.875 x the mean speed) exceeds but the plateau path (1 /
    (1 - ramp)) meets: the plateau is chosen; it starts and ends at rest, with continuous speed,
    its peak is the formula's and it is monotone; a limit too low for both keeps the plateau."""
    from evojax_motion.motion.timegrid import derivatives, make_time_grid
    from evojax_motion.online.limits import PLATEAU_RAMP, SPEED_BLENDS, fit_speed, minimum_jerk

    grid = make_time_grid(201)
    q0, qf = np.zeros((1, 1), np.float32), np.ones((1, 1), np.float32)
    q = np.asarray(minimum_jerk(grid, q0, qf))
    duration = np.array([1.0], np.float32)
    peak_plateau = 1.0 / (1.0 - PLATEAU_RAMP)
    for limit, expect in ((1.7, len(SPEED_BLENDS)), (1.2, len(SPEED_BLENDS)), (1.9, 0)):
        out, choice = (
            np.asarray(a)
            for a in fit_speed(grid, q, q0, qf, duration, np.array([limit], np.float32))
        )
        assert choice[0, 0] == expect, limit
    out, _ = (
        np.asarray(a) for a in fit_speed(grid, q, q0, qf, duration, np.array([1.7], np.float32))
    )
    qd = np.asarray(derivatives(grid, out, duration)[0])[0, :, 0]
    PEAK_TOL = 0.01  # finite differences on 201 samples against the closed-form peak
    assert abs(qd.max() - peak_plateau) < PEAK_TOL * peak_plateau
    assert (np.diff(out[0, :, 0]) >= 0).all()
    np.testing.assert_allclose(out[0, [0, -1], 0], [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(qd[[0, -1]], 0.0, atol=1e-3)
