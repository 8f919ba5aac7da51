"""Retargeting (evojax_motion.demonstrations.mocap.retarget): key points, scaling, batched
key-point IK, segmentation and resampling. References: C MuJoCo kinematics, trajectories the robot
itself produced (their key points are reachable, so the IK must find them), analytic speed
profiles."""

import functools
from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest

from evojax_motion.demonstrations.mocap import retarget as rt
from evojax_motion.demonstrations.mocap.markers import TrialError
from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.objective import torque_cost
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.demonstrations import IKSettings

TOL_FK = 1e-5  # [m] float32 FK vs C MuJoCo
TOL_IK = 1e-3  # [m] reachable key points, after the warm-up and 4 LM iterations per frame
TOL_LIMIT = 1e-6  # [rad]
B, F = 2, 64  # IK test shapes (one compilation per robot)
ROBOTS = Path(__file__).resolve().parents[3] / "shared" / "robots"  # published arms, unedited
GEN3 = ROBOTS / "kinova_gen3" / "gen3.xml"
XARM7 = ROBOTS / "ufactory_xarm7" / "xarm7_nohand.xml"


def _published(path):
    if not path.is_file():
        pytest.skip(
            f"{path.name}: the published robot models (folder 'shared/robots' beside the "
            "repository) are not here"
        )
    return load_robot(path)


@pytest.fixture(scope="module")
def mahru():
    robot = load_robot("mahru_arm")
    return robot, make_dynamics(robot)


@pytest.fixture(scope="module")
def arm6():
    robot = load_robot("arm6")
    return robot, make_dynamics(robot)


def _mujoco_points(robot, kp, q):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    d.qpos[robot.qpos_adr] = q
    mujoco.mj_kinematics(m, d)
    return np.stack([d.site_xpos[robot.site_id] if b < 0 else d.xpos[b] for b in kp.body_ids])


@pytest.mark.parametrize("name", ["mahru_arm", "arm6"])
def test_default_keypoints_match_mujoco(name, mahru, arm6):
    robot, dyn = mahru if name == "mahru_arm" else arm6
    kp = rt.robot_keypoints(robot)
    assert kp.human == ("shoulder", "elbow", "wrist", "hand")
    assert kp.robot[-1] == f"site:{robot.site_name}"
    # mahru's upper arm hangs as a person's: every key point; arm6's cannot: the hand only
    expected_w = (1.0, 1.0, 1.0, 1.0) if name == "mahru_arm" else (0.0, 0.0, 0.0, 1.0)
    assert kp.weights == expected_w
    q = np.clip(np.asarray(robot.rest) + 0.3, robot.lower, robot.upper)
    np.testing.assert_allclose(
        rt.rest_keypoints(dyn, kp, q), _mujoco_points(robot, kp, q), atol=TOL_FK
    )


def test_keypoint_maps_custom_guessed_and_bad(mahru):
    robot, _ = mahru
    kp = rt.robot_keypoints(robot, {"forearm": "elbow", "hand": "hand"}, {"elbow": 0.5})
    assert kp.robot == ("body:forearm", "site:hand") and kp.weights == (0.5, 1.0)
    assert rt.guess_keypoints(robot) == {
        "body:upper_arm": "shoulder",
        "body:forearm": "elbow",
        "body:hand": "wrist",
        "site:hand": "hand",
    }
    for mapping, match in [
        ({"body:nope": "elbow", "hand": "hand"}, "no body"),
        ({"site:other": "elbow", "hand": "hand"}, "end-effector site"),
        ({"forearm": "elbow"}, "need the hand"),
        ({"forearm": "knee", "hand": "hand"}, "expected a key point"),
    ]:
        with pytest.raises(UserError, match=match):
            rt.robot_keypoints(robot, mapping)
    with pytest.raises(UserError, match="weight"):
        rt.robot_keypoints(robot, None, {"hand": -1.0})
    assert rt.parse_pairs("a=b, c=d", "--x") == {"a": "b", "c": "d"}
    with pytest.raises(UserError):
        rt.parse_weights("hand=x")


