"""Robot models as users bring them (`evojax_motion.model.robot`, `evojax-motion robot`).

Published arms loaded unedited (../shared/robots: Kinova Gen3 with continuous joints and meshes,
UFACTORY xArm7 with and without its gripper; skipped where absent); a model with an include, a
mesh written here and a texture, loaded from its path and rebuilt from its stored text after its
folder has moved; a humanoid-like model with a free joint and a body as end effector; the rest
posture's keyframe order; the sources of torque and velocity limits; the CLI report.
References are MuJoCo's own: ``MjModel.from_xml_path`` of the original files, ``mj_kinematics``
and ``mj_inverse``.
"""

import re
import shutil
from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest
import yaml
from PIL import Image
from scipy.spatial import ConvexHull

from evojax_motion.cli.entry import main
from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import (
    END_EFFECTOR_SITE,
    MODELS_DIR,
    REST_MARGIN,
    load_robot,
    mj_inverse_torques,
    robot_from_mjcf_text,
)
from evojax_motion.motion.database import DatabaseMeta, load_database, make_database, save_database
from evojax_motion.report.kinematics import robot_from_meta
from evojax_motion.report.render import scene_model
from evojax_motion.run.workflow import make_robot
from evojax_motion.settings import config_from_dict

SHARED = Path(__file__).resolve().parents[3] / "shared" / "robots"
ASSETS = Path(__file__).resolve().parents[1] / "assets"
# MjSpec.to_xml writes numbers with 6 significant digits: an expanded model (includes, meshes)
# differs from its file by that rounding, a verbatim one not at all.
TOL_ROUNDED_REL = 1e-5  # masses, inertias, keyframe values of an expanded model, relative
TOL_ROUNDED_M = 1e-5  # [m] site positions of an expanded model at the same posture
TOL_EXACT = 1e-12  # the same text compiled twice
TOL_TAU_F64 = 1e-10  # max |tau - tau_ref| / max |tau_ref|, float64 RNEA against mj_inverse
N_POSTURES = 20

PUBLISHED = {
    # name: file, end effector (None: the only site), joints, continuous mask, torque limits
    "gen3": (
        "kinova_gen3/gen3.xml",
        None,
        tuple(f"joint_{i}" for i in range(1, 8)),
        [True, False, True, False, True, False, True],
        [105, 105, 105, 105, 52, 52, 52],
    ),
    "xarm7": (
        "ufactory_xarm7/xarm7.xml",
        "link_tcp",
        tuple(f"joint{i}" for i in range(1, 8)),
        [False] * 7,
        [50, 50, 30, 30, 30, 20, 20],
    ),
    "xarm7_nohand": (
        "ufactory_xarm7/xarm7_nohand.xml",
        None,
        tuple(f"joint{i}" for i in range(1, 8)),
        [False] * 7,
        [50, 50, 30, 30, 30, 20, 20],
    ),
}


def _site_positions(m: mujoco.MjModel, robot, q: np.ndarray, site: str) -> np.ndarray:
    """World positions of ``site`` of model ``m`` with ``robot``'s joints at ``q (N, J)``."""
    d = mujoco.MjData(m)
    qpos_adr = [m.jnt_qposadr[m.joint(n).id] for n in robot.joint_names]
    out = np.zeros((len(q), 3))
    for i, qi in enumerate(q):
        d.qpos[:] = m.qpos0
        d.qpos[qpos_adr] = qi
        mujoco.mj_kinematics(m, d)
        out[i] = d.site(site).xpos
    return out


