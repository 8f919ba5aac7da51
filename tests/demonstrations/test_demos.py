"""Synthetic human-like catching demonstrations (`evojax_motion.demonstrations.synthetic`).

The slow tests check the WHOLE default set (311 demonstrations, T = 100) of mahru_arm, generated
once per module, plus a small arm6 set with its own catch region.
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from evojax_motion.demonstrations.synthetic import (
    CITATIONS,
    generate_demonstrations,
    summarize_demonstrations,
)
from evojax_motion.demonstrations.workspace import (
    POSTURE_STD_MAX_DEG,
    REGION_AZIMUTH_HALF_DEG,
    REGION_RADIUS_FRACTION,
    ROBOT_PRESETS,
    derive_defaults,
)
from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import load_robot, robot_from_mjcf_text
from evojax_motion.motion.database import HUMAN
from evojax_motion.motion.objective import torque_cost
from evojax_motion.motion.timegrid import derivatives, make_time_grid
from evojax_motion.settings.demonstrations import CatchRegion, DemoSettings

TOL_END_SPEED = 1e-3  # [rad/s] joint speed at s = 0 and s = 1 (rest to rest)
TOL_CATCH = 5e-3  # [m] hand at the end vs the catch point (the brief's limit)
TOL_FK = 1e-5  # [m] float32 FK (dyn.site_pose) vs C MuJoCo mj_kinematics
TOL_REGION = 1e-4  # [m, rad] catch points inside the configured sector
SPEED_RIPPLE = 1e-3  # hand speed may dip this fraction of its peak and still count as one peak
TOL_COST_REL = 1e-4  # stored cost vs objective.torque_cost recomputed
HUMAN_DURATION_S = (0.4, 1.0)  # human reaching durations
DURATION_NOISE_SIGMAS = 3.0  # Fitts' law noise is clipped at 3 standard deviations
ARM6_REGION = CatchRegion("upper_link", (0.35, 0.6), (-30.0, 30.0), (-20.0, 20.0))
TREE_ARM = Path(__file__).parents[1] / "assets" / "tree_arm.xml"
CONTINUOUS_ARM = Path(__file__).parents[1] / "assets" / "continuous_arm.xml"
TOL_REACH_REL = 0.03  # derived reach (4096 postures) vs a 20 000-posture reference, relative
# A Franka-like arm (link offsets and joint ranges of the Franka Emika Panda, invented inertias)
# without a keyframe: the rest posture is qpos0 with joints 4 and 6 on their limits, moved off
# them by the robot; no preset.
FRANKA_LIKE = """
<mujoco model="franka_like">
  <compiler angle="radian" autolimits="true"/>
  <worldbody>
    <body name="link0">
      <inertial pos="-0.04 0 0.05" mass="0.63" diaginertia="0.003 0.003 0.003"/>
      <body name="link1" pos="0 0 0.333">
        <inertial pos="0 -0.04 -0.05" mass="4.97" diaginertia="0.70 0.70 0.009"/>
        <joint name="joint1" axis="0 0 1" range="-2.8973 2.8973"/>
        <body name="link2" quat="1 -1 0 0">
          <inertial pos="0 -0.07 0.03" mass="0.646" diaginertia="0.008 0.028 0.025"/>
          <joint name="joint2" axis="0 0 1" range="-1.7628 1.7628"/>
          <body name="link3" pos="0 -0.316 0" quat="1 1 0 0">
            <inertial pos="0.04 0.02 -0.04" mass="3.228" diaginertia="0.037 0.036 0.011"/>
            <joint name="joint3" axis="0 0 1" range="-2.8973 2.8973"/>
            <body name="link4" pos="0.0825 0 0" quat="1 1 0 0">
              <inertial pos="-0.05 0.05 0.03" mass="3.587" diaginertia="0.026 0.020 0.031"/>
              <joint name="joint4" axis="0 0 1" range="-3.0718 -0.0698"/>
              <body name="link5" pos="-0.0825 0.384 0" quat="1 -1 0 0">
                <inertial pos="0 0.04 -0.11" mass="1.226" diaginertia="0.036 0.029 0.009"/>
                <joint name="joint5" axis="0 0 1" range="-2.8973 2.8973"/>
                <body name="link6" quat="1 1 0 0">
                  <inertial pos="0.06 -0.01 0.01" mass="1.666" diaginertia="0.002 0.004 0.005"/>
                  <joint name="joint6" axis="0 0 1" range="-0.0175 3.7525"/>
                  <body name="link7" pos="0.088 0 0" quat="1 1 0 0">
                    <inertial pos="0 0 0.08" mass="0.735" diaginertia="0.013 0.010 0.005"/>
                    <joint name="joint7" axis="0 0 1" range="-2.8973 2.8973"/>
                    <site name="attachment_site" pos="0 0 0.107"/>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="joint1" forcerange="-87 87"/>
    <motor joint="joint2" forcerange="-87 87"/>
    <motor joint="joint3" forcerange="-87 87"/>
    <motor joint="joint4" forcerange="-87 87"/>
    <motor joint="joint5" forcerange="-12 12"/>
    <motor joint="joint6" forcerange="-12 12"/>
    <motor joint="joint7" forcerange="-12 12"/>
  </actuator>