def test_keypoints_from_the_kinematic_chain(arm6):
    """arm6's joints and bodies carry other names than mahru's; the kinematic rule (shoulder after
    the base yaw, elbow and wrist at the first and last bending joint) finds its arm."""
    robot, _ = arm6
    assert rt.guess_keypoints(robot) == {
        "body:upper_link": "shoulder",
        "body:fore_link": "elbow",
        "body:wrist_head": "wrist",
        "site:tool": "hand",
    }
    assert rt.base_height(robot) == pytest.approx(0.6)  # the turret's origin


@pytest.mark.parametrize(
    "path, expected",
    [
        (
            GEN3,
            {
                "body:half_arm_1_link": "shoulder",  # joint_2: joint_1 is the base yaw
                "body:forearm_link": "elbow",  # joint_4: joint_3 rolls about the upper arm
                "body:spherical_wrist_2_link": "wrist",  # joint_6
                "site:pinch_site": "hand",
            },
        ),
        (
            XARM7,
            {
                "body:link2": "shoulder",
                "body:link4": "elbow",
                "body:link6": "wrist",  # at the same point as joint5, a roll
                "site:attachment_site": "hand",
            },
        ),
    ],
    ids=["gen3", "xarm7"],
)
def test_published_arms_keypoints_and_weights(path, expected):
    """Names such as Gen3's ``shoulder_link`` (joint_1's body, 13 cm below the shoulder pivot)
    do not mislead the rule. Neither arm's upper arm can hang (joint_2 stops 52 / 60 deg short
    of straight down): the hand alone is matched."""
    robot = _published(path)
    assert rt.guess_keypoints(robot) == expected
    kp = rt.robot_keypoints(robot)
    assert kp.weights == (0.0, 0.0, 0.0, 1.0)
    ids = dict(zip(kp.human, kp.body_ids))
    assert not rt.upper_arm_can_hang(robot, ids["shoulder"], ids["elbow"])
    # user weights still win
    assert rt.robot_keypoints(robot, None, {"wrist": 0.5}).weights == (0.0, 0.0, 0.5, 1.0)


def test_default_weights_follow_the_hanging_test(mahru, arm6):
    for (robot, _), hangs in ((mahru, True), (arm6, False)):
        kp = rt.robot_keypoints(robot)
        ids = dict(zip(kp.human, kp.body_ids))
        assert rt.upper_arm_can_hang(robot, ids["shoulder"], ids["elbow"]) is hangs
    # a map without an elbow: the hand only
    robot, _ = mahru
    assert rt.default_weights(robot, ("shoulder", "hand"), (2, -1)) == {
        "shoulder": 0.0,
        "hand": 1.0,
    }


def test_lift_above_base():
    targets = np.zeros((5, 3, 3))
    targets[:, :, 2] = [0.3, 0.1, -0.2]  # shoulder, elbow, hand heights
    targets[2, -1, 2] = -0.3  # the lowest hand target
    lifted, lift = rt.lift_above_base(targets, base_z=0.1, clearance=0.05)
    assert lift == pytest.approx(0.45)
    np.testing.assert_allclose(lifted - targets, np.broadcast_to([0, 0, 0.45], targets.shape))
    assert lifted[:, -1, 2].min() == pytest.approx(0.15)
    same, lift = rt.lift_above_base(targets, base_z=-1.0)  # already above: unchanged
    assert lift == 0.0
    np.testing.assert_array_equal(same, targets)