def assert_same_bodies_and_geoms(m: mujoco.MjModel, ref: mujoco.MjModel, atol: float) -> None:
    """Masses and inertias (relative), centres of mass and geom frames ([m], rotation entries)
    of two compiled models agree: a mesh stored in the text sits where its file put it."""
    np.testing.assert_allclose(m.body_mass, ref.body_mass, rtol=TOL_ROUNDED_REL)
    np.testing.assert_allclose(m.body_inertia, ref.body_inertia, rtol=TOL_ROUNDED_REL)
    np.testing.assert_allclose(m.body_ipos, ref.body_ipos, atol=atol)
    np.testing.assert_allclose(m.geom_pos, ref.geom_pos, atol=atol)

    def rotations(quats):
        out = np.zeros((len(quats), 9))
        for q, r in zip(quats, out):
            mujoco.mju_quat2Mat(r, q)
        return out

    np.testing.assert_allclose(rotations(m.geom_quat), rotations(ref.geom_quat), atol=atol)


@pytest.fixture(scope="module", params=list(PUBLISHED))
def published(request):
    file, ee, joints, continuous, torque = PUBLISHED[request.param]
    path = SHARED / file
    if not path.is_file():
        pytest.skip(f"{path} not found (the published robot models sit beside the repository)")
    return path, load_robot(path, end_effector=ee), joints, continuous, torque


def test_published_arms_load_unedited(published):
    path, robot, joints, continuous, torque = published
    ref = mujoco.MjModel.from_xml_path(str(path))  # MuJoCo's reading of the original files
    assert robot.joint_names == joints  # the default: the path from the root to the site
    np.testing.assert_array_equal(robot.continuous, continuous)
    ids = [ref.joint(n).id for n in joints]
    lo, hi = ref.jnt_range[ids].T
    np.testing.assert_allclose(robot.lower, np.where(continuous, -np.inf, lo), rtol=1e-6)
    np.testing.assert_allclose(robot.upper, np.where(continuous, np.inf, hi), rtol=1e-6)
    np.testing.assert_array_equal(robot.torque_limit, torque)
    assert all("forcerange" in s for s in robot.torque_limit_source)
    assert np.all(np.isinf(robot.velocity_limit))  # MJCF has no velocity field
    home = ref.key_qpos[ref.key("home").id][ref.jnt_qposadr[ids]]
    np.testing.assert_allclose(robot.rest, home, rtol=TOL_ROUNDED_REL, atol=1e-12)
    assert robot.rest_source == "keyframe 'home'"
    # The files MuJoCo read: the model and every mesh it names, beside it.
    meshes = {Path(f).name for f in robot.files[1:]}
    assert robot.files[0] == str(path) and meshes and all(m.endswith(".stl") for m in meshes)
    assert all(Path(f).is_file() for f in robot.files)
    # The stored text is self-contained and is the same robot, to to_xml's rounding.
    assert "file=" not in robot.mjcf and "<include" not in robot.mjcf
    m = robot.mj_model
    assert_same_bodies_and_geoms(m, ref, TOL_ROUNDED_M)
    q = robot.sample_postures(np.random.default_rng(0), N_POSTURES)
    ours = _site_positions(m, robot, q, robot.site_name)
    theirs = _site_positions(ref, robot, q, robot.site_name)
    assert np.abs(ours - theirs).max() <= TOL_ROUNDED_M
    assert np.ptp(ours, axis=0).max() > 0.1  # the postures move the hand


def test_published_arm_rebuilds_from_its_stored_text(published):
    _, robot, *_ = published
    again = robot_from_mjcf_text(robot.name, robot.mjcf, robot.joint_names, robot.site_name)
    for attr in ("lower", "upper", "continuous", "torque_limit", "velocity_limit", "rest"):
        np.testing.assert_array_equal(getattr(again, attr), getattr(robot, attr))
    q = robot.sample_postures(np.random.default_rng(1), 5)
    np.testing.assert_allclose(
        _site_positions(again.mj_model, again, q, again.site_name),
        _site_positions(robot.mj_model, robot, q, robot.site_name),
        atol=TOL_EXACT,
    )


# -- a model with an include, a mesh and a texture, written here ---------------------------------


def write_stl(path: Path, points: np.ndarray) -> None:
    """Binary STL of the convex hull of ``points (n, 3)``, faces wound outward."""
    hull = ConvexHull(points)
    tri = points[hull.simplices]  # (m, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", normal, tri.mean(axis=1) - points.mean(axis=0)) < 0
    tri[inward] = tri[inward][:, ::-1]
    normal[inward] *= -1
    rec = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    rec["v"] = tri
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\0" * 80 + np.uint32(len(tri)).tobytes() + rec.tobytes())


