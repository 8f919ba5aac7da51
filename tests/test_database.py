"""Database layout, atomic save/load round trip, and clear errors on bad files."""

import numpy as np
import pytest

from evojax_motion.database import (
    EVOLVED,
    HUMAN,
    DatabaseMeta,
    humans_only,
    load_database,
    make_database,
    save_database,
)
from evojax_motion.errors import UserError

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