def test_scale_to_robot_keeps_directions_and_sets_lengths():
    rng = np.random.default_rng(0)
    human = np.cumsum(rng.normal(scale=0.2, size=(30, 4, 3)), axis=1)
    human -= human[0, 0]
    rest = np.array([[0.0, -0.19, 1.4], [0.0, -0.19, 1.12], [0.0, -0.19, 0.85], [0.0, -0.13, 0.8]])
    out = rt.scale_to_robot(human, rest)
    seg_t = np.diff(out.targets, axis=1)
    np.testing.assert_allclose(
        np.linalg.norm(seg_t, axis=-1), np.broadcast_to(out.robot_lengths, (30, 3)), atol=1e-12
    )
    seg_h = np.diff(human, axis=1)
    cos = (
        np.sum(seg_t * seg_h, -1) / np.linalg.norm(seg_t, axis=-1) / np.linalg.norm(seg_h, axis=-1)
    )
    np.testing.assert_allclose(cos, 1.0, atol=1e-12)
    ratio = out.robot_lengths.sum() / np.median(np.linalg.norm(seg_h, axis=-1), axis=0).sum()
    np.testing.assert_allclose(out.targets[:, 0], rest[0] + ratio * human[:, 0], atol=1e-12)
    # the root as the frame's origin in every frame: the robot's root target does not move
    fixed = rt.scale_to_robot(human - human[:, :1], rest)
    np.testing.assert_allclose(fixed.targets[:, 0], np.broadcast_to(rest[0], (30, 3)), atol=0)
    relative = out.targets[:, 1:] - out.targets[:, :1]  # the chain, rebuilt the same way
    np.testing.assert_allclose(fixed.targets[:, 1:] - rest[0], relative, atol=1e-12)
    bad = human.copy()
    bad[7, 2] = bad[7, 1]
    with pytest.raises(TrialError, match="key points 1 and 2 of the chain coincide at frame 7"):
        rt.scale_to_robot(bad, rest)


