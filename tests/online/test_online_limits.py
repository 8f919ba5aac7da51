"""Velocity and torque limits of online motions (the time scaling of online/limits.py,
catching.py, the CLI): the scaling's search against closed forms, a too-fast motion slowed to the
limits and checked by C MuJoCo's float64 inverse dynamics, and motions that no allowed duration
brings within the limits refused with their figures (exit status 2, nothing written)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from online_support import (
    BASIS,
    CATCH_KW,
    SETTINGS,
    cli_session,
    mj_inverse_torques,
    online_env,
    prepare_cli,
    query,
    run_cli,
    save_env_database,
)

from evojax_motion.online.explain import explain_unusable
from evojax_motion.online.generation import final_hand
from evojax_motion.online.limits import TimeLaw, shortest_duration

HEADROOM = SETTINGS.limit_headroom
TOL_SEARCH = 1e-5  # relative: the scan + 24 bisection steps vs a closed-form shortest duration
TOL_USAGE = 2e-3  # the binding limit's use at the chosen duration: float32 RNEA vs float64 C
SHORTER = 0.98  # a duration 2 % shorter than the chosen one must break the usable limits
GRAVITY = np.array([0.0, 0.0, -9.81], np.float32)


@pytest.fixture(scope="module")
def env():
    return online_env()


@pytest.fixture(scope="module")
def db_file(tmp_path_factory, env):
    return save_env_database(tmp_path_factory.mktemp("limits"), env)


def _usage(robot, q, qd, qdd) -> float:
    """Largest share of a velocity or torque limit, by C MuJoCo's float64 mj_inverse."""
    tau = mj_inverse_torques(robot, q, qd, qdd)
    return float(
        max(
            np.max(np.abs(tau) / robot.torque_limit),
            np.max(np.abs(qd) / robot.velocity_limit),
        )
    )


def _numpy_derivatives(grid, q, duration):
    """``qd, qdd`` of ``q (T, J)`` at ``duration`` from the grid's operators, in float64."""
    d1, d2 = np.asarray(grid.d1, np.float64), np.asarray(grid.d2, np.float64)
    q = np.asarray(q, np.float64)
    return d1 @ q / duration, d2 @ q / duration**2


def test_shortest_duration_matches_closed_forms():
    """Inertial torque ``a w^2`` against a limit L: D* = sqrt(|a| / L); a velocity slope s
    against V: D* = |s| / V; a constant (gravity) torque over L: none (inf); a motion already
    within its limits keeps its duration."""
    vel_use = np.array([4.0, np.inf], np.float32)
    tau_use = np.array([10.0, 5.0], np.float32)
    zero = np.zeros((4, 3, 2), np.float32)
    c0, c2, slope = zero.copy(), zero.copy(), zero.copy()
    c2[0, 1, 1] = -45.0  # torque-bound: D* = 3 s
    slope[1, 2, 0] = 6.0  # velocity-bound: D* = 1.5 s
    c0[2, 0, 0] = 12.0  # gravity over 10 N m: no duration helps
    c2[3, 0, 0] = 2.0  # within at the asked 1 s: stays 1 s
    law = TimeLaw(*(jnp.asarray(a) for a in (c0, zero, c2, slope)))
    asked = jnp.asarray([0.01, 0.01, 0.01, 1.0], jnp.float32)
    fn = jax.jit(shortest_duration, static_argnums=(4, 5))
    got = np.asarray(fn(law, asked, vel_use, tau_use, 32, 24))
    np.testing.assert_allclose(got[[0, 1, 3]], [3.0, 1.5, 1.0], rtol=TOL_SEARCH)
    assert np.isinf(got[2])


