"""Physics rollouts (online/simulate.py, cli/simulate.py): the reference against the plan, the
simulation model and the ball's flight against closed forms, tracking of a feasible plan, a plan
beyond the torque limits, a simulated catch that succeeds and the same plan started late that
fails, and the ``simulate`` command's files and refusals."""

from __future__ import annotations

import json
import re

import jax
import mujoco
import numpy as np
import pytest
from online_support import (
    catcher,
    cli_session,
    mj_inverse_torques,
    online_env,
    prepare_cli,
    query,
    run_cli,
    save_env_database,
)

from evojax_motion.online.simulate import (
    Ball,
    Plan,
    reference,
    simulate,
    simulation_model,
    summarise,
)
from evojax_motion.settings.online import SimSettings

SETTINGS = SimSettings()
GRAVITY = np.array([0.0, 0.0, -9.81])
TOL_REF = 1e-9  # the reference passes through the plan's samples (float64 Hermite pieces)
TOL_FLIGHT = 1e-9  # m: MuJoCo's semi-implicit Euler flight vs its closed form
TOL_TRACK_RAD = 2e-3  # rad: a feasible plan, 8 Hz computed-torque feedback, 2 ms steps
TOL_TRACK_MM = 2.0  # mm: the same at the hand
LATE = 0.3  # s: the late plan's delay
CATCH_T = 0.8  # s: the test ball passes the catch point this long after release


@pytest.fixture(scope="module")
def env():
    return online_env()


@pytest.fixture(scope="module")
def reach(env):
    """A feasible motion to a target near a database condition, as a `Plan`."""
    r = query(env, env.db.condition[:1] + 0.01)
    assert r.ok[0]
    return Plan(r.t[0], r.q[0], r.qd[0], r.qdd[0])


@pytest.fixture(scope="module")
def throw(env):
    """A ball through database condition 5 at 0.8 s, its planned catch and motion."""
    p0 = np.array([3.0, -0.2, 1.6])
    v0 = (env.db.condition[5] - p0 - 0.5 * GRAVITY * CATCH_T**2) / CATCH_T
    rest = np.asarray(env.robot.rest, np.float32)[None]
    plan, motion = jax.device_get(
        catcher()[1](env.db_device, p0[None].astype(np.float32), v0[None].astype(np.float32), rest)
    )
    assert plan.feasible[0] and motion.ok[0]
    ball = Ball(p0.astype(np.float32).astype(float), v0.astype(np.float32).astype(float))
    return ball, plan, Plan(motion.t[0], motion.q[0], motion.qd[0], motion.qdd[0])


def test_reference_passes_through_the_plan_and_rests_outside_it(reach):
    q, qd, qdd = reference(reach, reach.t)
    np.testing.assert_allclose(q, reach.q, atol=TOL_REF)
    np.testing.assert_allclose(qd, reach.qd, atol=TOL_REF)
    np.testing.assert_allclose(qdd, reach.qdd, atol=TOL_REF)
    before_after = np.array([-0.2, float(reach.t[-1]) + 0.2])
    q, qd, qdd = reference(reach, before_after)
    np.testing.assert_allclose(q, reach.q[[0, -1]], atol=TOL_REF)
    assert not qd.any() and not qdd.any()


def test_simulation_model_adds_a_colliding_ball(env):
    """The ball is a free body of the world that collides with every robot geom; the robot does
    not collide with itself; constraints and contacts on, the model's actuators off."""
    m = simulation_model(env.robot, SETTINGS, Ball(np.zeros(3), np.zeros(3)))
    robot = env.robot.mj_model
    assert m.nq == robot.nq + 7 and m.nv == robot.nv + 6
    ball = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "evojax_ball")
    assert m.body_parentid[ball] == 0 and m.jnt_type[m.body_jntadr[ball]] == 0  # free joint
    np.testing.assert_allclose(m.body_mass[ball], SETTINGS.ball_mass)

    def collide(a, b):
        return bool(m.geom_contype[a] & m.geom_conaffinity[b]) or bool(
            m.geom_contype[b] & m.geom_conaffinity[a]
        )

    sphere = int(np.flatnonzero(m.geom_bodyid == ball)[0])
    hand = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "hand")
    forearm = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "forearm")
    assert collide(sphere, hand) and not collide(hand, forearm)
    flags = mujoco.mjtDisableBit
    assert not m.opt.disableflags & (int(flags.mjDSBL_CONTACT) | int(flags.mjDSBL_CONSTRAINT))
    assert m.opt.disableflags & int(flags.mjDSBL_ACTUATION)


def test_ball_flies_as_the_integrator_says(env, reach):
    """A ball thrown away from the robot: positions are MuJoCo's semi-implicit Euler flight,
    ``p0 + v0 t + g t^2 / 2 + g dt t / 2`` (within ~5 mm of the vacuum parabola over 1 s)."""
    ball = Ball(np.array([2.0, 2.0, 1.0]), np.array([1.0, 0.5, 3.0]))
    rollout = simulate(env.robot, reach, SETTINGS, ball, t_end=1.0)
    dt = float(env.robot.mj_model.opt.timestep)
    t = rollout.time[:, None]
    expected = ball.p0 + ball.v0 * t + 0.5 * GRAVITY * t**2 + 0.5 * GRAVITY * dt * t
    np.testing.assert_allclose(rollout.ball, expected, atol=TOL_FLIGHT)
    assert not rollout.captured.any()


