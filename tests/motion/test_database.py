"""Database layout, atomic save/load round trip, and clear errors on bad files."""

from pathlib import Path

import numpy as np
import pytest

from evojax_motion.errors import UserError
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.database import (
    EVOLVED,
    HUMAN,
    DatabaseMeta,
    humans_only,
    load_database,
    make_database,
    save_database,
)

META = DatabaseMeta("toy", "<mujoco/>", ("a", "b"), "hand", True, "test data")


def toy_db(n=3, capacity=5, t=8):
    rng = np.random.default_rng(0)
    return make_database(
        rng.normal(size=(n, t, 2)), np.full(n, 0.7), rng.normal(size=(n, 3)), np.arange(n), capacity
    )


def test_layout_pads_with_empty_evolved_slots():
    db = toy_db()
    assert db.q.shape == (5, 8, 2)
    np.testing.assert_array_equal(db.valid, [1, 1, 1, 0, 0])
    np.testing.assert_array_equal(db.origin, [HUMAN] * 3 + [EVOLVED] * 2)
    assert np.isinf(db.cost[3:]).all()
    assert not humans_only(db._replace(valid=np.ones(5, bool))).valid[3:].any()


def test_round_trip_is_exact(tmp_path):
    db = toy_db()
    path = save_database(tmp_path / "db.npz", db, META)
    db2, meta2 = load_database(path)
    for a, b in zip(db, db2):
        np.testing.assert_array_equal(a, b)
    assert meta2 == META
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary left behind


def test_load_refuses_pickles_and_garbage(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(UserError, match=r"bad\.npz"):
        load_database(bad)
    with pytest.raises(UserError, match="not found"):
        load_database(tmp_path / "missing.npz")
    np.savez(tmp_path / "obj.npz", q=np.array([object()], dtype=object))
    with pytest.raises(UserError, match=r"obj\.npz"):
        load_database(tmp_path / "obj.npz")


def test_load_rejects_nan_and_shape_mismatch(tmp_path):
    db = toy_db()
    q = db.q.copy()
    q[1, 2, 0] = np.nan
    save_database(tmp_path / "nan.npz", db._replace(q=q), META)
    with pytest.raises(UserError, match="primitive 1 has NaN"):
        load_database(tmp_path / "nan.npz")
    meta3 = DatabaseMeta("toy", "<mujoco/>", ("a", "b", "c"), "hand", True)
    save_database(tmp_path / "joints.npz", db, meta3)
    with pytest.raises(UserError, match="joint_names"):
        load_database(tmp_path / "joints.npz")


CONTINUOUS_ARM = Path(__file__).parents[1] / "assets" / "continuous_arm.xml"
TOL_TURN = 1e-5  # [rad] float32 rounding of a whole turn added and taken away again


def _write_unnormalised(path, db, meta):
    """A database file as written before continuous joints were stored on the rest branch."""
    np.savez(
        path,
        **{k: np.asarray(v) for k, v in db._asdict().items()},
        joint_names=np.asarray(meta.joint_names, dtype=str),
        robot_name=np.asarray(meta.robot_name),
        robot_mjcf=np.asarray(meta.mjcf),
        site_name=np.asarray(meta.site_name),
        synthetic=np.asarray(meta.synthetic),
        description=np.asarray(meta.description),
        format_version=np.asarray(1),
    )


def test_continuous_joints_are_loaded_and_saved_on_the_rest_branch(tmp_path):
    """Rows stored whole turns away from the rest branch, or wrapped into [-pi, pi) in the
    middle of a motion, come back as the same poses on one branch; limited joints are untouched
    bit for bit."""
    robot = load_robot(CONTINUOUS_ARM)
    cont = robot.continuous
    assert cont.tolist() == [True, False, True, False]  # spin, lift, twist, reach
    rng = np.random.default_rng(1)
    n, t = 6, 16
    s = np.linspace(0.0, 1.0, t)[None, :, None]
    final = robot.rest + rng.uniform(-1.0, 1.0, (n, robot.n_joints)) * [2.0, 0.5, 2.0, 0.02]
    final[4, 0] = 4.0  # spin from rest (2.5 rad) past pi
    truth = (robot.rest + s * (final - robot.rest)[:, None]).astype(np.float32)  # (n, t, J)
    stored = truth.copy()
    turns = np.array([0, 1, -2, 3, 0, -1])
    stored[..., cont] += (2 * np.pi * turns)[:, None, None].astype(np.float32)
    wrapped = (stored[4] + np.pi) % (2 * np.pi) - np.pi  # wrapped like atan2 would
    stored[4][:, cont] = wrapped[:, cont]
    assert np.abs(np.diff(stored[4][:, 0])).max() > np.pi  # the row jumps a turn
    db = make_database(stored, np.full(n, 0.8), rng.normal(size=(n, 3)), np.ones(n))
    meta = DatabaseMeta.of_robot(robot, synthetic=True, description="branch test")

    old = tmp_path / "old.npz"
    _write_unnormalised(old, db, meta)
    loaded, _ = load_database(old)
    np.testing.assert_allclose(loaded.q[..., cont], truth[..., cont], atol=TOL_TURN)
    np.testing.assert_array_equal(loaded.q[..., ~cont], stored[..., ~cont])
    mean = loaded.q[..., cont].mean(axis=1)
    assert np.all(np.abs(mean - robot.rest[cont]) <= np.pi)

    saved = save_database(tmp_path / "new.npz", db, meta)
    with np.load(saved) as raw:
        np.testing.assert_allclose(raw["q"][..., cont], truth[..., cont], atol=TOL_TURN)
        np.testing.assert_array_equal(raw["q"][..., ~cont], stored[..., ~cont])


def test_limited_joints_round_trip_bit_for_bit(tmp_path):
    """A robot without continuous joints: the branch step leaves every bit as stored."""
    robot = load_robot("arm6")
    rng = np.random.default_rng(2)
    q = robot.rest + rng.normal(0.0, 0.5, (4, 10, robot.n_joints))
    db = make_database(q, np.ones(4), rng.normal(size=(4, 3)), np.ones(4), capacity=6)
    meta = DatabaseMeta.of_robot(robot, synthetic=False, description="")
    db2, _ = load_database(save_database(tmp_path / "db.npz", db, meta))
    assert np.asarray(db2.q).tobytes() == np.asarray(db.q).tobytes()