def _smooth_trajectory(robot, seed):
    """(B, F, J) smooth joint paths inside the limits, starting at rest."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(robot.lower), np.asarray(robot.upper)
    rest = np.asarray(robot.rest)
    s = np.linspace(0, 1, F)[None, :, None]
    mj = 10 * s**3 - 15 * s**4 + 6 * s**5
    goal = rest + rng.uniform(-0.4, 0.4, (B, 1, len(rest)))
    return np.clip(rest + (goal - rest) * mj, lo + 0.05, hi - 0.05)


@pytest.mark.parametrize("name", ["mahru_arm", "arm6"])
def test_ik_recovers_reachable_keypoints(name, mahru, arm6):
    robot, dyn = mahru if name == "mahru_arm" else arm6
    kp = rt.robot_keypoints(robot, weights={"shoulder": 1.0, "elbow": 1.0})
    q_true = _smooth_trajectory(robot, 0)
    targets = np.stack([[rt.rest_keypoints(dyn, kp, q) for q in path] for path in q_true])
    out = rt.solve_keypoint_ik(
        dyn, kp, IKSettings(), targets, robot.rest, robot.lower, robot.upper, robot.rest
    )
    err = np.asarray(out.error)
    assert err.max() < TOL_IK, err.max()
    q = np.asarray(out.q)
    assert (q >= robot.lower - TOL_LIMIT).all() and (q <= robot.upper + TOL_LIMIT).all()
    # the reported error is the distance of the solution's key points to the targets
    np.testing.assert_allclose(
        err[1, -1],
        np.linalg.norm(rt.rest_keypoints(dyn, kp, q[1, -1]) - targets[1, -1], axis=-1),
        atol=TOL_FK,
    )


def test_ik_keeps_limits_on_unreachable_targets(mahru):
    robot, dyn = mahru
    kp = rt.robot_keypoints(robot, weights={"shoulder": 1.0, "elbow": 1.0})
    targets = np.tile(rt.rest_keypoints(dyn, kp, robot.rest), (B, F, 1, 1))
    targets[..., 1:, :] += np.array([0.0, -2.0, 2.0])  # far above and to the right
    out = rt.solve_keypoint_ik(
        dyn, kp, IKSettings(), targets, robot.rest, robot.lower, robot.upper, robot.rest
    )
    q = np.asarray(out.q)
    assert np.isfinite(q).all()
    assert (q >= robot.lower - TOL_LIMIT).all() and (q <= robot.upper + TOL_LIMIT).all()
    assert rt.at_limit(q[0], robot.lower, robot.upper).any()  # it pushed into a limit
    assert np.asarray(out.error)[..., 1:].min() > 1.0  # the moved key points stay far


def test_segment_movement_on_a_minimum_jerk_reach():
    rate, dur, pre, post = 100.0, 0.8, 50, 40
    n = round(dur * rate)
    s = np.arange(n + 1) / n
    pos = 10 * s**3 - 15 * s**4 + 6 * s**5
    path = np.concatenate([np.zeros(pre), pos, np.ones(post)])
    hand = np.outer(0.4 * path, [1.0, 0.5, 0.0])
    seg = rt.segment_movement(hand, rate, threshold=0.05)
    # analytic crossing of 5 % of the peak speed (30 s^2 (1-s)^2 peaks at 1.875)
    fine = np.linspace(0, 0.5, 100001)
    s_on = fine[np.argmax(30 * fine**2 * (1 - fine) ** 2 >= 0.05 * 1.875)]
    assert abs(seg.onset - (pre + s_on * n)) <= 1.5
    assert abs(seg.offset - (pre + (1 - s_on) * n)) <= 1.5
    assert seg.peak_speed == pytest.approx(0.4 * np.hypot(1, 0.5) * 1.875 / dur, rel=2e-3)
    assert seg.rest_start and seg.rest_end
    with pytest.raises(TrialError, match="no movement"):
        rt.segment_movement(hand * 1e-3, rate)


def test_resample_is_exact_at_the_ends_and_never_overshoots():
    q = np.array([[0.0, 1.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    out = rt.resample(q, 50)
    np.testing.assert_allclose(out[[0, -1]], q[[0, -1]])
    assert out.min() >= 0.0 and out.max() <= 1.0
    lin = rt.resample(np.linspace(0, 1, 7)[:, None], 13)
    np.testing.assert_allclose(lin[:, 0], np.linspace(0, 1, 13), atol=1e-12)


def test_conditions_and_costs_match_references(mahru):
    robot, dyn = mahru
    q = _smooth_trajectory(robot, 1)[:, ::4]  # (2, 16, J)
    dur = np.array([0.8, 1.1])
    cond, cost = rt.conditions_and_costs(dyn, q, dur)
    m = robot.mj_model
    d = mujoco.MjData(m)
    grid = make_time_grid(q.shape[1])
    ref_cost = jax.jit(functools.partial(torque_cost, dyn, grid))
    for i in range(2):
        d.qpos[robot.qpos_adr] = q[i, -1]
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(cond[i], d.site_xpos[robot.site_id], atol=TOL_FK)
        ref = float(ref_cost(q[i].astype(np.float32), np.float32(dur[i])))
        assert cost[i] == pytest.approx(ref, rel=1e-5)


# A humanoid as published ones are built (Unitree G1-like): a free root, legs, a 3-joint waist,
# both arms off the chest; the right arm's shoulder joints sit in separate bodies a few cm apart
# and its wrist has three joints.
HUMANOID = """<mujoco model="humanoid_waist">
  <compiler angle="radian"/>
  <worldbody>
    <body name="pelvis" pos="0 0 0.8">
      <freejoint name="floating_base"/>
      <geom type="sphere" size="0.1" mass="5"/>
      <body name="left_thigh" pos="0 0.1 -0.1">
        <joint name="left_hip_pitch" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.05"/>
      </body>
      <body name="waist_yaw_link" pos="0 0 0.05">
        <joint name="waist_yaw" axis="0 0 1" range="-2.6 2.6"/>
        <geom type="sphere" size="0.03" mass="0.5"/>
        <body name="waist_roll_link" pos="-0.004 0 0.03">
          <joint name="waist_roll" axis="1 0 0" range="-0.5 0.5"/>
          <geom type="sphere" size="0.03" mass="0.5"/>
          <body name="torso">
            <joint name="waist_pitch" axis="0 1 0" range="-0.5 0.5"/>
            <geom type="box" size="0.08 0.12 0.15" pos="0 0 0.15" mass="8"/>
            <body name="left_upper_arm" pos="0 0.1 0.24">
              <joint name="left_shoulder_pitch" axis="0 1 0" range="-3 2.6"/>
              <geom type="capsule" fromto="0 0 0 0 0 -0.25" size="0.03"/>
            </body>
            <body name="r_sh_pitch" pos="0.004 -0.1 0.24">
              <joint name="r_shoulder_pitch" axis="0 0.97 -0.24" range="-3 2.6"/>
              <geom type="sphere" size="0.03" mass="0.5"/>
              <body name="r_sh_roll" pos="0 -0.038 -0.014">
                <joint name="r_shoulder_roll" axis="1 0 0" range="-2.2 1.6"/>
                <geom type="sphere" size="0.03" mass="0.5"/>
                <body name="r_sh_yaw" pos="0 -0.006 -0.1">
                  <joint name="r_shoulder_yaw" axis="0 0 1" range="-2.6 2.6"/>
                  <geom type="capsule" fromto="0 0 0 0 0 -0.08" size="0.03" mass="1"/>
                  <body name="r_elbow" pos="0.016 0 -0.1">
                    <joint name="r_elbow" axis="0 1 0" range="-1 2"/>
                    <geom type="capsule" fromto="0 0 0 0.1 0 -0.01" size="0.025" mass="0.6"/>
                    <body name="r_wr_roll" pos="0.1 -0.002 -0.01">
                      <joint name="r_wrist_roll" axis="1 0 0" range="-1.9 1.9"/>
                      <geom type="sphere" size="0.02" mass="0.3"/>
                      <body name="r_wr_pitch" pos="0.038 0 0">
                        <joint name="r_wrist_pitch" axis="0 1 0" range="-1.6 1.6"/>
                        <geom type="sphere" size="0.02" mass="0.3"/>
                        <body name="r_wr_yaw" pos="0.046 0 0">
                          <joint name="r_wrist_yaw" axis="0 0 1" range="-1.6 1.6"/>
                          <geom type="box" size="0.04 0.02 0.01" pos="0.04 0 0" mass="0.3"/>
                          <site name="palm" pos="0.08 0 0"/>
                        </body>
                      </body>
                    </body>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_humanoid_keypoints_start_below_the_chest(tmp_path):
    """The default joints run from the pelvis through the waist; the arm's key points start below
    the chest, which carries the other arm (not at the waist's first tilting joint), and the elbow
    is the bend in the middle of the arm (not the shoulder's second joint 4 cm out). Its upper arm
    hangs: every key point is matched."""
    path = tmp_path / "humanoid.xml"
    path.write_text(HUMANOID)
    robot = load_robot(path)
    assert robot.joint_names[:4] == ("waist_yaw", "waist_roll", "waist_pitch", "r_shoulder_pitch")
    assert rt.guess_keypoints(robot) == {
        "body:r_sh_pitch": "shoulder",
        "body:r_elbow": "elbow",
        "body:r_wr_yaw": "wrist",
        "site:palm": "hand",
    }
    assert rt.robot_keypoints(robot).weights == (1.0, 1.0, 1.0, 1.0)