MAIN_XML = """<mujoco model="include_arm">
  <compiler angle="radian" meshdir="meshes" texturedir="textures"/>
  <include file="parts/assets.xml"/>
  <worldbody>
    <body name="base" pos="0 0 0.1">
      <joint name="yaw" axis="0 0 1" range="-2 2"/>
      <geom type="mesh" mesh="link" density="1000"/>
      <body name="arm" pos="0 0 0.25" quat="0.9 0.1 0.3 0">
        <joint name="pitch" axis="0 1 0"/>
        <geom type="mesh" mesh="link" material="skin" density="800"/>
        <site name="tip" pos="0.01 0 0.3"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
INCLUDED_XML = """<mujoco>
  <asset>
    <mesh name="link" file="link.stl" scale="1 1 1.5"/>
    <texture name="grain" type="2d" file="grain.png"/>
    <material name="skin" texture="grain"/>
  </asset>
</mujoco>
"""


@pytest.fixture
def include_model(tmp_path):
    """A model folder: main file, an include in a subfolder, an STL mesh and a PNG texture.
    The bodies' inertias come from the mesh (no <inertial>)."""
    folder = tmp_path / "my_arm"
    (folder / "parts").mkdir(parents=True)
    (folder / "textures").mkdir()
    (folder / "robot.xml").write_text(MAIN_XML)
    (folder / "parts" / "assets.xml").write_text(INCLUDED_XML)
    # A skewed box off the origin: MuJoCo moves and turns it (mesh_pos, mesh_quat).
    corners = np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T
    rot = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])
    points = (corners * [0.03, 0.05, 0.2] + [[0.0, 0.0, 0.0]] * 8) @ rot.T + [0.01, 0.02, 0.02]
    write_stl(folder / "meshes" / "link.stl", points)
    Image.new("RGB", (4, 4), (200, 150, 100)).save(folder / "textures" / "grain.png")
    return folder


def test_include_mesh_model_loads_and_moves(include_model, tmp_path, capsys):
    main_file = include_model / "robot.xml"
    robot = load_robot(main_file)
    assert "texture files are not stored" in capsys.readouterr().err
    assert robot.files == tuple(
        str(include_model / f)
        for f in ("robot.xml", "parts/assets.xml", "meshes/link.stl", "textures/grain.png")
    )
    assert robot.joint_names == ("yaw", "pitch") and robot.site_name == "tip"
    np.testing.assert_array_equal(robot.continuous, [False, True])
    ref = mujoco.MjModel.from_xml_path(str(main_file))
    q = robot.sample_postures(np.random.default_rng(2), N_POSTURES)
    tip = _site_positions(ref, robot, q, "tip")
    assert_same_bodies_and_geoms(robot.mj_model, ref, TOL_ROUNDED_M)
    assert ref.body_mass[1] > 0.1  # the mesh's volume gives the mass
    assert np.abs(ref.mesh_pos).max() > 0.01  # MuJoCo moved the mesh: stored, it is moved back
    # A database and a run folder store robot.mjcf; the model's folder then moves away.
    db_path = tmp_path / "db.npz"
    q_db = np.broadcast_to(robot.rest, (2, 3, 2)).astype(np.float32)
    db = make_database(q_db, np.ones(2), np.zeros((2, 3)))
    save_database(db_path, db, DatabaseMeta.of_robot(robot, synthetic=True, description="test"))
    shutil.move(include_model, tmp_path / "moved_away")
    with pytest.raises(UserError, match="not found"):
        load_robot(main_file)
    _, meta = load_database(db_path)
    again = robot_from_meta(meta, source=str(db_path))
    assert again.joint_names == robot.joint_names and again.mjcf == robot.mjcf
    np.testing.assert_allclose(_site_positions(again.mj_model, again, q, "tip"), tip, atol=1e-5)
    assert_same_bodies_and_geoms(again.mj_model, ref, TOL_ROUNDED_M)
    pictures = scene_model(again.mjcf, floor=0.0)  # rendering keeps the mesh
    assert pictures.nmesh == 1 and pictures.mesh_vertnum[0] == ref.mesh_vertnum[0]
    np.testing.assert_allclose(pictures.mesh_vert, ref.mesh_vert, atol=1e-6)


