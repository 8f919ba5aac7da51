"""Survivor selection, slot layout, the condition set and one jitted generation (evolution.py,
conditions.py)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evojax_motion.database import EVOLVED, HUMAN, make_database
from evojax_motion.evolution import (
    EvolutionSettings,
    init_evolved_slots,
    rms_deviation_deg,
    select_survivors,
    write_slots,
)

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
