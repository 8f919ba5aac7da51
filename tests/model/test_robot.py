"""Shipped robot models and `evojax_motion.model.robot`: limits, de Leva inertias, reach, user
errors."""

import pickle
from pathlib import Path

import mujoco
import numpy as np
import pytest
from scipy.spatial import cKDTree

from evojax_motion.errors import UserError
from evojax_motion.model.robot import (
    MODELS_DIR,
    REST_MARGIN,
    SHIPPED_ROBOTS,
    Robot,
    load_robot,
    robot_from_mjcf_text,
)

BODY_MASS_KG = 73.0  # de Leva (1996) reference male: 73.0 kg, 1.741 m
# de Leva (1996) Table 4, males: mass fraction, length [m], CoM fraction from the proximal end,
# radii of gyration (sagittal, transverse, longitudinal) as fractions of the length.
DE_LEVA = {
    "trunk": (0.4346, 0.5155, 0.4310, (0.384, 0.358, 0.197)),  # MIDS-MIDH
    "upper_arm": (0.0271, 0.2817, 0.5772, (0.285, 0.269, 0.158)),
    "forearm": (0.0162, 0.2689, 0.4574, (0.276, 0.265, 0.121)),
    "hand": (0.0061, 0.0862, 0.7900, (0.628, 0.513, 0.401)),
}
TOL_MASS_KG = 1e-6
TOL_COM_M = 1e-4
TOL_INERTIA_REL = 1e-4

SHOULDER = np.array([0.0, -0.19, 1.40])  # right shoulder joint centre at q = 0 [m]
# The catch region the demonstrations may use, verified reachable with MARGIN_RAD to every limit.
CATCH_LO = np.array([0.20, -0.50, 1.10])
CATCH_HI = np.array([0.50, 0.10, 1.70])
MARGIN_RAD = 0.1
N_SAMPLES = 20_000
TOL_COVER_M = 0.05  # a sampled posture puts the hand this close to every grid point...
TOL_REACH_M = 1e-3  # ...and a few damped least-squares steps from it reach the point exactly


@pytest.fixture(scope="module")
def mahru():
    return load_robot("mahru_arm")


@pytest.fixture(scope="module")
def arm6():
    return load_robot("arm6")


@pytest.mark.parametrize("name", sorted(SHIPPED_ROBOTS))
def test_shipped_robot_limits_and_rest(name):
    robot = load_robot(name)
    entry = SHIPPED_ROBOTS[name]
    m = robot.mj_model
    assert robot.name == name
    assert robot.joint_names == entry.joints and robot.site_name == entry.site
    assert robot.n_joints == len(entry.joints)
    assert np.all(robot.lower < robot.upper)
    # The rest posture is strictly inside every range (not parked on a limit).
    assert np.all(robot.rest > robot.lower) and np.all(robot.rest < robot.upper)
    assert np.all(np.isfinite(robot.velocity_limit)) and np.all(robot.velocity_limit > 0)
    assert np.all(np.isfinite(robot.torque_limit)) and np.all(robot.torque_limit > 0)
    # Pure rigid-body inverse dynamics: no constraint forces, no joint-space extras.
    assert m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    for extra in (m.dof_armature, m.dof_damping, m.dof_frictionloss, m.jnt_stiffness):
        assert np.all(extra == 0)
    assert np.array_equal(robot.qpos_adr, m.jnt_qposadr[robot.joint_ids])
    assert np.array_equal(robot.dof_adr, m.jnt_dofadr[robot.joint_ids])


def test_mahru_values(mahru):
    deg = np.pi / 180
    np.testing.assert_allclose(
        mahru.lower, np.array([-45, -50, -40, -90, 0, -70, -35]) * deg, atol=1e-6
    )
    np.testing.assert_allclose(
        mahru.upper, np.array([45, 170, 150, 70, 145, 80, 20]) * deg, atol=1e-6
    )
    np.testing.assert_array_equal(mahru.rest, [0.0, 0.1, 0.1, 0.0, 0.3, 0.0, 0.0])
    np.testing.assert_array_equal(mahru.velocity_limit, [3, 5, 5, 5, 6, 6, 6])
    np.testing.assert_array_equal(mahru.torque_limit, [100, 80, 80, 40, 60, 15, 15])


def _hand(robot, q):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[robot.qpos_adr] = q
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[robot.site_id].copy(), d