def test_verbatim_text_for_a_file_without_includes_or_assets():
    """Shipped models (and old databases, which hold such text) stay exactly as written."""
    for name in ("mahru_arm", "arm6"):
        robot = load_robot(name)
        assert robot.mjcf == (MODELS_DIR / f"{name}.xml").read_text()
    mahru = load_robot("mahru_arm")
    state = {"name": mahru.name, "mjcf": mahru.mjcf, "joint_names": mahru.joint_names}
    state.update(site_name=mahru.site_name, source="")  # a pickle made before `files`
    old = object.__new__(type(mahru))
    old.__setstate__(state)
    assert old.files == () and np.array_equal(old.rest, mahru.rest)


# -- a humanoid-like model: free joint, no site, a body as end effector --------------------------

HUMANOID = """<mujoco model="humanoid_like">
  <compiler angle="radian"/>
  <worldbody>
    <body name="torso" pos="0 0 1.0">
      <freejoint name="root"/>
      <geom type="capsule" fromto="0 0 -0.3 0 0 0.3" size="0.12"/>
      <body name="chest" pos="0 0 0.3">
        <joint name="waist_yaw" axis="0 0 1" range="-1 1"/>
        <geom type="sphere" size="0.1" mass="8"/>
        <body name="upper_arm" pos="0 -0.2 0.1" quat="0.98 0.1 0 0.17">
          <joint name="shoulder_pitch" axis="0 1 0" range="-2 3"/>
          <joint name="shoulder_roll" axis="1 0 0" range="-1.5 1"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.28" size="0.04"/>
          <body name="forearm" pos="0 0 -0.28">
            <joint name="elbow" axis="0 1 0" range="0 2.5"/>
            <geom type="capsule" fromto="0 0 0 0 0 -0.26" size="0.035"/>
            <body name="hand" pos="0 0 -0.26" quat="0.9 0 0.2 0.3">
              <geom type="box" size="0.02 0.04 0.06" pos="0 0 -0.06"/>
            </body>
          </body>
        </body>
        <body name="left_arm" pos="0 0.2 0.1">
          <joint name="left_shoulder" axis="0 1 0" range="-2 3"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.04"/>
        </body>
      </body>
      <body name="thigh" pos="0 -0.1 -0.35">
        <joint name="hip" type="ball"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.06"/>
        <body name="shin" pos="0 0 -0.4">
          <joint name="knee" axis="0 1 0" range="-2.5 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.05"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
HAND_OFFSET = np.array([0.01, -0.02, -0.09])  # [m] the palm's centre, in the hand's frame


def test_humanoid_with_a_body_as_end_effector(tmp_path):
    path = tmp_path / "humanoid_like.xml"
    path.write_text(HUMANOID)
    with pytest.raises(UserError, match="end_effector: expected the name"):
        load_robot(path)  # no site: the end effector must be named
    robot = load_robot(path, end_effector="hand", end_effector_offset=HAND_OFFSET)
    # Default joints: the hinges from the root to the hand (not the free joint, the other arm
    # or the legs).
    assert robot.joint_names == ("waist_yaw", "shoulder_pitch", "shoulder_roll", "elbow")
    assert robot.site_name == END_EFFECTOR_SITE
    np.testing.assert_allclose(robot.rest, [0.0, 0.0, 0.0, REST_MARGIN * 2.5])
    ref = mujoco.MjModel.from_xml_path(str(path))
    q = robot.sample_postures(np.random.default_rng(3), N_POSTURES)
    d = mujoco.MjData(ref)
    hand = ref.body("hand").id
    qpos_adr = [ref.jnt_qposadr[ref.joint(n).id] for n in robot.joint_names]
    expected = np.zeros((N_POSTURES, 3))
    for i, qi in enumerate(q):
        d.qpos[:] = ref.qpos0
        d.qpos[qpos_adr] = qi
        mujoco.mj_kinematics(ref, d)
        expected[i] = d.xpos[hand] + d.xmat[hand].reshape(3, 3) @ HAND_OFFSET
    got = _site_positions(robot.mj_model, robot, q, robot.site_name)
    np.testing.assert_allclose(got, expected, atol=TOL_EXACT)
    # Stored text rebuilds the same robot (the added site is part of it).
    again = robot_from_mjcf_text(robot.name, robot.mjcf, robot.joint_names, robot.site_name)
    np.testing.assert_allclose(_site_positions(again.mj_model, again, q, again.site_name), got)
    # Torques: the RNEA with the free joint held at qpos0, against mj_inverse.
    rng = np.random.default_rng(4)
    qd = 2.0 * rng.standard_normal((N_POSTURES, robot.n_joints))  # [rad/s]
    qdd = 10.0 * rng.standard_normal((N_POSTURES, robot.n_joints))  # [rad/s^2]
    ref_tau = mj_inverse_torques(robot, q, qd, qdd)
    with jax.enable_x64(True):
        dyn = make_dynamics(robot, "rnea", np.float64)
        tau = np.asarray(jax.jit(jax.vmap(dyn.inverse))(q, qd, qdd))
    assert np.abs(ref_tau).max() > 1.0
    assert np.abs(tau - ref_tau).max() <= TOL_TAU_F64 * np.abs(ref_tau).max()


def test_site_end_effector_with_offset():
    robot = load_robot(
        ASSETS / "continuous_arm.xml", end_effector="tip", end_effector_offset=[0.01, 0.02, 0.03]
    )
    plain = load_robot(ASSETS / "continuous_arm.xml")
    assert plain.site_name == "tip" and robot.site_name == END_EFFECTOR_SITE
    q = plain.sample_postures(np.random.default_rng(5), N_POSTURES)
    m = plain.mj_model
    d = mujoco.MjData(m)
    expected = np.zeros((N_POSTURES, 3))
    for i, qi in enumerate(q):
        d.qpos[plain.qpos_adr] = qi
        mujoco.mj_kinematics(m, d)
        expected[i] = d.site("tip").xpos + d.site("tip").xmat.reshape(3, 3) @ [0.01, 0.02, 0.03]
    got = _site_positions(robot.mj_model, robot, q, robot.site_name)
    np.testing.assert_allclose(got, expected, atol=TOL_EXACT)
    assert np.abs(got - _site_positions(m, plain, q, "tip")).max() > 0.01


# -- rest posture, torque and velocity limits --------------------------------------------------

KEYED = """<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body name="a">
      <joint name="j1" axis="0 0 1" range="-1 1"/>
      <joint name="j2" axis="0 1 0"/>
      <geom size="0.1" mass="1"/>
      <site name="tip" pos="0 0 0.2"/>
    </body>
  </worldbody>
  <keyframe>{keys}</keyframe>