FINGERTIP_ARM = """<mujoco model="fingertip_arm">
  <compiler angle="radian"/>
  <worldbody>
    <body name="upper" pos="0 0 0.5">
      <joint name="shoulder" axis="0 1 0" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <body name="fore" pos="0.3 0 0">
        <joint name="elbow" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03"/>
        <body name="palm" pos="0.25 0 0">
          <joint name="wrist" axis="0 1 0" range="-2 2"/>
          <geom type="box" size="0.04 0.03 0.01" pos="0.04 0 0"/>
          <body name="finger_a" pos="0.08 0.02 0">
            <joint name="finger_a" type="slide" axis="0 1 0" range="-0.02 0"/>
            <geom type="box" size="0.02 0.005 0.01" pos="0.02 0 0"/>
            <site name="tip" pos="0.04 0 0"/>
          </body>
          <body name="finger_b" pos="0.08 -0.02 0">
            <joint name="finger_b" type="slide" axis="0 1 0" range="0 0.02"/>
            <geom type="box" size="0.02 0.005 0.01" pos="0.02 0 0"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_a_branch_below_the_wrist_is_not_the_arm(tmp_path):
    """The end effector on a finger: the palm carries the other finger, but no arm starts below
    it, so the whole chain is the arm."""
    path = tmp_path / "fingertip_arm.xml"
    path.write_text(FINGERTIP_ARM)
    robot = load_robot(path)
    assert rt.guess_keypoints(robot) == {
        "body:upper": "shoulder",
        "body:fore": "elbow",
        "body:palm": "wrist",
        "site:tip": "hand",
    }