def test_mahru_geometry_and_joint_signs(mahru):
    m = mahru.mj_model
    zero = np.zeros(mahru.n_joints)
    hand0, d = _hand(mahru, zero)
    body = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in DE_LEVA}
    np.testing.assert_allclose(d.xpos[body["trunk"]], [0, 0, 1.0], atol=1e-12)
    np.testing.assert_allclose(d.xpos[body["upper_arm"]], SHOULDER, atol=1e-12)
    # Arm hanging: the hand lies straight below the shoulder, arm length + palm offset down.
    np.testing.assert_allclose(
        hand0, SHOULDER + np.array([0, 0.015, -(0.2817 + 0.2689 + 0.06)]), atol=1e-9
    )
    # Rest: hand beside the thigh, below the waist, a little forward.
    rest_hand, _ = _hand(mahru, mahru.rest)
    assert rest_hand[2] < 0.9 and rest_hand[1] < -0.19 and 0 < rest_hand[0] < 0.25

    def moved(joint, angle=0.3):
        q = zero.copy()
        q[mahru.joint_names.index(joint)] = angle
        return _hand(mahru, q)[0] - hand0

    # Positive directions are anatomical (docs/robot_models.md).
    assert moved("shoulder_pitch")[0] > 0.1  # flexion: forward
    assert moved("shoulder_roll")[1] < -0.1  # abduction of the right arm: outward (-y)
    assert moved("elbow")[0] > 0.05  # flexion: forward
    assert moved("wrist_pitch")[1] > 0.01  # palmar flexion: toward the palm (+y at q = 0)
    assert moved("wrist_yaw")[0] > 0.01  # radial deviation: thumb side (+x at q = 0)
    assert moved("waist_yaw", 0.5)[0] > 0.05  # trunk turns left: the right hand comes forward
    np.testing.assert_allclose(np.linalg.norm(moved("shoulder_yaw")), 0.015 * 2 * np.sin(0.15))


def test_mahru_inertia_is_de_leva(mahru):
    m = mahru.mj_model
    arm_mass = 0.0
    for body, (frac, length, com, radii) in DE_LEVA.items():
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)
        mass = frac * BODY_MASS_KG
        assert abs(m.body_mass[b] - mass) < TOL_MASS_KG, body
        np.testing.assert_array_equal(m.body_iquat[b], [1, 0, 0, 0])
        if body == "trunk":  # CoM measured down from mid-shoulder, 0.40 m above the waist
            np.testing.assert_allclose(m.body_ipos[b], [0, 0, 0.40 - com * length], atol=TOL_COM_M)
        else:  # CoM measured from the proximal joint, down the hanging segment
            np.testing.assert_allclose(m.body_ipos[b], [0, 0, -com * length], atol=TOL_COM_M)
            arm_mass += m.body_mass[b]
        sag, trans, long_ = (mass * (r * length) ** 2 for r in radii)
        # Forearm and hand hang in neutral pronation: their sagittal axis is body y.
        expected = [trans, sag, long_] if body in ("forearm", "hand") else [sag, trans, long_]
        np.testing.assert_allclose(m.body_inertia[b], expected, rtol=TOL_INERTIA_REL, err_msg=body)
    # de Leva's whole arm: 4.94 % of body mass.
    assert abs(arm_mass - 0.0494 * BODY_MASS_KG) < 3 * TOL_MASS_KG