</mujoco>
"""


@pytest.mark.parametrize(
    "keys, source, rest",
    [
        (
            '<key name="a" qpos="0.1 5"/><key name="home" qpos="0.2 6"/><key name="rest" '
            'qpos="0.3 7"/>',
            "keyframe 'rest'",
            [0.3, 7],
        ),
        (
            '<key name="a" qpos="0.1 5"/><key name="home" qpos="0.2 6"/>',
            "keyframe 'home'",
            [0.2, 6],
        ),
        ('<key name="a" qpos="0.1 5"/><key name="b" qpos="0.2 6"/>', "keyframe 'a'", [0.1, 5]),
        ('<key qpos="0.4 -5"/>', "keyframe '#0'", [0.4, -5]),
        ("", "qpos0 (the model has no keyframe)", [0.0, 0.0]),
        (
            '<key name="home" qpos="1 -9"/>',
            "keyframe 'home', moved 5% of the range off the limits for ['j1']",
            [1 - REST_MARGIN * 2, -9],
        ),
    ],
)
def test_rest_keyframe_order(tmp_path, keys, source, rest):
    path = tmp_path / "keyed.xml"
    path.write_text(KEYED.format(keys=keys))
    robot = load_robot(path)
    assert robot.rest_source == source
    np.testing.assert_allclose(robot.rest, rest, rtol=1e-12)


def test_rest_keyframe_outside_the_limits_is_refused(tmp_path):
    path = tmp_path / "keyed.xml"
    path.write_text(KEYED.format(keys='<key name="home" qpos="1.5 0"/>'))
    with pytest.raises(UserError, match=r"keyframe 'home'.*'j1'"):
        load_robot(path)


TORQUES = """<mujoco>
  <worldbody>
    <body name="a">
      <joint name="frc" axis="0 0 1" actuatorfrcrange="-10 12"/>
      <joint name="two" axis="0 1 0"/>
      <joint name="free_motor" axis="1 0 0"/>
      <joint name="bare" axis="0 0 1"/>
      <joint name="servo" axis="0 1 0"/>
      <geom size="0.1" mass="1"/>
      <site name="tip" pos="0 0 0.2"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="frc" forcerange="-50 50"/>
    <motor name="m1" joint="two" gear="2" forcerange="-5 5"/>
    <motor name="m2" joint="two" gear="-3" forcerange="-4 6"/>
    <motor name="unlimited" joint="free_motor"/>
    <position name="servo" joint="servo" kp="100" forcerange="-7 9"/>
    {extra}
  </actuator>
