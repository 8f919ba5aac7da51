"""Trajectory files (export.py): columns, exact round trips in the three formats, refusal of
NaN, and torques that C MuJoCo's ``mj_inverse`` recomputes from the file's own q, qd, qdd."""

from __future__ import annotations

import json

import numpy as np
import pytest
from online_support import mj_inverse_torques, online_env, query

from evojax_motion.errors import UserError
from evojax_motion.run.export import (
    column_names,
    make_trajectory_data,
    read_trajectory,
    resolve_format,
    write_trajectory,
)

TOL_TAU = 2e-3  # N m: float32 RNEA torques vs float64 mj_inverse of the written rows
NAMES = ("a", "b")


def _data(meta=None, dtype=np.float32):
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 0.7, 5).astype(dtype)
    q, qd, qdd, tau = (rng.normal(size=(5, 2)).astype(dtype) * 10.0**k for k in range(4))
    return make_trajectory_data(t, q, qd, qdd, tau, NAMES, meta or {"target": [0.1, 0.2, 0.3]})


def test_columns():
    assert column_names(NAMES) == [
        "t", "q_a", "q_b", "qd_a", "qd_b", "qdd_a", "qdd_b", "tau_a", "tau_b",
    ]  # fmt: skip


@pytest.mark.parametrize("fmt", ["csv", "npz", "json"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_round_trip_is_exact(tmp_path, fmt, dtype):
    data = _data(dtype=dtype)
    path = write_trajectory(tmp_path / f"traj.{fmt}", data)
    back = read_trajectory(path)
    assert back.joint_names == NAMES
    for name in ("t", "q", "qd", "qdd", "tau"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name), dtype), getattr(data, name))
    assert back.meta == {"target": [0.1, 0.2, 0.3]}


def test_csv_layout(tmp_path):
    path = write_trajectory(tmp_path / "traj.csv", _data())
    lines = path.read_text().splitlines()
    assert lines[0] == "# target: [0.1, 0.2, 0.3]"  # the meta, as comments before the header
    assert lines[1] == ",".join(column_names(NAMES))
    assert len(lines) == 7 and all(len(row.split(",")) == 9 for row in lines[1:])


def test_nan_is_never_written(tmp_path):
    data = _data()
    q = data.q.copy()
    q[2, 1] = np.nan
    with pytest.raises(UserError, match=r"trajectory\.q: contains NaN/inf"):
        write_trajectory(tmp_path / "bad.csv", data._replace(q=q))
    assert not (tmp_path / "bad.csv").exists() and list(tmp_path.iterdir()) == []
    # NaN in the metadata becomes null (strict JSON), never "NaN"
    path = write_trajectory(tmp_path / "m.json", _data(meta={"margin": float("nan")}))
    assert json.loads(path.read_text())["meta"] == {"margin": None}


def test_format_resolution():
    assert resolve_format("x.CSV") == "csv"
    assert resolve_format("x.out", "json") == "json"
    with pytest.raises(UserError, match="cannot tell the format"):
        resolve_format("x.txt")
    with pytest.raises(UserError, match="contradicts --format npz"):
        resolve_format("x.csv", "npz")
    with pytest.raises(UserError, match=r"trajectory\.tau: expected shape"):
        d = _data()
        make_trajectory_data(d.t, d.q, d.qd, d.qdd, d.tau[:, :1], NAMES)


@pytest.mark.parametrize("fmt", ["csv", "json"])
def test_exported_torques_equal_mj_inverse_of_the_file(tmp_path, fmt):
    """The required check: read the file back, recompute tau with C MuJoCo from its own columns."""
    env = online_env()
    r = query(env, env.db.condition[2:3] + 0.01)
    assert r.ok[0]
    data = make_trajectory_data(r.t[0], r.q[0], r.qd[0], r.qdd[0], r.tau[0], env.robot.joint_names)
    back = read_trajectory(write_trajectory(tmp_path / f"traj.{fmt}", data))
    ref = mj_inverse_torques(env.robot, back.q, back.qd, back.qdd)
    assert np.abs(back.tau).max() > 1.0  # a real motion, not zeros
    np.testing.assert_allclose(back.tau, ref, atol=TOL_TAU)