def test_too_fast_motion_is_slowed_to_the_limits(env):
    """``duration = 1 ms`` asks for kN m and thousands of rad/s: the result is the same path,
    slowed down just enough; C MuJoCo's float64 inverse dynamics of its rows confirms it is
    within every limit, uses (1 - headroom) of the binding one, and breaks it 2 % faster."""
    targets = env.db.condition[:3] + 0.01
    plain = query(env, targets)
    fast = query(env, targets, duration=0.001)
    assert fast.ok.all() and fast.within_time.all()
    np.testing.assert_array_equal(fast.duration_asked, np.float32(0.001))
    assert (fast.duration > 0.1).all()
    np.testing.assert_allclose(fast.q, plain.q, atol=1e-6)  # slowed down, not reshaped
    for i in range(3):
        q, qd, qdd = fast.q[i], fast.qd[i], fast.qdd[i]
        use = _usage(env.robot, q, qd, qdd)
        assert abs(use - (1.0 - HEADROOM)) <= TOL_USAGE
        shorter = SHORTER * float(fast.duration[i])
        assert _usage(env.robot, q, *_numpy_derivatives(env.grid, q, shorter)) > 1 - HEADROOM
        # the 1 ms motion itself, as it would have been
        over = _usage(env.robot, q, *_numpy_derivatives(env.grid, q, 0.001))
        assert over > 1e3
        # the margins it reports are those of its rows
        tau = mj_inverse_torques(env.robot, q, qd, qdd)
        margin = np.min(1.0 - np.abs(tau).max(0) / env.robot.torque_limit)
        np.testing.assert_allclose(fast.torque_margin[i], margin, atol=TOL_USAGE)
    # motions already within the limits are left alone, with their margins
    assert (plain.duration == plain.duration_asked).all() and (plain.torque_margin > 0).all()


