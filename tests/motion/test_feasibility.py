"""Feasibility in the offline evolution: joint, velocity and torque limits (continuous joints have
none), the rejection counts of the generation step and the human rows over a limit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from evojax_motion.compiler.optimisation import LIMIT_TOL, checked_limits
from evojax_motion.errors import UserError
from evojax_motion.motion.database import make_database

ASSETS = Path(__file__).resolve().parents[1] / "assets"
REPO = Path(__file__).resolve().parents[2]

N_HUMAN, T_SAMPLES, M_COND = 40, 24, 5
REL_TOL = 1e-4  # float32 torques / velocities recomputed here against those of the step
BAD_LIMITS = r"^joint limits: expected finite limits \(or -inf / \+inf: none\) with lower < upper"


def peaks(dyn, grid, q, duration):
    """Peak |qd| and |tau| of each row, computed here: ``(n, J)`` x 2 (numpy)."""
    import jax

    from evojax_motion.motion.objective import trajectory_torques
    from evojax_motion.motion.timegrid import derivatives

    def one(q1, d):
        qd, _ = derivatives(grid, q1, d)
        return abs(qd).max(axis=0), abs(trajectory_torques(dyn, grid, q1, d)).max(axis=0)

    pqd, ptau = jax.jit(jax.vmap(one))(np.asarray(q), np.asarray(duration))
    return np.asarray(pqd), np.asarray(ptau)


def small_setup(robot, seed: int = 0):
    """Synthetic human reaches (warped minimum jerk from rest plus a bump) to postures drawn in
    ``robot.posture_box`` near rest, their conditions and the pieces of a generation step."""
    import jax

    from evojax_motion.evolution.conditions import make_conditions
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.motion.objective import torque_cost
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.settings.compiler import BasisSettings, OptimSettings
    from evojax_motion.settings.evolution import EvolutionSettings

    dyn = make_dynamics(robot, "rnea")
    grid = make_time_grid(T_SAMPLES)
    rng = np.random.default_rng(seed)
    lo, hi = robot.posture_box(0.05)
    span = hi - lo
    qf = np.clip(robot.rest + rng.normal(0, 0.15, (N_HUMAN, robot.n_joints)) * span, lo, hi)
    s = np.asarray(grid.s, np.float64)[None, :, None]
    w = s + rng.uniform(-0.4, 0.4, (N_HUMAN, 1, 1)) * s * (1 - s)
    mj = 10 * w**3 - 15 * w**4 + 6 * w**5
    bump = np.sin(np.pi * s) ** 2 * rng.normal(0, 0.05, (N_HUMAN, 1, robot.n_joints)) * span
    q = np.clip(robot.rest + (qf - robot.rest)[:, None, :] * mj + bump, lo, hi).astype(np.float32)
    dur = rng.uniform(0.6, 0.9, N_HUMAN).astype(np.float32)
    hand = np.asarray(jax.vmap(lambda x: dyn.site_pose(x)[0])(q[:, -1]))
    cost = jax.jit(jax.vmap(lambda a, d: torque_cost(dyn, grid, a, d)))(q, dur)
    humans = make_database(q, dur, hand, cost=np.asarray(cost))
    spread = float(np.max(np.ptp(hand, axis=0)))
    basis = BasisSettings(radius=max(0.15, spread / 2), neighbours=6)
    evo = EvolutionSettings(conditions=M_COND, generations=2, min_neighbours=3)
    cond = make_conditions(humans, dyn, robot, evo, basis, grid, jax.random.key(3))
    cond = jax.tree_util.tree_map(np.asarray, cond)
    optim = OptimSettings(method="adam", max_iters=10)
    return dict(robot=robot, dyn=dyn, grid=grid, humans=humans, basis=basis, evo=evo,
                cond=cond, optim=optim)  # fmt: skip


def run_generations(s, generations: int = 2, **limits):
    """``(db, [stats])`` after ``generations`` steps from empty evolved slots."""
    import jax

    from evojax_motion.evolution.step import init_evolved_slots, make_generation_step

    r = s["robot"]
    step = make_generation_step(
        s["dyn"], s["grid"], r.lower, r.upper, N_HUMAN, s["basis"], s["optim"], s["evo"], **limits
    )
    db = init_evolved_slots(s["humans"], s["cond"])
    all_stats = []
    for g in range(1, generations + 1):
        db, stats = step(db, s["cond"], np.int32(g))
        all_stats.append(jax.tree_util.tree_map(np.asarray, stats))
    return jax.tree_util.tree_map(np.asarray, db), all_stats


def test_infinite_limits_mean_none_and_bad_ones_are_refused():
    lo, hi = checked_limits([-np.inf, -1.0], [np.inf, 1.0])
    assert np.isneginf(lo[0]) and np.isposinf(hi[0])
    bad = [
        ([np.nan, -1.0], [1.0, 1.0]),
        ([1.0, -1.0], [0.5, 1.0]),
        ([np.inf, -1.0], [np.inf, 1.0]),
        ([-np.inf, -1.0], [-np.inf, 1.0]),
    ]
    for lower, upper in bad:
        with pytest.raises(UserError, match=BAD_LIMITS):
            checked_limits(lower, upper)


@pytest.fixture(scope="module")
def continuous():
    from evojax_motion.model.robot import load_robot

    robot = load_robot(ASSETS / "continuous_arm.xml")
    assert robot.continuous.any() and not robot.continuous.all()
    return small_setup(robot, seed=1)


def test_generation_with_continuous_joints_respects_the_finite_limits(continuous):
    s = continuous
    r = s["robot"]
    db, stats = run_generations(s)
    last = stats[-1]
    assert int(last.n_valid) > 0, last
    assert np.isfinite(float(last.db_cost_mean))
    ev = slice(N_HUMAN, None)
    q = db.q[ev][db.valid[ev]]
    finite = ~r.continuous
    assert np.all(q[..., finite] >= r.lower[finite] - LIMIT_TOL)
    assert np.all(q[..., finite] <= r.upper[finite] + LIMIT_TOL)
    assert np.all(np.isfinite(q))


@pytest.fixture(scope="module")
def mahru():
    from evojax_motion.model.robot import load_robot

    return small_setup(load_robot("mahru_arm"), seed=0)


def test_low_torque_and_velocity_limits_reject_offspring(mahru):
    """Limits at half the human rows' peaks: some offspring are rejected for each, and every
    accepted row is within all limits (torques and velocities recomputed here)."""
    s = mahru
    humans = s["humans"]
    pqd, ptau = peaks(s["dyn"], s["grid"], humans.q, humans.duration)
    _, free_stats = run_generations(s, generations=1)
    assert int(free_stats[0].n_rejected_torque) == int(free_stats[0].n_rejected_velocity) == 0
    n_free_valid = int(free_stats[0].n_valid)
    assert n_free_valid > 0

    tau_limit = 0.5 * np.median(ptau, axis=0)
    db, stats = run_generations(s, generations=1, torque_limit=tau_limit)
    assert int(stats[0].n_rejected_torque) > 0, stats[0]
    qd_limit = 0.5 * np.median(pqd, axis=0)
    db_v, stats_v = run_generations(s, generations=1, velocity_limit=qd_limit)
    assert int(stats_v[0].n_rejected_velocity) > 0, stats_v[0]
    for st in (stats[0], stats_v[0], free_stats[0]):  # the rejections exclude each other
        rejected = sum(int(getattr(st, f)) for f in st._fields if f.startswith("n_rejected_"))
        assert rejected <= M_COND

    ev = slice(N_HUMAN, None)
    for d, tl, vl in ((db, tau_limit, np.inf), (db_v, np.inf, qd_limit)):
        keep = d.valid[ev]
        if keep.any():
            v, t = peaks(s["dyn"], s["grid"], d.q[ev][keep], d.duration[ev][keep])
            assert np.all(t <= tl * (1 + REL_TOL)) and np.all(v <= vl * (1 + REL_TOL))


def test_count_over_limits_of_human_rows(mahru):
    from evojax_motion.motion.feasibility import count_over_limits, over_limits_line

    s = mahru
    humans, robot = s["humans"], s["robot"]
    pqd, ptau = peaks(s["dyn"], s["grid"], humans.q, humans.duration)
    counts = count_over_limits(humans, robot, s["dyn"])
    assert counts.rows == N_HUMAN
    assert counts.torque == int(np.any(ptau > robot.torque_limit, axis=1).sum())
    assert counts.velocity == int(np.any(pqd > robot.velocity_limit, axis=1).sum())
    assert counts.joint == 0  # the synthetic rows are clipped into the box

    class Low:  # the same robot with a torque limit below most peaks
        lower, upper, velocity_limit = robot.lower, robot.upper, robot.velocity_limit
        torque_limit = np.median(ptau, axis=0)

    low = count_over_limits(humans, Low, s["dyn"])
    expected = int(np.any(ptau > Low.torque_limit, axis=1).sum())
    assert low.torque == expected > 0 and low.any >= expected
    assert f"{low.any} of {N_HUMAN}" in over_limits_line(low)

    # as a run counts them: from the peaks of the cost program's own pass (`initial_state`)
    from evojax_motion.motion.objective import CostProgram

    measured = CostProgram(s["dyn"], s["grid"], N_HUMAN)(np.asarray(humans.q), humans.duration)
    np.testing.assert_allclose(measured.peak_torque, ptau, rtol=REL_TOL)
    np.testing.assert_allclose(measured.peak_velocity, pqd, rtol=REL_TOL)
    given = count_over_limits(
        humans, Low, s["dyn"], peaks=(measured.peak_velocity, measured.peak_torque)
    )
    assert given.torque == int(np.any(measured.peak_torque > Low.torque_limit, axis=1).sum())
    assert abs(given.torque - low.torque) <= 1  # the row at the median may round either way
    assert (given.rows, given.joint, given.velocity) == (low.rows, low.joint, low.velocity)
    twice = 2 * measured.peak_torque  # the count is the given peaks', not recomputed ones
    doubled = count_over_limits(humans, Low, s["dyn"], peaks=(measured.peak_velocity, twice))
    assert doubled.torque == int(np.any(twice > Low.torque_limit, axis=1).sum()) > given.torque


@pytest.mark.slow
def test_tiny_run_keeps_evolved_rows_within_every_limit(tmp_path):
    """configs/tiny.yaml trained: every valid evolved row of db_final is inside the joint ranges,
    and its peak |qd| and |tau| (recomputed here with the run's dynamics) within the limits."""
    from evojax_motion.motion.database import human_mask, load_database
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run.training import run_training
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import load_config

    cfg = load_config(REPO / "configs" / "tiny.yaml")
    run_training(cfg, tmp_path / "run", progress=False)
    db, _ = load_database(tmp_path / "run" / "db_final.npz")
    robot, dyn = make_robot_dynamics(cfg)
    rows = np.asarray(db.valid) & ~human_mask(db)
    assert rows.any()
    q, dur = np.asarray(db.q)[rows], np.asarray(db.duration)[rows]
    assert np.all((q >= robot.lower - LIMIT_TOL) & (q <= robot.upper + LIMIT_TOL))
    pqd, ptau = peaks(dyn, make_time_grid(q.shape[1]), q, dur)
    assert np.all(pqd <= robot.velocity_limit * (1 + REL_TOL)), pqd.max(axis=0)
    assert np.all(ptau <= robot.torque_limit * (1 + REL_TOL)), ptau.max(axis=0)
    metrics = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    assert all("n_rejected_torque" in json.loads(x) for x in metrics)


# Velocities scale exactly with 1 / duration; the derivative stencil and the division round in
# float32 (a few ulps of the speeds recomputed here).
SLOWED_REL_TOL = 1e-5


def test_demonstrations_are_slowed_just_to_the_velocity_limits():
    """`slowed_to_velocity_limits`: at the returned durations every row's joint speeds,
    recomputed from its samples, keep within (1 - headroom) x limit; a slowed row has its
    fastest joint at that bound (slowed no more than needed); a row within keeps its duration
    bit for bit; a joint without a limit (inf) never slows a row."""
    from evojax_motion.motion.feasibility import slowed_line, slowed_to_velocity_limits
    from evojax_motion.motion.timegrid import derivatives, make_time_grid

    rng = np.random.default_rng(3)
    grid = make_time_grid(T_SAMPLES)
    n, j, headroom = 12, 3, 0.05
    s = np.asarray(grid.s, np.float64)[None, :, None]
    q = (rng.normal(0, 1.0, (n, 1, j)) * (10 * s**3 - 15 * s**4 + 6 * s**5)).astype(np.float32)
    q[:, :, 2] *= 50.0  # far too fast, but the joint has no limit
    duration = rng.uniform(0.5, 1.5, n).astype(np.float32)
    limit = np.array([1.0, 1.5, np.inf])

    def speeds(d):
        return np.abs(np.asarray(derivatives(grid, q, np.asarray(d, np.float32))[0])).max(axis=1)

    slowed, factor = slowed_to_velocity_limits(duration, speeds(duration), limit, headroom)
    usage = (speeds(slowed) / ((1 - headroom) * limit))[:, :2].max(axis=1)
    was = factor > 1
    assert was.any() and (~was).any()  # the draw has rows of both kinds
    assert (usage <= 1 + SLOWED_REL_TOL).all()
    np.testing.assert_allclose(usage[was], 1.0, rtol=SLOWED_REL_TOL)
    np.testing.assert_array_equal(slowed[~was], duration[~was].astype(np.float64))
    np.testing.assert_allclose(slowed / duration, factor, rtol=1e-12)
    line = slowed_line(factor, headroom)
    assert line is not None and line.startswith(f"demonstrations: {was.sum()} of {n} faster")
    assert slowed_line(np.ones(n), headroom) is None


def test_a_run_counts_its_demonstrations_slowed_unless_told_otherwise(capsys):
    """`run.training.neighbour_durations`: the slowed durations with ``evolution.fit_speed``
    (and one log line), the recorded ones (None) without it or with a fixed duration."""
    from types import SimpleNamespace

    from evojax_motion.run.training import neighbour_durations
    from evojax_motion.settings import config_from_dict

    cfg = config_from_dict({})
    robot = SimpleNamespace(velocity_limit=np.array([1.0, 2.0]))  # all that is read of it
    duration = np.array([1.0, 2.0])
    peak = np.array([[2.0, 1.0], [0.5, 1.0]])  # row 0 twice too fast on joint 0
    got = neighbour_durations(cfg, robot, duration, peak)
    usable = 1 - cfg.compiler.limit_headroom
    np.testing.assert_allclose(got, [2.0 / usable, 2.0])
    assert "demonstrations: 1 of 2 faster" in capsys.readouterr().err
    off = config_from_dict({}, ["evolution.fit_speed=false"])
    fixed = config_from_dict({}, ["evolution.duration=1.5"])
    assert neighbour_durations(off, robot, duration, peak) is None
    assert neighbour_durations(fixed, robot, duration, peak) is None


def test_a_run_says_when_a_generation_discards_many_offspring():
    """`run.training.rejections_line`: from a quarter of the conditions on, one warning with
    each reason's count and the hint of the most common one; below it, nothing."""
    from evojax_motion.run.training import rejections_line

    row = {"generation": 10, "n_rejected_velocity": 36, "n_rejected_torque": 1,
           "n_rejected_bc": 1, "n_rejected_limits": 0, "n_rejected_nonfinite": 0}  # fmt: skip
    line = rejections_line(row, 40)
    assert line is not None
    assert line.startswith("warning: generation 10 discarded 38 of 40 offspring (velocity limit")
    assert "torque limit 1, boundary conditions 1;" in line and "joint range" not in line
    assert line.endswith("(evolution.fit_speed, evolution.duration)")
    assert rejections_line({**row, "n_rejected_velocity": 7}, 40) is None  # 9 < 10
    assert rejections_line({**row, "n_rejected_velocity": 8}, 40) is not None  # 10 of 40
    only_range = {"generation": 2, "n_rejected_limits": 5}
    assert "(evolution.region_margin)" in rejections_line(only_range, 8)
