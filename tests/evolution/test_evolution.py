"""Survivor selection, slot layout, the condition set and one jitted generation (evolution.py,
conditions.py)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evojax_motion.evolution.step import (
    init_evolved_slots,
    rms_deviation_deg,
    select_survivors,
    write_slots,
)
from evojax_motion.motion.database import EVOLVED, HUMAN, make_database
from evojax_motion.settings.evolution import EvolutionSettings

# --------------------------------------------------------------------------- survivor selection


def _reference_selection(cost_inc, valid_inc, cost_off, accept):
    """Plain-Python survivor rule: the offspring wins iff accepted and strictly cheaper than a
    filled incumbent (or the slot is empty)."""
    wins = [
        bool(a) and (not bool(v) or float(co) < float(ci))
        for ci, v, co, a in zip(cost_inc, valid_inc, cost_off, accept)
    ]
    return np.array(wins, bool)


_costs = st.lists(
    st.one_of(
        st.floats(0.0, 1e4, width=32),
        st.sampled_from([np.inf, np.nan, 1.0]),  # ties and junk
    ),
    min_size=6,
    max_size=6,
)


@settings(max_examples=150, deadline=None)
@given(
    cost_inc=_costs,
    cost_off=_costs,
    valid=st.lists(st.booleans(), min_size=6, max_size=6),
    accept=st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_selection_never_worsens_a_slot(cost_inc, cost_off, valid, accept):
    m, t, j = 6, 4, 2
    cost_inc = np.array(cost_inc, np.float32)
    cost_off = np.array(cost_off, np.float32)
    valid = np.array(valid)
    # a filled incumbent always has a finite cost (it was accepted once)
    cost_inc = np.where(valid & ~np.isfinite(cost_inc), 3.0, cost_inc).astype(np.float32)
    # accepted offspring are finite (the step rejects non-finite ones before selection)
    accept = np.array(accept) & np.isfinite(cost_off)
    q_inc = np.arange(m * t * j, dtype=np.float32).reshape(m, t, j)
    q_off = -q_inc - 1.0
    gen_inc = np.full(m, 2, np.int32)

    sel = select_survivors(
        jnp.asarray(q_inc), jnp.asarray(cost_inc), jnp.asarray(valid), jnp.asarray(gen_inc),
        jnp.asarray(q_off), jnp.asarray(cost_off), jnp.asarray(accept), 5,
    )  # fmt: skip
    wins = _reference_selection(cost_inc, valid, cost_off, accept)
    np.testing.assert_array_equal(np.asarray(sel.replaced), wins)
    np.testing.assert_array_equal(np.asarray(sel.valid), valid | wins)
    np.testing.assert_array_equal(np.asarray(sel.q), np.where(wins[:, None, None], q_off, q_inc))
    np.testing.assert_array_equal(np.asarray(sel.generation), np.where(wins, 5, 2))
    new_cost = np.asarray(sel.cost)
    # the property: a filled slot's cost never increases, and it stays filled
    assert (new_cost[valid] <= cost_inc[valid]).all()
    assert np.asarray(sel.valid)[valid].all()
    # with an unchanged set of filled slots the database mean cannot increase either
    if (np.asarray(sel.valid) == valid).all() and valid.any():
        assert new_cost[valid].mean() <= cost_inc[valid].mean()


def test_selection_tie_keeps_incumbent():
    """Equal cost: the incumbent stays (argmin takes the first), no churn."""
    q = jnp.zeros((1, 3, 2))
    sel = select_survivors(
        q, jnp.array([2.0]), jnp.array([True]), jnp.array([1], jnp.int32),
        q + 1.0, jnp.array([2.0]), jnp.array([True]), 4,
    )  # fmt: skip
    assert not bool(sel.replaced[0])
    assert float(sel.q[0, 0, 0]) == 0.0 and int(sel.generation[0]) == 1


# ------------------------------------------------------------------------------- slot layout


class _FakeBoundary:
    def __init__(self, duration):
        self.duration = duration


class _FakeConditions:
    def __init__(self, target, duration):
        self.target = target
        self.boundary = _FakeBoundary(duration)


def _humans(n=5, t=8, j=3, seed=0):
    rng = np.random.default_rng(seed)
    return make_database(
        rng.normal(size=(n, t, j)),
        rng.uniform(0.5, 1.5, n),
        rng.normal(size=(n, 3)),
        cost=rng.uniform(1, 2, n),
    )


def test_init_slots_layout_and_humans_untouched():
    humans = _humans()
    m = 4
    target = np.arange(m * 3, dtype=np.float32).reshape(m, 3)
    dur = np.linspace(0.7, 1.0, m).astype(np.float32)
    db = init_evolved_slots(humans, _FakeConditions(target, dur))
    n = humans.q.shape[0]
    assert db.q.shape == (n + m, *humans.q.shape[1:])
    np.testing.assert_array_equal(np.asarray(db.condition[n:]), target)
    np.testing.assert_array_equal(np.asarray(db.duration[n:]), dur)
    assert (np.asarray(db.origin[:n]) == HUMAN).all() and (
        np.asarray(db.origin[n:]) == EVOLVED
    ).all()
    assert not np.asarray(db.valid[n:]).any() and np.isinf(np.asarray(db.cost[n:])).all()
    for a, b in zip(humans, db):
        np.testing.assert_array_equal(np.asarray(b)[:n], np.asarray(a))

    # writing the evolved slots passes the human rows through bit for bit
    rng = np.random.default_rng(1)
    sel = select_survivors(
        db.q[n:], db.cost[n:], db.valid[n:], db.generation[n:],
        jnp.asarray(rng.normal(size=(m, *db.q.shape[1:])), jnp.float32),
        jnp.asarray(rng.uniform(0, 1, m), jnp.float32), jnp.ones(m, bool), 1,
    )  # fmt: skip
    new = write_slots(db, n, sel)
    for a, b in zip(humans, new):
        assert np.asarray(b)[:n].tobytes() == np.asarray(a).tobytes()
    assert np.asarray(new.valid[n:]).all()


def test_rms_deviation_deg():
    q = jnp.zeros((2, 4, 3))
    ref = q.at[1].set(np.radians(2.0))
    np.testing.assert_allclose(np.asarray(rms_deviation_deg(q, ref)), [0.0, 2.0], atol=1e-5)


@pytest.mark.parametrize(
    "field, value",
    [
        ("conditions", 0),
        ("generations", -1),
        ("min_neighbours", 0),
        ("candidates_per_condition", 0),
        ("ik_tolerance", 0.0),
        ("duration", -1.0),
        ("bc_tolerance", 0.0),
        ("bc_velocity_tolerance", -1.0),
    ],
)
def test_settings_reject_bad_values(field, value):
    with pytest.raises(ValueError, match=rf"^{field}: expected"):
        EvolutionSettings(**{field: value})


def test_settings_defaults_are_the_papers():
    s = EvolutionSettings()
    assert (s.conditions, s.generations) == (300, 10)


# ----------------------------------------------- conditions and one generation on a small arm

TOL_BC_POS = 1e-4  # [rad] float32 start/end angles of compiled trajectories
TOL_COST_REL = 1e-4  # stored cost vs eq. 5 recomputed from the stored trajectory (float32)
N_HUMAN, T_SAMPLES, M_COND = 40, 24, 5


@pytest.fixture(scope="module")
def small():
    """A synthetic human database on the shipped arm (rest-to-rest, time-warped minimum-jerk
    reaches to noisy comfortable postures), its condition set and a jitted generation step."""
    import jax

    from evojax_motion.evolution.conditions import make_conditions
    from evojax_motion.evolution.step import make_generation_step
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import load_robot
    from evojax_motion.motion.objective import torque_cost
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.settings.compiler import BasisSettings, OptimSettings

    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot, "rnea")
    grid = make_time_grid(T_SAMPLES)
    rng = np.random.default_rng(0)
    lo, hi = robot.lower, robot.upper
    comfort = np.clip(robot.rest + np.radians([0, 45, 10, 10, 60, 0, 0]), lo + 0.1, hi - 0.1)
    qf = np.clip(comfort + rng.normal(0, 0.2, (N_HUMAN, robot.n_joints)), lo + 0.05, hi - 0.05)
    # minimum jerk on a randomly warped time plus a rest-to-rest bump: varied shapes, so that the
    # neighbours' PCA has several components (a plain scaled minimum jerk would span one)
    s = np.asarray(grid.s, np.float64)[None, :, None]
    w = s + rng.uniform(-0.4, 0.4, (N_HUMAN, 1, 1)) * s * (1 - s)
    mj = 10 * w**3 - 15 * w**4 + 6 * w**5
    bump = np.sin(np.pi * s) ** 2 * rng.normal(0, 0.1, (N_HUMAN, 1, robot.n_joints))
    q = robot.rest + (qf - robot.rest)[:, None, :] * mj + bump
    q = np.clip(q, lo + 0.01, hi - 0.01).astype(np.float32)
    dur = rng.uniform(0.6, 0.9, N_HUMAN).astype(np.float32)
    hand = np.asarray(jax.vmap(lambda x: dyn.site_pose(x)[0])(jnp.asarray(q[:, -1])))
    cost = jax.jit(jax.vmap(lambda a, d: torque_cost(dyn, grid, a, d)))(q, dur)
    humans = make_database(q, dur, hand, cost=np.asarray(cost))

    basis = BasisSettings(radius=0.15, neighbours=6)
    evo = EvolutionSettings(conditions=M_COND, generations=2, min_neighbours=3)
    cond = make_conditions(humans, dyn, robot, evo, basis, grid, jax.random.key(3))
    cond = jax.tree_util.tree_map(np.asarray, cond)
    optim = OptimSettings(method="adam", max_iters=10)
    step = make_generation_step(dyn, grid, lo, hi, N_HUMAN, basis, optim, evo)
    return dict(
        robot=robot, dyn=dyn, grid=grid, humans=humans, basis=basis, evo=evo, cond=cond,
        step=step, torque_cost=torque_cost,
    )  # fmt: skip


@pytest.mark.slow
def test_conditions_are_reachable_human_like_and_rest_to_rest(small):
    import jax

    robot, dyn, humans, cond = small["robot"], small["dyn"], small["humans"], small["cond"]
    evo, basis = small["evo"], small["basis"]
    b = cond.boundary
    # targets come from the demonstrations' box and have enough human neighbours (recounted)
    lo, hi = humans.condition.min(0), humans.condition.max(0)
    assert ((cond.target >= lo) & (cond.target <= hi)).all()
    dist = np.linalg.norm(cond.target[:, None] - humans.condition[None], axis=-1)
    np.testing.assert_array_equal(cond.n_human_inside, (dist <= basis.radius).sum(1))
    assert (cond.n_human_inside >= evo.min_neighbours).all()
    # qf: reaches the target (forward kinematics, independently of the IK's own report)
    hand = np.asarray(jax.vmap(lambda x: dyn.site_pose(x)[0])(jnp.asarray(b.qf)))
    np.testing.assert_allclose(hand, cond.target, atol=evo.ik_tolerance)
    assert (cond.ik_error <= evo.ik_tolerance).all()
    assert ((b.qf >= robot.lower) & (b.qf <= robot.upper)).all()
    # rest to rest; duration inside the demonstrations' range
    np.testing.assert_allclose(b.q0, np.broadcast_to(robot.rest, b.q0.shape), atol=1e-6)
    assert (b.qd0 == 0).all() and (b.qdf == 0).all()
    assert ((b.duration >= humans.duration.min()) & (b.duration <= humans.duration.max())).all()
    # the human-only interpolation meets the position BCs
    np.testing.assert_allclose(cond.human_q[:, 0], b.q0, atol=TOL_BC_POS)
    np.testing.assert_allclose(cond.human_q[:, -1], b.qf, atol=TOL_BC_POS)


@pytest.mark.slow
def test_conditions_take_the_durations_they_are_given(small):
    """``make_conditions(durations=...)``: each condition's duration is the mean of its
    neighbours' durations as given (twice the recorded ones here: twice the conditions'), the
    draw (targets, postures) and the human-only path in normalised time stay the same."""
    import jax

    from evojax_motion.evolution.conditions import make_conditions

    robot, dyn, humans, grid = (small[k] for k in ("robot", "dyn", "humans", "grid"))
    cond, evo, basis = small["cond"], small["evo"], small["basis"]
    slow = make_conditions(
        humans, dyn, robot, evo, basis, grid, jax.random.key(3), durations=2 * humans.duration
    )
    slow = jax.tree_util.tree_map(np.asarray, slow)
    np.testing.assert_allclose(slow.boundary.duration, 2 * cond.boundary.duration, rtol=1e-6)
    for name in ("q0", "qf", "qd0", "qdf"):
        np.testing.assert_array_equal(getattr(slow.boundary, name), getattr(cond.boundary, name))
    np.testing.assert_array_equal(slow.target, cond.target)
    np.testing.assert_allclose(slow.human_q, cond.human_q, atol=TOL_BC_POS)


# The IK of one candidate does not depend on which others share its batch (same program, rows
# independent); a candidate's posture may still differ in the last bits between batch sizes.
TOL_IK_BATCH = 1e-5  # [rad]
# The candidates' uniform draw is compiled as a one-shot program (`compile_options.ONE_SHOT`):
# its affine map ``lo + u (hi - lo)`` may round otherwise than at the full level (3e-8 m seen).
TOL_DRAW_M = 1e-6


@pytest.mark.slow
def test_conditions_are_the_first_qualifying_candidates_in_key_order(small):
    """The IK runs on m candidates at a time: the conditions must still be the first m candidates
    in key order with enough neighbours and a reachable IK posture, as if all had been solved.
    A copy of the demonstrations with their hand positions 0.6 m higher (out of reach) makes many
    candidates miss the IK by centimetres, so that several batches are needed."""
    import jax

    from evojax_motion.evolution.conditions import make_conditions, sampling_box
    from evojax_motion.linalg.reductions import masked_row_mean
    from evojax_motion.model.ik import solve_ik
    from evojax_motion.motion.database import make_database

    robot, dyn, h, grid, basis = (small[k] for k in ("robot", "dyn", "humans", "grid", "basis"))
    humans = make_database(
        np.concatenate([h.q, h.q]),
        np.concatenate([h.duration, h.duration]),
        np.concatenate([h.condition, h.condition + np.float32([0.0, 0.0, 0.6])]),
        cost=np.concatenate([h.cost, h.cost]),
    )
    per = 12
    evo = EvolutionSettings(
        conditions=M_COND, min_neighbours=2, candidates_per_condition=per, region_margin=0.0
    )
    key = jax.random.key(5)
    cond = jax.tree_util.tree_map(
        np.asarray, make_conditions(humans, dyn, robot, evo, basis, grid, key)
    )
    # reference: every candidate at once, the neighbours in numpy
    lo, hi = sampling_box(humans, evo.region_margin)
    cand = np.asarray(jax.random.uniform(key, (M_COND * per, 3), jnp.float32, lo, hi))
    dist = np.linalg.norm(cand[:, None] - humans.condition[None], axis=-1)
    order = np.argsort(dist, axis=1, kind="stable")[:, : basis.neighbours]
    final = humans.q[order, -1]
    mask = np.ones(order.shape, bool)
    pref = masked_row_mean(final, mask)
    ik = solve_ik(dyn, cand, final[:, 0], robot.lower, robot.upper, q_pref=pref)
    near = np.flatnonzero((dist <= basis.radius).sum(1) >= evo.min_neighbours)
    first = near[np.asarray(ik.pos_error)[near] <= evo.ik_tolerance][:M_COND]
    assert np.searchsorted(near, first[-1]) >= M_COND, "one batch sufficed: nothing tested"
    np.testing.assert_allclose(cond.target, cand[first], rtol=0, atol=TOL_DRAW_M)
    np.testing.assert_allclose(cond.boundary.qf, np.asarray(ik.q)[first], atol=TOL_IK_BATCH)


def test_conditions_refuse_impossible_settings():
    from evojax_motion.errors import UserError
    from evojax_motion.evolution.conditions import make_conditions, sampling_box
    from evojax_motion.settings.compiler import BasisSettings

    humans = _humans(n=5)
    with pytest.raises(UserError, match=r"evolution\.region_margin"):
        sampling_box(humans, -5.0)
    settings = EvolutionSettings(conditions=2, min_neighbours=6)
    with pytest.raises(UserError, match=r"evolution\.min_neighbours: expected <= the 5"):
        make_conditions(humans, None, None, settings, BasisSettings(), None, None)


@pytest.mark.slow
def test_generation_step_rejects_selects_and_keeps_humans(small):
    import jax

    robot, dyn, grid, humans = small["robot"], small["dyn"], small["grid"], small["humans"]
    cond, step, torque_cost = small["cond"], small["step"], small["torque_cost"]
    # condition 0 ends beyond a joint limit (every offspring must leave the range); condition 1
    # has a NaN final posture (non-finite offspring). The others are ordinary.
    qf = cond.boundary.qf.copy()
    qf[0, 4] = robot.upper[4] + 0.3
    qf[1, :] = np.nan
    cond = cond._replace(boundary=cond.boundary._replace(qf=qf))
    db0 = jax.tree_util.tree_map(jax.numpy.asarray, init_evolved_slots(humans, cond))
    db1, s1 = step(db0, cond, np.int32(1))
    db2, s2 = step(db1, cond, np.int32(2))
    assert step._cache_size() == 1  # the second generation reuses the compilation

    n = N_HUMAN
    v1, v2 = np.asarray(db1.valid[n:]), np.asarray(db2.valid[n:])
    assert not v2[0] and not v2[1] and v1[2:].any(), s1  # the ordinary ones may fail too (few
    for s, v in ((s1, v1), (s2, v2)):  # Adam steps), but not all of them
        assert int(s.n_rejected_nonfinite) == 1 and int(s.n_rejected_limits) >= 1
        assert int(s.n_valid) == v.sum()
    assert int(s1.n_replaced) == v1.sum() and (v2 >= v1).all()

    # humans untouched, bit for bit
    for a, b in zip(db0, db2):
        assert np.asarray(a)[:n].tobytes() == np.asarray(b)[:n].tobytes()
    # survivors never get worse; stored costs are eq. 5 of the stored trajectories
    c1, c2 = np.asarray(db1.cost[n:]), np.asarray(db2.cost[n:])
    assert (c2[v1] <= c1[v1]).all()
    q2, d2 = np.asarray(db2.q[n:]), np.asarray(db2.duration[n:])
    recomputed = np.asarray(jax.vmap(lambda a, d: torque_cost(dyn, grid, a, d))(q2, d2))
    np.testing.assert_allclose(c2[v2], recomputed[v2], rtol=TOL_COST_REL)
    np.testing.assert_allclose(float(s2.db_cost_mean), c2[v2].mean(), rtol=1e-6)
    # survivors meet the boundary conditions and the limits
    np.testing.assert_allclose(q2[v2][:, 0], cond.boundary.q0[v2], atol=TOL_BC_POS)
    np.testing.assert_allclose(q2[v2][:, -1], cond.boundary.qf[v2], atol=TOL_BC_POS)
    assert ((q2[v2] >= robot.lower - 1e-5) & (q2[v2] <= robot.upper + 1e-5)).all()
    # human deviation: RMS degrees from the human-only interpolation, averaged over the slots
    dev = np.degrees(np.sqrt(((q2[v2] - cond.human_q[v2]) ** 2).mean(axis=(1, 2))))
    np.testing.assert_allclose(float(s2.human_deviation_deg), dev.mean(), rtol=1e-5)
    gen = np.asarray(db2.generation[n:])
    assert set(gen[v2]) <= {1, 2} and (gen[~v2] == 0).all()


@pytest.mark.slow
def test_generation_step_with_search_candidates_is_the_same_generation(small):
    """Candidate lists (`with_search_candidates`, forced at this size) change only how the
    neighbours are found: two generations give the same database and statistics, bit for bit,
    and a resumed run (conditions from a checkpoint tree) gets the same lists again."""
    import jax

    from evojax_motion.evolution.conditions import conditions_from_tree, conditions_to_tree
    from evojax_motion.evolution.step import with_search_candidates

    s, step = small, small["step"]
    db0 = init_evolved_slots(s["humans"], s["cond"])
    plain = s["cond"]
    listed = with_search_candidates(db0, plain, s["basis"], min_conditions=1)
    assert plain.candidates is None and listed.candidates.shape == (M_COND, 5 * 6)
    assert with_search_candidates(db0, plain, s["basis"], min_conditions=M_COND + 1) is plain
    runs = []
    for cond in (plain, listed):
        db, stats = jax.tree_util.tree_map(jax.numpy.asarray, db0), []
        for g in (1, 2):
            db, st = step(db, cond, np.int32(g))
            stats.append(st)
        runs.append((db, stats))
    for a, b in zip(jax.tree_util.tree_leaves(runs[0]), jax.tree_util.tree_leaves(runs[1])):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    resumed = with_search_candidates(
        runs[1][0], conditions_from_tree(conditions_to_tree(listed)), s["basis"], min_conditions=1
    )
    np.testing.assert_array_equal(resumed.candidates, listed.candidates)


def _dot_precisions(jaxpr) -> list:
    """The ``precision`` of every ``dot_general`` in ``jaxpr`` and its sub-programs."""
    import jax.extend

    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            found += _dot_precisions(sub)
    return found


def test_generation_step_traces_exact_float32_products(small):
    """Every matrix product of a generation (plain and sharded step) is traced at HIGHEST
    precision, whatever the caller's default: GPUs would run DEFAULT ones in TF32, which
    rejected 99 % of the offspring for joint limits on an H200 (`precision`)."""
    import jax

    from evojax_motion.evolution.sharding import make_sharded_generation_step
    from evojax_motion.evolution.step import make_generation_step
    from evojax_motion.settings.compiler import OptimSettings

    robot, s = small["robot"], small
    db0 = init_evolved_slots(s["humans"], s["cond"])
    args = (s["dyn"], s["grid"], robot.lower, robot.upper, N_HUMAN, s["basis"])
    optim = OptimSettings(method="newton", max_iters=2, search_stride=2, max_free_per_joint=2)
    steps = {
        "plain": s["step"],
        "newton": make_generation_step(*args, optim, s["evo"]),
        "sharded": make_sharded_generation_step(*args, optim, s["evo"], devices=1),
    }
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    with jax.default_matmul_precision("default"):
        for name, step in steps.items():
            found = _dot_precisions(jax.make_jaxpr(step)(db0, s["cond"], np.int32(1)).jaxpr)
            assert len(found) > 10, name  # the walk reaches the optimiser's products
            loose = [p for p in found if p != highest]
            assert not loose, f"{name}: {len(loose)} of {len(found)} products at {loose[0]}"