def test_feasible_plan_is_tracked_closely(env, reach):
    summary = summarise(simulate(env.robot, reach, SETTINGS), with_ball=False)
    assert summary.tracking_max <= TOL_TRACK_RAD and summary.hand_max_mm <= TOL_TRACK_MM
    assert summary.at_torque_limit == 0.0 and summary.caught is None


def test_plan_beyond_the_torque_limits_saturates(env, reach):
    """The same path four times faster asks for more torque than the joints have: the rollout
    sits at a limit and tracks far worse (what time scaling prevents online)."""
    fast = Plan(reach.t / 4, reach.q, reach.qd * 4, reach.qdd * 16)
    ff = np.abs(mj_inverse_torques(env.robot, *fast[1:]))
    assert (ff.max(0) > env.robot.torque_limit).any()
    summary = summarise(simulate(env.robot, fast, SETTINGS), with_ball=False)
    assert summary.at_torque_limit > 0.05
    assert summary.tracking_max > 10 * TOL_TRACK_RAD


def test_catch_succeeds_and_the_same_plan_started_late_fails(env, throw):
    """On time the ball reaches the palm, slowly enough to be gripped; 0.3 s late the hand is
    still on its way when the ball passes: the criterion fails, with the closest distance."""
    ball, plan, motion = throw
    t_end = float(plan.catch_time[0]) + SETTINGS.hold
    rollout = simulate(env.robot, motion, SETTINGS, ball, t_end)
    on_time = summarise(rollout, with_ball=True)
    assert on_time.caught
    assert abs(on_time.capture_time - float(plan.catch_time[0])) <= 0.05
    k = int(np.argmax(rollout.captured))
    assert rollout.distance[k] <= SETTINGS.capture_radius
    assert rollout.relative_speed[k] <= SETTINGS.max_relative_speed
    assert on_time.tracking_max <= 10 * TOL_TRACK_RAD  # the ball's knock included

    late = motion._replace(t=motion.t + LATE)
    missed = summarise(simulate(env.robot, late, SETTINGS, ball, t_end + LATE), with_ball=True)
    assert missed.caught is False and np.isnan(missed.capture_time)
    assert missed.closest_distance > SETTINGS.capture_radius


def test_settings_validation():
    with pytest.raises(ValueError, match=r"^capture_radius: expected a number > 0 m"):
        SimSettings(capture_radius=0.0)
    with pytest.raises(ValueError, match=r"^hold: expected"):
        SimSettings(hold=float("nan"))
    assert SETTINGS.max_relative_speed == pytest.approx(10.0)


# -------------------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def db_file(tmp_path_factory, env):
    return save_env_database(tmp_path_factory.mktemp("simulate"), env)


def test_cli_simulate(env, throw, db_file, tmp_path, capsys, monkeypatch):
    """``simulate --ball``: summary, simulation.json and an animation; ``--delay`` misses; bad
    input is one line, exit 2, nothing written."""
    from PIL import Image

    prepare_cli(monkeypatch, cli_session(env, db_file))
    ball, plan, _ = throw
    args = ["simulate", "--db", str(db_file), "--horizon", "1.2", "--renderer", "stick"]
    args += ["--ball", *(f"{x:.6f}" for x in np.r_[ball.p0, ball.v0])]
    out = tmp_path / "sim"
    assert run_cli([*args, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "caught" in text and "yes, at t =" in text and "tracking error" in text
    doc = json.loads((out / "simulation.json").read_text())
    assert doc["task"] == "catch" and doc["result"]["caught"] is True
    assert doc["catch_time"] == pytest.approx(float(plan.catch_time[0]))
    assert doc["controller"]["bandwidth_hz"] == SETTINGS.bandwidth
    assert doc["catch_criterion"]["capture_radius"] == SETTINGS.capture_radius
    assert doc["result"]["closest_distance"] <= SETTINGS.capture_radius
    assert doc["renderer"].startswith("stick")
    frames = len(np.arange(0.0, doc["steps"] * doc["controller"]["timestep"], 1 / SETTINGS.fps))
    with Image.open(out / "simulation.gif") as gif:  # Pillow merges identical frames
        shown = 0
        for k in range(gif.n_frames):
            gif.seek(k)
            shown += gif.info["duration"]
    assert gif.n_frames > frames // 2 and shown == frames * round(1000 / SETTINGS.fps)

    assert run_cli([*args, "--out", str(out)]) == 2  # refuses to overwrite
    assert "already holds simulation.json" in capsys.readouterr().out
    assert run_cli([*args, "--delay", "0.3"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"^caught +no \(closest \d+\.\d mm", text, re.MULTILINE)
    assert "started 0.300 s late" in text

    bad = tmp_path / "bad"
    for extra, why in (
        (["--delay", "-1"], "--delay: expected"),
        (["--duration", "0.5"], "--duration: only with --target"),
    ):
        assert run_cli([*args, *extra, "--out", str(bad)]) == 2
        assert why in capsys.readouterr().out
    far = ["simulate", "--db", str(db_file), "--target", "1.5", "-0.3", "1.4", "--out", str(bad)]
    assert run_cli(far) == 2
    assert "outside the reachable region" in capsys.readouterr().out
    assert not bad.exists()