def _grid(lo, hi, n=3):
    axes = [np.linspace(a, b, n) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _reach(robot, target, q, lo, hi, steps=60):
    """Damped least squares on the hand position, clipped to [lo, hi]; returns the final error."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    jac = np.zeros((3, m.nv))
    err = np.inf
    for _ in range(steps):
        d.qpos[robot.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        e = target - d.site_xpos[robot.site_id]
        err = float(np.linalg.norm(e))
        if err < 0.1 * TOL_REACH_M:
            break
        mujoco.mj_jacSite(m, d, jac, None, robot.site_id)
        jq = jac[:, robot.dof_adr]
        q = np.clip(q + jq.T @ np.linalg.solve(jq @ jq.T + 1e-4 * np.eye(3), e), lo, hi)
    return err


def test_mahru_catch_region_is_reachable_inside_limits(mahru):
    lo, hi = mahru.lower + MARGIN_RAD, mahru.upper - MARGIN_RAD
    rng = np.random.default_rng(0)
    qs = rng.uniform(lo, hi, size=(N_SAMPLES, mahru.n_joints))
    m = mahru.mj_model
    d = mujoco.MjData(m)
    hands = np.empty((N_SAMPLES, 3))
    for i, q in enumerate(qs):
        d.qpos[mahru.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        hands[i] = d.site_xpos[mahru.site_id]
    tree = cKDTree(hands)
    targets = _grid(CATCH_LO, CATCH_HI)
    dist, _ = tree.query(targets)
    assert dist.max() < TOL_COVER_M, targets[dist.argmax()]
    for target in targets:
        _, near = tree.query(target, k=4)
        best = min(_reach(mahru, target, qs[i].copy(), lo, hi) for i in near)
        assert best < TOL_REACH_M, (target, best)
    # The check can fail: 0.9 m ahead of the shoulder is out of reach.
    far = SHOULDER + np.array([0.9, 0.0, 0.0])
    assert tree.query(far)[0] > 0.2
    assert _reach(mahru, far, qs[tree.query(far)[1]].copy(), lo, hi) > 0.2


def test_arm6_is_not_mahru(arm6, mahru):
    m = arm6.mj_model
    assert arm6.n_joints == 6 and m.njnt == 7  # the slide joint "finger" is not controlled
    finger = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "finger")
    assert finger not in arm6.joint_ids and m.jnt_qposadr[finger] not in arm6.qpos_adr
    # velocity_limit holds one value per model joint: the controlled ones are picked by id.
    np.testing.assert_array_equal(arm6.velocity_limit, [2.5, 2.5, 3.0, 4.0, 4.0, 6.0])
    np.testing.assert_array_equal(arm6.rest, [0, -0.4, 0.9, 0, 0.8, 0])
    assert arm6.site_name == "tool" and not np.allclose(arm6.lower[:6], mahru.lower[:6])
    tool0, _ = _hand(arm6, np.zeros(6))
    np.testing.assert_allclose(tool0, [0.05 + 0.2 + 0.15 + 0.06 + 0.10, 0, 0.6 + 0.18 + 0.40])


def test_joint_subset_order_and_slide_joint():
    robot = load_robot("arm6", joints=("finger", "elbow_lift", "base_yaw"), site="tool")
    m = robot.mj_model
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in robot.joint_names]
    np.testing.assert_array_equal(robot.joint_ids, ids)
    np.testing.assert_array_equal(robot.qpos_adr, m.jnt_qposadr[ids])
    np.testing.assert_allclose(robot.lower, [0.0, -2.617994, -2.96706])
    np.testing.assert_allclose(robot.upper, [0.04, 2.617994, 2.96706])
    np.testing.assert_array_equal(robot.velocity_limit, [0.2, 3.0, 2.5])
    np.testing.assert_array_equal(robot.torque_limit, [20, 80, 150])
    # The keyframe puts the finger on its lower limit: the rest posture keeps REST_MARGIN of
    # its range off it.
    np.testing.assert_allclose(robot.rest, [REST_MARGIN * 0.04, 0.9, 0.0], rtol=1e-12)
    assert "keyframe 'rest'" in robot.rest_source and "['finger']" in robot.rest_source


def test_robot_from_mjcf_text_round_trip(mahru):
    again = robot_from_mjcf_text(mahru.name, mahru.mjcf, mahru.joint_names, mahru.site_name)
    for attr in ("lower", "upper", "velocity_limit", "torque_limit", "rest", "qpos_adr"):
        np.testing.assert_array_equal(getattr(again, attr), getattr(mahru, attr))
    q = np.random.default_rng(1).uniform(mahru.lower, mahru.upper)
    np.testing.assert_array_equal(_hand(again, q)[0], _hand(mahru, q)[0])
    assert again is not mahru and hash(again) != hash(mahru)  # identity hash: jit static arg
    with pytest.raises(ValueError):
        mahru.lower[0] = 0.0  # cached arrays are read-only
    copied = pickle.loads(pickle.dumps(mahru))
    np.testing.assert_array_equal(copied.rest, mahru.rest)
    assert not copied.rest.flags.writeable and "mj_model" not in pickle.dumps(mahru).decode(
        "latin1"
    )


BARE = """<mujoco model="bare">
  <compiler angle="radian"/>
  <worldbody>
    <body name="a">
      <joint name="j1" axis="0 0 1" range="0.5 1.0"/>
      <inertial pos="0 0 0.1" mass="1" diaginertia="0.01 0.01 0.01"/>
      <site name="tip" pos="0 0 0.2"/>
      {extra}
    </body>
  </worldbody>
  {tail}
</mujoco>
"""


def _write(tmp_path, text, name="model.xml"):
    path = Path(tmp_path) / name
    path.write_text(text)
    return path


def test_defaults_for_a_user_file(tmp_path):
    path = _write(tmp_path, BARE.format(extra="", tail=""), "my_arm.xml")
    robot = load_robot(path)
    assert robot.name == "my_arm" and robot.joint_names == ("j1",) and robot.site_name == "tip"
    assert robot.velocity_limit[0] == np.inf and robot.torque_limit[0] == np.inf
    assert robot.torque_limit_source == ("none",)
    # No keyframe: qpos0 = 0 brought into [0.5, 1.0], REST_MARGIN of the range off the limit.
    assert robot.rest[0] == pytest.approx(0.5 + REST_MARGIN * 0.5, rel=1e-12)
    assert robot.rest_source.startswith("qpos0") and "['j1']" in robot.rest_source
    assert robot.mjcf == path.read_text() and robot.files == (str(path),)  # kept verbatim
    # Constraints are switched off even though this MJCF leaves them on.
    assert robot.mj_model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    assert load_robot(str(path)).joint_names == ("j1",)
    user_mahru = load_robot(MODELS_DIR / "mahru_arm.xml", site="hand")
    assert user_mahru.name == "mahru_arm" and user_mahru.n_joints == 7


UNLIMITED = '<body name="b"><joint name="free_spin" axis="1 0 0" limited="false"/>' + (
    '<inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/></body>'
)
BALL = '<body name="b"><joint name="shoulder_ball" type="ball"/>' + (
    '<inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/></body>'
)
SECOND_SITE = '<site name="other"/>'


@pytest.mark.parametrize(
    "spec, kwargs, xml, expected",
    [
        ("mahru", {}, None, ["'mahru'", "mahru_arm", "arm6"]),
        ("{tmp}/missing.xml", {}, None, ["missing.xml", "not found"]),
        ("{file}", {}, "<mujoco><worldbody><body>", ["model.xml", "does not compile", "XML"]),
        ("mahru_arm", {"joints": ("waist_yaw", "knee")}, None, ["'knee'", "'elbow'"]),
        ("mahru_arm", {"joints": ("elbow", "elbow")}, None, ["'elbow'", "twice"]),
        ("mahru_arm", {"joints": ()}, None, ["at least one"]),
        ("mahru_arm", {"joints": "elbow"}, None, ["joints", "string"]),
        ("mahru_arm", {"site": "gripper"}, None, ["'gripper'", "'hand'"]),
        (
            "{file}",
            {"joints": ("j1", "shoulder_ball")},
            BARE.format(extra=BALL, tail=""),
            ["'shoulder_ball'", "ball", "hinge or slide"],
        ),
        ("{file}", {}, BARE.format(extra=SECOND_SITE, tail=""), ["'tip'", "'other'", "site"]),
        ("{file}", {"site": "nope"}, BARE.format(extra="", tail=""), ["'nope'", "'tip'"]),
        (
            "{file}",
            {},
            BARE.format(
                extra="", tail='<custom><numeric name="velocity_limit" data="1 2"/></custom>'
            ),
            ["velocity_limit", "expected 1 values"],
        ),
        (
            "{file}",
            {},
            BARE.format(
                extra="", tail='<custom><numeric name="velocity_limit" data="0"/></custom>'
            ),
            ["velocity_limit", "> 0"],
        ),
        (
            "{file}",
            {},
            BARE.format(extra="", tail='<keyframe><key name="rest" qpos="2.0"/></keyframe>'),
            ["keyframe 'rest'", "'j1'"],
        ),
    ],
)
def test_user_errors_name_the_item(tmp_path, spec, kwargs, xml, expected):
    if xml is not None:
        path = _write(tmp_path, xml)
        spec = spec.format(file=path)
    spec = spec.format(tmp=tmp_path)
    with pytest.raises(UserError) as info:
        load_robot(spec, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    for part in expected:
        assert part in message, (part, message)
    if xml is not None:
        assert str(path) in message


def test_joint_without_range_is_continuous(tmp_path):
    path = _write(tmp_path, BARE.format(extra=UNLIMITED, tail=""))
    robot = load_robot(path, joints=("j1", "free_spin"), site="tip")
    np.testing.assert_array_equal(robot.continuous, [False, True])
    np.testing.assert_array_equal(robot.lower, [0.5, -np.inf])
    np.testing.assert_array_equal(robot.upper, [1.0, np.inf])
    assert robot.rest[1] == 0.0  # qpos0: a continuous joint has no limit to keep off
    lo, hi = robot.posture_box(margin=0.1)
    np.testing.assert_allclose(lo, [0.6, -np.pi])
    np.testing.assert_allclose(hi, [0.9, np.pi])
    q = robot.sample_postures(np.random.default_rng(0), 500, margin=0.1)
    assert np.isfinite(q).all() and (q >= lo).all() and (q <= hi).all()
    assert q[:, 1].min() < -3.0 and q[:, 1].max() > 3.0  # one turn about rest


def test_ball_joint_beside_controlled_joints_is_allowed(tmp_path):
    # Joints that are not controlled may be of any type: they are held at qpos0.
    path = _write(tmp_path, BARE.format(extra=BALL, tail=""))
    robot = load_robot(path, joints=("j1",), site="tip")
    assert robot.n_joints == 1 and robot.qpos_adr[0] == 0


def test_robot_validates_on_construction(mahru):
    with pytest.raises(UserError, match="'nope'"):
        Robot(name="x", mjcf=mahru.mjcf, joint_names=("nope",), site_name="hand")