def test_cli_generate_slows_a_too_fast_motion(env, db_file, tmp_path, capsys, monkeypatch):
    """``generate --duration 0.001`` writes a feasible, slower motion and says so; the CSV's
    comment lines carry the margins."""
    from evojax_motion.run.export import read_trajectory

    prepare_cli(monkeypatch, cli_session(env, db_file))
    target = [f"{v:.4f}" for v in env.db.condition[3] + 0.01]
    out = tmp_path / "fast.csv"
    argv = ["generate", "--db", str(db_file), "--target", *target, "--duration", "0.001"]
    assert run_cli([*argv, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "stretched from 0.001 s to" in text and "limit margins" in text
    data = read_trajectory(out)
    assert data.meta["time_scaled"] and data.meta["duration_asked"] == pytest.approx(0.001)
    assert data.t[-1] > 0.1
    assert min(data.meta["torque_margin"], data.meta["velocity_margin"]) >= HEADROOM - TOL_USAGE
    assert "# torque_margin: " in out.read_text() and "# velocity_margin: " in out.read_text()
    assert _usage(env.robot, data.q, data.qd, data.qdd) <= 1.0


def _throw_through(point, t_hit, p0):
    """Release velocity of a vacuum throw from ``p0`` that passes ``point`` at ``t_hit``."""
    return ((np.asarray(point) - p0 - 0.5 * GRAVITY * t_hit**2) / t_hit).astype(np.float32)


def test_catch_that_cannot_arrive_in_time_exits_2_with_figures(
    env, db_file, tmp_path, capsys, monkeypatch
):
    """A planner allowed to rush (speedup 4) picks a catch the limits cannot make in time: the
    motion would have to start before the reaction time. The catch is refused with the time it
    needs, the time it has, and the binding joint's figures; nothing is written."""
    from evojax_motion.cli import online as online_cli
    from evojax_motion.online.catching import make_catcher
    from evojax_motion.settings.online import CatchSettings

    rushed = CatchSettings(**CATCH_KW, speedup=4.0)
    fn = make_catcher(env.robot, env.dyn, env.grid, BASIS, SETTINGS, rushed)
    p0 = np.array([3.0, -0.2, 1.6], np.float32)
    v0 = _throw_through(env.db.condition[5], 0.4, p0)
    rest = np.asarray(env.robot.rest, np.float32)[None]
    plan, motion = jax.device_get(fn(env.db_device, p0[None], v0[None], rest))
    available = float(plan.catch_time[0]) - rushed.reaction_time
    assert plan.feasible[0] and not motion.ok[0] and not motion.within_time[0]
    assert float(motion.duration_needed[0]) > available + 0.05
    np.testing.assert_allclose(motion.duration[0], available, rtol=1e-6)
    np.testing.assert_allclose(motion.t[0, 0], rushed.reaction_time, atol=1e-5)

    opened = prepare_cli(monkeypatch, cli_session(env, db_file))
    # the command line's catch settings for --horizon 1.2, served by the rushed planner
    monkeypatch.setitem(online_cli._CATCHERS, (id(opened[0]), CatchSettings(**CATCH_KW)), fn)
    out = tmp_path / "late.csv"
    ball = [f"{x:.6f}" for x in np.r_[p0, v0]]
    argv = ["catch", "--db", str(db_file), "--ball", *ball, "--horizon", "1.2", "--out", str(out)]
    assert run_cli(argv) == 2
    msg = capsys.readouterr().out
    needed = f"{float(motion.duration_needed[0]):.3f} s"
    assert msg.startswith(f"error: the motion needs {needed} to stay within")
    assert f"only {available:.3f} s are available between the reaction time" in msg
    joint = env.robot.joint_names[int(motion.worst_joint[0])]
    assert f"joint {joint!r} needs" in msg and "against a limit of" in msg
    assert "nothing written" in msg and not out.exists()


@pytest.mark.slow
def test_gravity_over_a_torque_limit_has_no_motion(env, db_file, tmp_path, capsys, monkeypatch):
    """A shoulder too weak to hold the raised arm (3 N m against ~10 N m of gravity): no
    duration helps; the refusal names the joint and the torque it needs."""
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import robot_from_mjcf_text
    from evojax_motion.online.generation import OnlineModel, make_online_generator
    from evojax_motion.settings.online import MAX_DURATION

    mjcf = env.robot.mjcf.replace(
        'range="-0.872665 2.967060"\n               actuatorfrcrange="-80 80"',
        'range="-0.872665 2.967060"\n               actuatorfrcrange="-3 3"',
    )
    assert mjcf != env.robot.mjcf
    weak = robot_from_mjcf_text("weak", mjcf, env.robot.joint_names, env.robot.site_name)
    gen = make_online_generator(weak, make_dynamics(weak), env.grid, BASIS, SETTINGS)
    targets = env.db.condition[3:4] + 0.01
    dur = np.full(1, np.nan, np.float32)
    rest = np.asarray(weak.rest, np.float32)[None]
    motion = jax.device_get(gen(env.db_device, targets, dur, rest))
    assert motion.reachable[0] and not motion.ok[0] and np.isinf(motion.duration_needed[0])
    assert weak.joint_names[int(motion.worst_joint[0])] == "shoulder_pitch"
    assert float(motion.worst_value[0]) > 3.0 and motion.worst_kind[0] == 0
    np.testing.assert_allclose(motion.duration[0], MAX_DURATION)
    why = explain_unusable(weak, motion, 0, SETTINGS)
    assert why.startswith("no motion within the velocity and torque limits: even in 60.000 s")

    model = cli_session(env, db_file)[0]
    prepare_cli(monkeypatch, (OnlineModel(**{**model.__dict__, "robot": weak}), gen, None))
    out = tmp_path / "weak.npz"
    target = [f"{v:.4f}" for v in targets[0]]
    assert run_cli(["generate", "--db", str(db_file), "--target", *target, "--out", str(out)]) == 2
    msg = capsys.readouterr().out
    assert "joint 'shoulder_pitch' needs" in msg and "N m of torque" in msg
    assert "against a limit of 3 N m" in msg and not out.exists()


# --- no useless success: the hand must end within --tolerance of the target --------------------

TOL_HAND = 5e-3  # [m] the CLI's default --tolerance (5 mm)
TOL_ROUND = 1e-4  # [m] the written meta rounds coordinates to 0.1 mm


def _written_hand(env, path) -> np.ndarray:
    """Where the written final posture puts the hand, by C MuJoCo's mj_kinematics: ``(3,)``."""
    from evojax_motion.run.export import read_trajectory

    return final_hand(env.robot, read_trajectory(path).q[-1:])[0]


def test_generate_normal_target_ends_within_tolerance(env, db_file, tmp_path, monkeypatch):
    prepare_cli(monkeypatch, cli_session(env, db_file))
    target = np.asarray(env.db.condition[5], np.float64) + 0.01
    out = tmp_path / "near.json"
    argv = ["generate", "--db", str(db_file), "--target", *map(str, target), "--out", str(out)]
    assert run_cli(argv) == 0
    assert np.linalg.norm(_written_hand(env, out) - target) <= TOL_HAND


def test_generate_unreachable_target_exits_2_with_the_miss(
    env, db_file, tmp_path, capsys, monkeypatch
):
    prepare_cli(monkeypatch, cli_session(env, db_file))
    out = tmp_path / "far.json"
    argv = ["generate", "--db", str(db_file), "--target", "1.5", "-0.3", "1.4", "--out", str(out)]
    capsys.readouterr()
    assert run_cli(argv) == 2
    msg = capsys.readouterr().out
    assert msg.startswith("error: ") and msg.count("\n") == 1
    assert "would miss it by" in msg and " mm" in msg and "nearest reachable point" in msg
    assert not out.exists()
    # --nearest: a motion whose hand ends within the tolerance of the reported nearest point
    assert run_cli([*argv, "--nearest"]) == 0
    printed = capsys.readouterr().out
    assert "using it (--nearest)" in printed
    from evojax_motion.run.export import read_trajectory

    point = np.asarray(read_trajectory(out).meta["target"])
    assert str([round(float(v), 4) for v in point]) in printed  # the point the output reports
    assert np.linalg.norm(_written_hand(env, out) - point) <= TOL_HAND + TOL_ROUND


def test_generate_miss_over_tolerance_exits_2(env, db_file, tmp_path, capsys, monkeypatch):
    """A reachable target still misses a tolerance below the motion's own miss: exit 2."""
    prepare_cli(monkeypatch, cli_session(env, db_file))
    target = [f"{v:.4f}" for v in env.db.condition[5] + 0.01]
    out = tmp_path / "tight.csv"
    argv = ["generate", "--db", str(db_file), "--target", *target, "--out", str(out)]
    capsys.readouterr()
    assert run_cli([*argv, "--tolerance", "1e-6"]) == 2
    msg = capsys.readouterr().out
    assert "the hand misses the target" in msg and "tolerance 1e-06 mm" in msg
    assert not out.exists()
    assert run_cli([*argv, "--tolerance", "0"]) == 2
    assert "--tolerance: expected a number > 0 [mm]" in capsys.readouterr().out


def test_projection_that_moves_the_hand_off_target_is_an_error(env, db_file, tmp_path):
    """The reported case: a joint-limit projection far off (71.4 rad) and a 324 mm miss: an error
    with the figures, not a note."""
    import argparse

    from evojax_motion.cli import online as online_cli

    model = cli_session(env, db_file)[0]
    motion = query(env, env.db.condition[5:6] + 0.01)
    # move the written final posture until the hand is ~0.3 m off the target
    q = np.array(motion.q)
    q[0, -1] = np.clip(q[0, -1] + 0.6, env.robot.lower, env.robot.upper)
    miss = np.linalg.norm(final_hand(env.robot, q[0, -1:])[0] - motion.target[0])
    assert miss > 0.05
    bad = motion._replace(q=q, limit_excess=np.array([71.4], np.float32))
    out = tmp_path / "bad.csv"
    args = argparse.Namespace(out=str(out), tolerance=5.0)
    with pytest.raises(online_cli.UserError) as err:
        online_cli._write(args, "csv", model, bad, 0, {})
    msg = str(err.value)
    assert f"by {miss * 1e3:.1f} mm" in msg
    assert "exceeded the joint limits by 71.4000 rad" in msg and "nothing written" in msg
    assert not out.exists()