</mujoco>
"""


def test_torque_limit_sources(tmp_path):
    path = tmp_path / "torques.xml"
    path.write_text(TORQUES.format(extra=""))
    robot = load_robot(path)
    np.testing.assert_array_equal(robot.torque_limit, [10, 5 * 2 + 4 * 3, np.inf, np.inf, 7])
    assert robot.torque_limit_source == (
        "joint actuatorfrcrange",  # the joint's own range wins over its actuator's
        "actuator 'm1', 'm2' forcerange x |gear|",
        "none (actuator 'unlimited' has no forcerange)",
        "none",
        "actuator 'servo' forcerange x |gear|",
    )
    path.write_text(TORQUES.format(extra='<motor name="push" joint="bare" forcerange="0 5"/>'))
    with pytest.raises(UserError, match=r"actuator 'push': forcerange: expected lower < 0"):
        load_robot(path)


def test_velocity_limits_from_a_config_are_stored_in_the_model():
    path = ASSETS / "continuous_arm.xml"
    robot = load_robot(path, velocity_limits={"spin": 3.0, "reach": 0.5})
    np.testing.assert_array_equal(robot.velocity_limit, [3.0, np.inf, np.inf, 0.5])
    again = robot_from_mjcf_text(robot.name, robot.mjcf, robot.joint_names, robot.site_name)
    np.testing.assert_array_equal(again.velocity_limit, robot.velocity_limit)
    listed = load_robot(path, joints=["lift", "spin"], velocity_limits=[1.5, 2.5])
    np.testing.assert_array_equal(listed.velocity_limit, [1.5, 2.5])
    # Over the model's own numeric: the joints not given keep its values.
    mahru = load_robot("mahru_arm", velocity_limits={"elbow": 2.0})
    np.testing.assert_array_equal(mahru.velocity_limit, [3, 5, 5, 5, 2, 6, 6])
    for limits, expected in [
        ({"knee": 1.0}, "'knee' is not a controlled joint"),
        ([1.0, 2.0], "expected 4 values"),
        ({"spin": -1.0}, "spin: expected a number > 0"),
        ({"spin": "fast"}, "spin: expected a number > 0"),
        ("fast", "expected a list of numbers or a mapping"),
    ]:
        with pytest.raises(UserError, match=expected):
            load_robot(path, velocity_limits=limits)


def test_config_keys_reach_the_robot():
    cfg = config_from_dict(
        {
            "robot": {
                "mjcf": str(ASSETS / "continuous_arm.xml"),
                "end_effector": "fore",
                "end_effector_offset": [0.0, 0.0, 0.1],
                "velocity_limits": {"lift": 2.0},
            }
        }
    )
    robot = make_robot(cfg)
    assert robot.joint_names == ("spin", "lift", "twist", "reach")
    assert robot.site_name == END_EFFECTOR_SITE
    np.testing.assert_array_equal(robot.velocity_limit, [np.inf, 2.0, np.inf, np.inf])
    with pytest.raises(UserError, match="expected one of them"):
        load_robot(ASSETS / "continuous_arm.xml", site="tip", end_effector="fore")
    with pytest.raises(UserError, match="end_effector_offset: expected 3 finite numbers"):
        load_robot(ASSETS / "continuous_arm.xml", end_effector_offset=[0.0, 1.0])
    with pytest.raises(UserError, match="no site or body named 'paw'"):
        load_robot(ASSETS / "continuous_arm.xml", end_effector="paw")


# -- the command line ----------------------------------------------------------------------------


def test_cli_robot_report_and_config_section(include_model, capsys):
    path = include_model / "robot.xml"
    argv = ["robot", str(path), "--end-effector", "arm", "--end-effector-offset", "0", "0", "0.3"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "files read (4," in out and "parts/assets.xml" in out and "meshes/link.stl" in out
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("  ")}
    assert "continuous" in rows["pitch"] and "-2 .. 2 rad" in rows["yaw"]
    assert "'arm' (site 'end_effector' added to body 'arm')" in out
    assert "rest posture: qpos0 (the model has no keyframe): [0., 0.]" in out
    # the reach from the deepest body that stays put, and the demos region derived from it
    reach = re.search(r"^reach: (\S+) m from body '(\w+)'", out, re.M)
    region = re.search(r"^demos region \(derived from the reach\): about body '(\w+)', radius "
                       r"(\S+) \.\. (\S+) m", out, re.M)  # fmt: skip
    assert reach and region, out
    assert region[1] == reach[2] and float(region[3]) == pytest.approx(0.75 * float(reach[1]), 1e-3)
    section = yaml.safe_load(out[out.index("\nrobot:") :])
    assert section["robot"]["end_effector_offset"] == [0.0, 0.0, 0.3]
    robot = make_robot(config_from_dict(section))  # the printed section is a working config
    assert robot.joint_names == ("yaw", "pitch") and robot.site_name == END_EFFECTOR_SITE
    assert main(["robot", str(path), "--joints", "pitch,yaw"]) == 0
    assert "joints (2, as given)" in capsys.readouterr().out
    assert main(["robot", str(path.with_name("missing.xml"))]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "missing.xml: MJCF file not found" in err
    assert "other joints" not in out  # every joint of that model is controlled


def test_cli_robot_names_the_joints_it_holds(tmp_path, capsys):
    """A model with more joints than the chain (a floating base, the other arm): the report
    names those held at qpos0, and says so of a free joint."""
    text = (ASSETS / "tree_arm.xml").read_text()
    assert main(["robot", str(ASSETS / "tree_arm.xml")]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("other joints"))
    assert "r_slide (slide), r_sh (hinge), r_elbow (hinge), r_wrist (hinge)" in line
    assert "free joint" not in out
    body = text.index("<body", text.index("<worldbody>"))
    floating = text[: text.index(">", body) + 1] + '<freejoint name="float"/>'
    floating += text[text.index(">", body) + 1 :]
    (tmp_path / "floating.xml").write_text(floating)
    assert main(["robot", str(tmp_path / "floating.xml")]) == 0
    out = capsys.readouterr().out
    assert "float (free)" in out and "the chain's base is held fixed" in out
