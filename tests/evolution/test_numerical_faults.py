"""Numerical faults during evolution (issue #9, item 3), a property test over generations.

On the tiny run (configs/tiny.yaml: 40 demonstrations, 6 conditions, T = 24) hypothesis injects
into the generation's inputs: NaN/inf in one demonstration (its trajectory, hand position or
duration), a degenerate basis (one condition's neighbours made identical: no variance, zero
principal components) and an unreachable condition (its final posture beyond a joint limit, or
NaN as from a failed IK). Over several generations: the faulty items are flagged or rejected,
every other condition is compiled exactly as without the faults, and no valid row of the
database ever holds a NaN/inf.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[2]
GENERATIONS = 3


@pytest.fixture(scope="module")
def tiny():
    """Generation 0 of configs/tiny.yaml (as `run.training.run_training` builds it), its jitted
    generation step, and generation 1 without faults."""
    import jax

    from evojax_motion.evolution.sharding import make_sharded_generation_step
    from evojax_motion.motion.database import HUMAN
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run.training import initial_state
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import load_config

    cfg = load_config(REPO / "configs" / "tiny.yaml")
    robot, dyn = make_robot_dynamics(cfg)
    db, cond, *_ = initial_state(cfg, robot, dyn)
    n_human = int(np.sum(db.origin == HUMAN))
    grid = make_time_grid(db.q.shape[1])
    step = make_sharded_generation_step(
        dyn, grid, robot.lower, robot.upper, n_human, cfg.basis, cfg.compiler, cfg.evolution,
        devices=cfg.parallel.devices,
    )  # fmt: skip

    def run(db, cond, g):
        new, stats = step(db, cond, np.asarray(g, np.int32))
        new, stats = jax.device_get((new, stats))
        return type(db)(*(np.asarray(a) for a in new)), stats

    clean1, _ = run(db, cond, 1)
    assert clean1.valid[n_human:].sum() >= 3, "too few conditions compiled to compare with"
    return _Tiny(cfg=cfg, robot=robot, db=db, cond=cond, n=n_human, run=run, clean1=clean1)


class _Tiny(dict):
    def __repr__(self) -> str:  # hypothesis prints the arguments of a failing example
        return "<configs/tiny.yaml generation 0>"


def _neighbours(tiny, db, cond) -> np.ndarray:
    """``(m, k)`` database rows each condition's basis uses in generation 1."""
    from evojax_motion.compiler.basis import select_neighbours

    b = tiny["cfg"].basis
    nb = select_neighbours(db.condition, db.valid, cond.target, b.neighbours, b.radius, b.w_pos)
    return np.where(np.asarray(nb.mask), np.asarray(nb.index), -1)


def _finite_rows(db) -> bool:
    v = db.valid
    return bool(
        np.isfinite(db.q[v]).all()
        and np.isfinite(db.cost[v]).all()
        and np.isfinite(db.duration[v]).all()
        and np.isfinite(db.condition[v]).all()
    )


@settings(
    max_examples=60,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(data=st.data())
def test_faults_are_isolated_and_never_reach_the_database(tiny, data):
    from evojax_motion.evolution.step import boundary_errors
    from evojax_motion.motion.database import nonfinite_rows
    from evojax_motion.motion.timegrid import make_time_grid

    db0, cond0, n, run = tiny["db"], tiny["cond"], tiny["n"], tiny["run"]
    robot, evo = tiny["robot"], tiny["cfg"].evolution
    m = cond0.target.shape[0]
    draw = data.draw
    unreachable = draw(st.integers(0, m - 1), label="unreachable condition")
    degenerate = draw(st.integers(0, m - 1).filter(lambda c: c != unreachable), label="degenerate")
    bad = draw(st.integers(0, n - 1), label="faulty demonstration")
    where = draw(st.sampled_from(["q", "condition", "duration"]), label="field")
    value = draw(st.sampled_from([np.nan, np.inf, -np.inf]), label="value")

    db = type(db0)(*(a.copy() for a in db0))
    # a degenerate basis: the degenerate condition's neighbours all become one demonstration
    rows = _neighbours(tiny, db, cond0)[degenerate]
    rows = rows[rows >= 0]
    db.q[rows], db.duration[rows] = db.q[rows[0]], db.duration[rows[0]]
    # NaN/inf in one demonstration
    if where == "q":
        t = draw(st.integers(0, db.q.shape[1] - 1))
        db.q[bad, t, draw(st.integers(0, db.q.shape[2] - 1))] = value
    elif where == "condition":
        db.condition[bad, draw(st.integers(0, 2))] = value
    else:
        db.duration[bad] = value
    # the product's check of a demonstration database flags exactly the faulty one
    assert nonfinite_rows(db).tolist() == [bad]
    # an unreachable condition: its final posture beyond a joint limit, or NaN (IK failed)
    qf = cond0.boundary.qf.copy()
    if draw(st.booleans(), label="beyond the limits"):
        j = draw(st.integers(0, robot.n_joints - 1))
        qf[unreachable, j] = robot.upper[j] + 0.3
    else:
        qf[unreachable] = np.nan
    cond = cond0._replace(boundary=cond0.boundary._replace(qf=qf))

    # which conditions see a changed demonstration in generation 1
    nb = _neighbours(tiny, db, cond)
    touched = np.isin(nb, [*rows.tolist(), bad]).any(axis=1)
    touched |= (nb != _neighbours(tiny, db0, cond0)).any(axis=1)  # a NaN condition is skipped
    uses_bad = (nb == bad).any(axis=1)
    grid = make_time_grid(db.q.shape[1])

    # the faulty demonstration stays in the database as it was (valid): the generation step
    # itself must keep it out of every evolved row
    for g in range(1, GENERATIONS + 1):
        new, stats = run(db, cond, g)
        ev = slice(n, None)
        assert _finite_rows(new._replace(valid=new.valid & (new.origin == 1)))
        for a, b in zip(db, new):  # the demonstrations are never touched
            assert np.asarray(a)[:n].tobytes() == np.asarray(b)[:n].tobytes()
        assert not new.valid[n + unreachable], g  # rejected, every generation
        assert int(stats.n_rejected_nonfinite) + int(stats.n_rejected_limits) >= 1
        # survivors meet the boundary conditions (a degenerate basis included)
        pos, _ = boundary_errors(grid, new.q[ev], cond.boundary)
        assert (np.asarray(pos)[new.valid[ev]] <= evo.bc_tolerance).all(), g
        if g == 1:
            # a condition whose basis holds a NaN/inf trajectory is rejected as non-finite
            # (a neighbour's NaN duration does not matter: the condition sets the duration) ...
            if where == "q":
                assert not new.valid[ev][uses_bad].any()
                assert int(stats.n_rejected_nonfinite) >= int(uses_bad.sum())
            # ... the rest of the generation proceeds: the untouched, reachable conditions are
            # compiled exactly as without any fault
            same = ~touched
            same[unreachable] = False
            clean = tiny["clean1"]
            np.testing.assert_array_equal(new.valid[ev][same], clean.valid[ev][same])
            np.testing.assert_array_equal(new.q[ev][same], clean.q[ev][same])
            np.testing.assert_array_equal(new.cost[ev][same], clean.cost[ev][same])
        db = new
    assert np.isfinite(np.asarray(stats.db_cost_mean)) or not db.valid[n:].any()