</mujoco>
"""


@pytest.fixture(scope="module")
def mahru():
    robot = load_robot("mahru_arm")
    return robot, make_dynamics(robot, backend="rnea")


@pytest.fixture(scope="module")
def default_set(mahru):
    robot, dyn = mahru
    return generate_demonstrations(robot, dyn, DemoSettings(), jax.random.key(0))


@pytest.fixture(scope="module")
def hand(mahru, default_set):
    """Hand positions ``(N, T, 3)`` along every demonstration, by dyn.site_pose."""
    _, dyn = mahru
    db, _ = default_set
    fk = jax.jit(jax.vmap(jax.vmap(lambda q: dyn.site_pose(q)[0])))
    return np.asarray(fk(jnp.asarray(db.q)))


def _mj_site(robot, q):
    d = mujoco.MjData(robot.mj_model)
    d.qpos[robot.qpos_adr] = q
    mujoco.mj_kinematics(robot.mj_model, d)
    return d.site_xpos[robot.site_id].copy()


def _end_speeds(db):
    qd, _ = derivatives(make_time_grid(db.q.shape[1]), jnp.asarray(db.q), jnp.asarray(db.duration))
    return np.abs(np.asarray(qd)[:, [0, -1]]).max(axis=(1, 2))


@pytest.mark.slow
def test_default_set_size_and_provenance(default_set):
    db, report = default_set
    assert db.q.shape == (311, 100, 7)
    assert db.valid.all() and (db.origin == HUMAN).all() and (db.generation == 0).all()
    assert report["synthetic"] is True and report["count"] == 311
    assert "Flash & Hogan 1985" in report["description"] and "Fitts 1954" in report["description"]
    assert any("Fitts (1954)" in c for c in report["citations"]) and len(CITATIONS) >= 5
    assert report["candidates_valid"] >= 311 and report["candidates_tried"] >= 311
    assert np.isfinite(db.q).all() and np.isfinite(db.cost).all() and (db.cost > 0).all()


@pytest.mark.slow
def test_every_demo_inside_joint_limits(mahru, default_set):
    robot, _ = mahru
    db, report = default_set
    margin = np.minimum(db.q - robot.lower, robot.upper - db.q).min(axis=(0, 1))
    assert np.all(margin >= np.deg2rad(DemoSettings().limit_margin_deg))
    np.testing.assert_allclose(
        list(report["min_limit_margin_deg"].values()), np.rad2deg(margin), atol=0.01
    )


@pytest.mark.slow
def test_every_demo_starts_and_ends_at_rest(mahru, default_set):
    robot, _ = mahru
    db, _ = default_set
    np.testing.assert_array_equal(db.q[:, 0], np.broadcast_to(robot.rest, (311, 7)).astype("f4"))
    assert np.max(_end_speeds(db)) <= TOL_END_SPEED


@pytest.mark.slow
def test_every_demo_ends_on_its_catch_point(mahru, default_set, hand):
    robot, _ = mahru
    db, report = default_set
    catch = np.asarray(report["catch_points"])
    assert np.max(np.linalg.norm(hand[:, -1] - catch, axis=-1)) <= TOL_CATCH
    np.testing.assert_allclose(db.condition, hand[:, -1], atol=TOL_FK)  # condition = FK at the end
    for i in range(0, 311, 62):  # the JAX kinematics agree with C MuJoCo
        np.testing.assert_allclose(_mj_site(robot, db.q[i, -1]), hand[i, -1], atol=TOL_FK)
        np.testing.assert_allclose(_mj_site(robot, db.q[i, 50]), hand[i, 50], atol=TOL_FK)


@pytest.mark.slow
def test_catch_points_fill_the_region(default_set):
    _, report = default_set
    region = ROBOT_PRESETS["mahru_arm"].region
    rel = np.asarray(report["catch_points"]) - np.asarray(report["region"]["centre_m"])
    r = np.linalg.norm(rel, axis=1)
    az = np.rad2deg(np.arctan2(rel[:, 1], rel[:, 0]))
    el = np.rad2deg(np.arcsin(rel[:, 2] / r))
    for value, (lo, hi) in (
        (r, region.radius),
        (az, region.azimuth_deg),
        (el, region.elevation_deg),
    ):
        assert value.min() >= lo - TOL_REGION and value.max() <= hi + TOL_REGION
        # low-discrepancy fill: every tenth of each range is populated
        counts = np.histogram(value, bins=10, range=(lo, hi))[0]
        assert counts.min() >= 10


@pytest.mark.slow
def test_hand_speed_is_single_peaked(default_set, hand):
    db, _ = default_set
    grid = make_time_grid(db.q.shape[1])
    speed = np.linalg.norm(np.einsum("ts,nsk->ntk", grid.d1, hand), axis=-1) / db.duration[:, None]
    peak = speed.max(axis=1)
    k = speed.argmax(axis=1)
    for i in range(len(speed)):
        rise, fall = np.diff(speed[i, : k[i] + 1]), np.diff(speed[i, k[i] :])
        assert rise.min(initial=0.0) >= -SPEED_RIPPLE * peak[i], i
        assert fall.max(initial=0.0) <= SPEED_RIPPLE * peak[i], i
    assert np.all((k > 10) & (k < 90))  # the peak is inside the motion, not at an end
    assert np.max(speed[:, [0, -1]]) < 1e-3 * peak.min()


@pytest.mark.slow
def test_durations_follow_fitts_law(default_set, hand):
    db, report = default_set
    st = DemoSettings()
    lo, hi = HUMAN_DURATION_S
    assert db.duration.min() >= lo and db.duration.max() <= hi
    travel = np.linalg.norm(hand[:, -1] - hand[:, 0], axis=1)
    fitts = st.fitts_a + st.fitts_b * np.log2(np.maximum(2 * travel / st.target_width, 1.0))
    ratio = db.duration / fitts
    bound = np.exp(DURATION_NOISE_SIGMAS * st.duration_noise) * (1 + 1e-5)
    stretched = ratio > bound
    assert stretched.sum() <= report["duration_stretched"] <= 311 // 10
    assert np.all(ratio >= 1 / bound)  # never shorter than Fitts' law allows
    assert np.corrcoef(db.duration, fitts)[0, 1] > 0.5


@pytest.mark.slow
def test_costs_are_eq5_torque_costs(mahru, default_set):
    _, dyn = mahru
    db, _ = default_set
    grid = make_time_grid(db.q.shape[1])
    rows = np.array([0, 155, 310])
    cost = jax.jit(jax.vmap(lambda q, d: torque_cost(dyn, grid, q, d)))(
        jnp.asarray(db.q[rows]), jnp.asarray(db.duration[rows])
    )
    np.testing.assert_allclose(db.cost[rows], cost, rtol=TOL_COST_REL)


@pytest.mark.slow
def test_deterministic_for_a_key_and_different_for_another(mahru, default_set):
    robot, dyn = mahru
    db, _ = default_set
    again, _ = generate_demonstrations(robot, dyn, DemoSettings(), jax.random.key(0))
    for name, a, b in zip(db._fields, db, again):
        assert np.array_equal(a, b), name
    other, other_report = generate_demonstrations(robot, dyn, DemoSettings(), jax.random.key(1))
    assert other.valid.sum() == 311
    assert not np.allclose(other.condition, db.condition, atol=1e-3)
    assert np.median(np.abs(other.duration - db.duration)) > 1e-3
    assert np.max(_end_speeds(other)) <= TOL_END_SPEED
    assert other_report["catch_miss_max_m"] <= TOL_CATCH


@pytest.mark.slow
def test_summary_matches_database(mahru, default_set):
    robot, _ = mahru
    db, report = default_set
    summary = summarize_demonstrations(db, robot)
    assert summary["count"] == 311 and summary["samples"] == 100
    assert summary["duration_min_s"] == pytest.approx(float(db.duration.min()))
    assert summary["duration_max_s"] == pytest.approx(float(db.duration.max()))
    assert summary["duration_mean_s"] == pytest.approx(float(db.duration.mean()), rel=1e-6)
    assert summary["min_limit_margin_deg"] == pytest.approx(
        report["min_limit_margin_deg"], abs=0.01
    )
    assert summary["max_end_speed_rad_s"] <= TOL_END_SPEED
    np.testing.assert_allclose(summary["catch_max_m"], db.condition.max(axis=0), atol=1e-4)


@pytest.fixture(scope="module")
def arm6():
    robot = load_robot("arm6")
    return robot, make_dynamics(robot, backend="rnea")


@pytest.mark.slow
def test_arm6_with_its_own_region(arm6):
    robot, dyn = arm6
    settings = DemoSettings(count=8, samples=32, region=ARM6_REGION)
    db, report = generate_demonstrations(robot, dyn, settings, jax.random.key(3))
    assert db.q.shape == (8, 32, 6) and db.valid.all()
    assert np.all(db.q >= robot.lower) and np.all(db.q <= robot.upper)
    np.testing.assert_array_equal(db.q[:, 0], np.broadcast_to(robot.rest, (8, 6)).astype("f4"))
    assert np.max(_end_speeds(db)) <= TOL_END_SPEED
    catch = np.asarray(report["catch_points"])
    ends = np.stack([_mj_site(robot, q) for q in db.q[:, -1]])
    assert np.max(np.linalg.norm(ends - catch, axis=1)) <= TOL_CATCH
    centre = np.asarray(report["region"]["centre_m"])
    np.testing.assert_allclose(centre, [0.05, 0.0, 0.78], atol=1e-6)  # upper_link origin
    r = np.linalg.norm(catch - centre, axis=1)
    assert r.min() >= ARM6_REGION.radius[0] - TOL_REGION
    assert r.max() <= ARM6_REGION.radius[1] + TOL_REGION


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"count": 0}, "count"),
        ({"samples": 4}, "samples"),
        ({"fitts_a": -0.1}, "fitts_a"),
        ({"duration_noise": 0.9}, "duration_noise"),
        ({"arc_blend": 1.5}, "arc_blend"),
        ({"comfort_joints": ("elbow",)}, "comfort_deg"),
        ({"comfort_joints": ("elbow",), "comfort_deg": (1.0, 2.0)}, "comfort_deg"),
        ({"posture_weight": (0.0,)}, "posture_weight"),
        ({"posture_std_deg": (-1.0,)}, "posture_std_deg"),
        ({"ik_iters": True}, "ik_iters"),
    ],
)
def test_settings_validation_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=rf"^{field}: expected"):
        DemoSettings(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"radius": (0.5, 0.3)}, "radius"),
        ({"radius": (0.0, 0.3)}, "radius"),
        ({"azimuth_deg": (-400.0, 0.0)}, "azimuth_deg"),
        ({"azimuth_deg": (-100.0, 300.0)}, "azimuth_deg"),  # more than one turn
        ({"elevation_deg": (10.0,)}, "elevation_deg"),
        ({"frame": ""}, "frame"),
    ],
)
def test_region_validation_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=rf"^{field}: expected"):
        CatchRegion(**kwargs)


def test_robot_specific_settings_are_checked_against_the_robot(mahru):
    robot, dyn = mahru
    cases = [
        (DemoSettings(region=CatchRegion(frame="no_such_body")), "demos.region.frame"),
        (DemoSettings(comfort_joints=("knee",), comfort_deg=(10.0,)), "demos.comfort_joints"),
        (DemoSettings(posture_std_deg=(1.0, 2.0)), "demos.posture_std_deg"),
    ]
    for settings, where in cases:
        with pytest.raises(UserError, match=where):
            generate_demonstrations(robot, dyn, settings, jax.random.key(0))
    outside = DemoSettings(comfort_joints=("elbow",), comfort_deg=(170.0,))  # range 0..145
    with pytest.raises(UserError, match=r"^demos\.comfort_deg: joint 'elbow' at 170 deg"):
        generate_demonstrations(robot, dyn, outside, jax.random.key(0))


def test_a_rest_posture_near_a_limit_is_named_before_any_trial():
    """tree_arm has no keyframe: its l_elbow rests at qpos0 = 0, on its limit, moved 5 % of the
    range (7.2 deg) off it by the robot. A margin wider than that fails every trial; the error
    names the joint and the rest posture, not the catch region."""
    custom = robot_from_mjcf_text("custom", TREE_ARM.read_text(), site="tip")
    k = custom.joint_names.index("l_elbow")
    gap = np.rad2deg(custom.rest[k] - custom.lower[k])
    assert gap == pytest.approx(0.05 * np.rad2deg(2.5))
    settings = DemoSettings(limit_margin_deg=10.0)
    with pytest.raises(UserError, match=r"^demos\.limit_margin_deg: the rest posture .* 'l_elbow'"):
        generate_demonstrations(custom, make_dynamics(custom), settings, jax.random.key(0))


def test_a_run_keeps_its_synthesised_demonstrations(tmp_path, monkeypatch, capsys):
    """With the compilation cache on, `run.workflow.demonstrations` synthesises a config's
    demonstrations once and reads them back in later runs (bit for bit, no synthesis); a
    damaged file is reported and synthesised again; without a cache key nothing is kept."""
    from evojax_motion.demonstrations import synthetic as demos
    from evojax_motion.run import cache as compile_cache
    from evojax_motion.run import workflow
    from evojax_motion.settings import load_config

    # another seed than tiny.yaml's: none shipped (`demonstrations.shipped`)
    cfg = load_config(
        Path(__file__).resolve().parents[2] / "configs" / "tiny.yaml", overrides=["demos.seed=1"]
    )
    robot, dyn = workflow.make_robot_dynamics(cfg)
    parts = workflow.cache_parts(cfg, robot, dyn)
    kept = compile_cache.result_path({"result": "demonstrations", "parts": parts})
    assert kept is not None and kept.parent.name == compile_cache.RESULTS_DIR  # conftest's cache
    path = tmp_path / "results" / "demos.npz"
    monkeypatch.setattr(compile_cache, "result_path", lambda parts, suffix=".npz": path)
    calls, made = [], []
    synthesise = demos.generate_demonstrations

    def counted(*args, **kwargs):  # synthesises once; later calls return that result again
        calls.append(1)
        made[:] = made or [synthesise(*args, **kwargs)]
        return made[0]

    monkeypatch.setattr(demos, "generate_demonstrations", counted)

    def same(a, b):
        for x, y in zip(a[0], b[0], strict=True):
            assert np.asarray(x).dtype == np.asarray(y).dtype
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
        assert a[1] == b[1]

    first = workflow.demonstrations(cfg, robot, dyn, parts)
    assert len(calls) == 1 and path.is_file()
    same(workflow.demonstrations(cfg, robot, dyn, parts), first)
    assert len(calls) == 1  # read back, not synthesised
    path.write_bytes(b"damaged")
    same(workflow.demonstrations(cfg, robot, dyn, parts), first)
    assert len(calls) == 2 and "cached demonstrations unreadable" in capsys.readouterr().err
    same(workflow.demonstrations(cfg, robot, dyn, parts), first)
    assert len(calls) == 2  # written anew
    path.unlink()
    same(workflow.demonstrations(cfg, robot, dyn), first)  # no key: nothing kept
    assert len(calls) == 3 and not path.exists()


@pytest.fixture(scope="module")
def franka_like():
    return robot_from_mjcf_text("franka_like", FRANKA_LIKE)


def _reference_reach(robot, body: str, n: int = 20_000) -> float:
    """Largest distance of the site from ``body``'s rest origin over ``n`` postures drawn
    uniformly within the limits (continuous joints: a full turn), by C MuJoCo."""
    m, d = robot.mj_model, mujoco.MjData(robot.mj_model)
    d.qpos[robot.qpos_adr] = robot.rest
    mujoco.mj_kinematics(m, d)
    centre = d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)].copy()
    lo = np.where(robot.continuous, -np.pi, robot.lower)
    hi = np.where(robot.continuous, np.pi, robot.upper)
    reach = 0.0
    for q in np.random.default_rng(1).uniform(lo, hi, (n, robot.n_joints)):
        d.qpos[robot.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        reach = max(reach, float(np.linalg.norm(d.site_xpos[robot.site_id] - centre)))
    return reach


def test_defaults_derived_for_an_arm_without_preset(franka_like):
    """No keyframe, no preset: the comfortable posture is rest moved into the central half of
    each range (joints 4 and 6 rest near their limits), the noise 4 % of a range at most 8 deg,
    the region a shell sector around the shoulder (link2, on joint 1's axis) at 0.5-0.75 of the
    reach, in front (+x: the hand rests nearly above the shoulder)."""
    robot = franka_like
    d = derive_defaults(robot)
    span = robot.upper - robot.lower
    expected = np.rad2deg(robot.rest)
    expected[3] = np.rad2deg(robot.upper[3] - 0.25 * span[3])  # rest -0.22 rad: beyond -0.82
    expected[5] = np.rad2deg(robot.lower[5] + 0.25 * span[5])  # rest 0.17 rad: below 0.93
    np.testing.assert_allclose(list(d.comfort_deg.values()), expected, atol=1e-9)
    std = np.minimum(np.rad2deg(0.04 * span), POSTURE_STD_MAX_DEG)
    np.testing.assert_allclose(list(d.posture_std_deg.values()), std, atol=1e-9)
    assert std[3] < POSTURE_STD_MAX_DEG  # joint 4's 172 deg range: 6.9 deg
    assert d.region.frame == "link2"
    assert d.region.azimuth_deg == (-REGION_AZIMUTH_HALF_DEG, REGION_AZIMUTH_HALF_DEG)
    reach = _reference_reach(robot, "link2")
    lo, hi = REGION_RADIUS_FRACTION
    assert d.region.radius[1] == pytest.approx(hi * reach, rel=TOL_REACH_REL)
    assert d.region.radius[0] == pytest.approx(lo * reach, rel=TOL_REACH_REL)


def test_derived_defaults_of_continuous_joints_are_about_rest():
    """continuous_arm: spin and twist have no range; their comfortable angle is rest (spin
    rests 2.5 rad from 0) and their noise the largest; the limited joints follow their ranges."""
    robot = load_robot(CONTINUOUS_ARM)
    d = derive_defaults(robot)
    comfort = np.deg2rad(list(d.comfort_deg.values()))
    np.testing.assert_allclose(comfort[robot.continuous], robot.rest[robot.continuous])
    std = np.array(list(d.posture_std_deg.values()))
    np.testing.assert_allclose(std[robot.continuous], POSTURE_STD_MAX_DEG)
    span = (robot.upper - robot.lower)[~robot.continuous]
    np.testing.assert_allclose(std[~robot.continuous], np.rad2deg(0.04 * span))


def test_an_end_effector_that_does_not_move_is_an_empty_workspace():
    xml = """<mujoco><compiler angle="radian"/><worldbody><body name="b">
      <joint name="j" axis="0 0 1" range="-1 1"/><geom size="0.1"/><site name="s" pos="0 0 0.3"/>
      </body></worldbody></mujoco>"""
    robot = robot_from_mjcf_text("spinner", xml)
    with pytest.raises(UserError, match=r"^robot 'spinner': the end effector 's' .* empty"):
        derive_defaults(robot)


@pytest.mark.slow
def test_an_arm_without_preset_or_keyframe_gets_its_demonstrations(franka_like):
    """The Franka-like arm with every demos setting at its default: every trial of the set
    valid, inside the limits with the margin, rest to rest, ending on its catch point."""
    robot = franka_like
    settings = DemoSettings(count=8, samples=24)
    db, report = generate_demonstrations(robot, make_dynamics(robot), settings, jax.random.key(0))
    assert report["robot_defaults"] == "derived from the robot" and db.valid.sum() == 8
    margin = np.minimum(db.q - robot.lower, robot.upper - db.q).min()
    assert margin >= np.deg2rad(settings.limit_margin_deg)
    np.testing.assert_array_equal(db.q[:, 0], np.broadcast_to(robot.rest, (8, 7)).astype("f4"))
    catch = np.asarray(report["catch_points"])
    ends = np.stack([_mj_site(robot, q) for q in db.q[:, -1]])
    assert np.max(np.linalg.norm(ends - catch, axis=1)) <= TOL_CATCH


@pytest.mark.slow
def test_a_region_beyond_reach_is_named_with_figures(arm6):
    """Catch points 1.1-1.3 m from arm6's shoulder (it reaches about 1 m): the error counts
    the missed points, says how far the hand reaches and blames the region."""
    robot, dyn = arm6
    far = CatchRegion("upper_link", (1.1, 1.3), (-30.0, 30.0), (-20.0, 20.0))
    settings = DemoSettings(count=8, samples=32, region=far, max_rounds=1)
    with pytest.raises(UserError) as err:
        generate_demonstrations(robot, dyn, settings, jax.random.key(3))
    text = str(err.value)
    assert text.startswith("demos: only 0 of 10 candidate trials passed")
    assert "10 missed the catch point" in text
    assert "10 of them farther from body 'upper_link' than the hand reaches" in text
    assert "move demos.region inside the robot's reach" in text
