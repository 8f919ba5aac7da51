"""One generation of the evolutionary algorithm over the primitive database (paper sec. 3.1, 4.3).

Genetic operator: every condition c of the fixed set (``conditions.py``) is compiled by the
movement compiler via optimisation (eq. 3-5) from a basis of its neighbours (eq. 6) in the current
database; neighbour search sees the human originals and the survivors alike. Offspring that are not
finite, leave the joint ranges, exceed a torque or velocity limit (peak |tau| or |qd| over the T
samples; `model.robot.Robot.torque_limit`, ``velocity_limit``) or miss the boundary conditions
(eq. 2) are discarded (sec. 3.1, 5). An infinite limit (a continuous joint's range, a joint
without torque or velocity limit) is never violated.
Survivor selection (sec. 4.3): slot ``n_human + c`` keeps the cheaper of incumbent and offspring by
the eq. 5 cost, a batched argmin; the human originals (slots ``0 .. n_human-1``) never change.

``make_generation_step`` closes over the static pieces (dynamics, time grid, settings) and returns
one jitted function ``step(db, conditions, generation) -> (db, GenerationStats)``: the whole
generation (neighbours, PCA, optimisation, selection, metrics) is a single XLA program.
`generation_stages` gives the same step as two programs, ``prepare`` (neighbours, PCA, the reduced
problems, BFGS's first model) and ``finish`` (the optimiser, selection, metrics): a run compiles
them side by side (`run.compilation.compile_generation_step`), which on 2 CPU cores shortens the
wait for its first generation.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import short_run as short_run_options
from evojax_motion.compiler.basis import (
    neighbour_candidates,
    pca_basis,
    select_neighbours,
    select_neighbours_among,
)
from evojax_motion.compiler.optimisation import (
    Prepared,
    checked_limits,
    cpu_fast_path,
    optimise_prepared,
    prepare_optimisation,
    validate_rate_limits,
)
from evojax_motion.evolution.stats import GenerationStats
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.linalg.reductions import masked_mean
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.motion.database import EVOLVED, Database, count_human
from evojax_motion.motion.objective import torque_sum, trajectory_torques
from evojax_motion.motion.timegrid import TimeGrid, derivatives
from evojax_motion.settings.compiler import BasisSettings, OptimSettings
from evojax_motion.settings.evolution import EvolutionSettings


class Selection(NamedTuple):
    """Result of survivor selection over the m evolved slots."""

    q: jnp.ndarray  # (m, T, J)
    cost: jnp.ndarray  # (m,)
    valid: jnp.ndarray  # (m,) bool
    generation: jnp.ndarray  # (m,) int32, generation that produced the survivor
    replaced: jnp.ndarray  # (m,) bool, the offspring won


def select_survivors(
    q_inc, cost_inc, valid_inc, gen_inc, q_off, cost_off, accept_off, generation
) -> Selection:
    """Per slot, keep the cheaper of incumbent and offspring (paper sec. 3.1 step 5).

    A batched argmin over ``(incumbent, offspring)`` costs, where an empty slot or a rejected
    offspring counts as ``+inf``; ties keep the incumbent (argmin takes the first), so a slot's
    cost never increases and an equal-cost offspring never churns the database.
    ``q_*: (m, T, J)``, ``cost_*, valid_inc, accept_off: (m,)``, ``gen_inc: (m,)``.
    """
    inf = jnp.asarray(jnp.inf, cost_inc.dtype)
    pair = jnp.stack(
        [jnp.where(valid_inc, cost_inc, inf), jnp.where(accept_off, cost_off, inf)], axis=0
    )
    winner = jnp.argmin(pair, axis=0)  # 0 = incumbent, 1 = offspring
    replaced = (winner == 1) & accept_off
    return Selection(
        q=jnp.where(replaced[:, None, None], q_off, q_inc),
        cost=jnp.where(replaced, cost_off, cost_inc),
        valid=valid_inc | replaced,
        generation=jnp.where(replaced, jnp.asarray(generation, gen_inc.dtype), gen_inc),
        replaced=replaced,
    )


def write_slots(db: Database, n_human: int, sel: Selection) -> Database:
    """The database with its evolved slots ``n_human:`` replaced; human rows are passed through
    untouched (concatenation of the original slice: bit-for-bit the same)."""

    def cat(old, new):
        return jnp.concatenate([old[:n_human], new.astype(old.dtype)], axis=0)

    return db._replace(
        q=cat(db.q, sel.q),
        cost=cat(db.cost, sel.cost),
        valid=cat(db.valid, sel.valid),
        generation=cat(db.generation, sel.generation),
    )


def init_evolved_slots(humans: Database, conditions) -> Database:
    """Database of capacity ``n_human + m``: the human rows, then one empty slot per condition.

    Slot ``n_human + c`` gets condition c's target and duration (``valid=False`` until first
    filled, ``origin=EVOLVED``, ``cost=inf``). ``humans``: only valid human rows. Returns
    numpy arrays.
    """
    m = conditions.target.shape[0]

    def cat(a, b):  # numpy: on the host, once per run (eager jnp would compile per array)
        a = np.asarray(a)
        fill = np.broadcast_to(np.asarray(b), (m, *a.shape[1:]))
        return np.concatenate([a, fill.astype(a.dtype)])

    return Database(
        q=cat(humans.q, 0.0),
        duration=cat(humans.duration, conditions.boundary.duration),
        condition=cat(humans.condition, conditions.target),
        cost=cat(humans.cost, np.inf),
        origin=cat(humans.origin, EVOLVED),
        valid=cat(humans.valid, False),
        generation=cat(humans.generation, 0),
    )


def boundary_errors(grid: TimeGrid, q, boundary):
    """Largest start/end errors per primitive: ``(position [rad] (m,), velocity [rad/s] (m,))``.

    ``q: (m, T, J)``; NaN anywhere gives NaN (which every ``<=`` test rejects).
    """
    qd, _ = derivatives(grid, q, boundary.duration)
    pos = jnp.stack([q[:, 0] - boundary.q0, q[:, -1] - boundary.qf])
    vel = jnp.stack([qd[:, 0] - boundary.qd0, qd[:, -1] - boundary.qdf])

    def worst(e):
        bad = ~jnp.all(jnp.isfinite(e), axis=(0, 2))
        return jnp.where(bad, jnp.nan, jnp.max(jnp.abs(e), axis=(0, 2)))

    return worst(pos), worst(vel)


def rms_deviation_deg(q, q_ref):
    """RMS joint-angle difference in degrees per primitive. ``q, q_ref: (m, T, J)`` -> ``(m,)``."""
    return jnp.degrees(jnp.sqrt(jnp.mean((q - q_ref) ** 2, axis=(1, 2))))


# Conditions from which the generation step searches neighbours among candidate lists made once
# per run (`with_search_candidates`), not the whole database: the whole search is m x (n_human +
# m) distances, 8 ms of a 191 ms generation at 10,000 conditions and 228 ms of 2.33 s at 100,000
# (H100, docs/scaling.md); at the paper's 300 it is negligible and the step stays as it was.
SEARCH_CANDIDATES_MIN_CONDITIONS = 2048
# Evolved slots per list, per neighbour: a list stays exact while k of them are filled or nearer.
CANDIDATE_SLOTS_PER_NEIGHBOUR = 4


_neighbour_candidates = jax.jit(neighbour_candidates, static_argnums=(2, 4, 5, 6))


def with_search_candidates(
    db: Database,
    conditions,
    basis_settings: BasisSettings,
    min_conditions: int | None = None,
    placeholder: bool = False,
):
    """``conditions`` with their neighbour-search candidate lists in ``db`` (``candidates``,
    `compiler.basis.neighbour_candidates`: the k nearest human rows and the ``4 k`` nearest evolved
    slots of each condition), when there are at least ``min_conditions`` conditions (default
    `SEARCH_CANDIDATES_MIN_CONDITIONS`); else ``conditions`` unchanged (the step then searches
    the whole database).

    ``db``: of capacity ``n_human + m`` (`init_evolved_slots`); its slot conditions never
    change, nor do its human rows, so the lists hold for every generation of the run. The step's
    search is exact either way (`search_neighbours`). ``placeholder``: zeros of the right shape
    (the step's expected inputs, before the database exists). Returns numpy arrays.
    """
    m = conditions.target.shape[0]
    if m < (SEARCH_CANDIDATES_MIN_CONDITIONS if min_conditions is None else min_conditions):
        return conditions
    k = basis_settings.neighbours
    width = k + CANDIDATE_SLOTS_PER_NEIGHBOUR * k
    if placeholder:
        return conditions._replace(candidates=np.zeros((m, width), np.int32))
    cand = _neighbour_candidates(
        jnp.asarray(db.condition), jnp.asarray(db.valid), count_human(db),
        jnp.asarray(conditions.target), k, width - k, basis_settings.w_pos,
    )  # fmt: skip
    return conditions._replace(candidates=np.asarray(cand))


def search_neighbours(db: Database, conditions, basis_settings: BasisSettings):
    """Eq. 6 neighbours of every condition in ``db`` (`compiler.basis.Neighbours`, position only).

    With ``conditions.candidates`` (`with_search_candidates`): among the lists, and in the
    whole database (one ``lax.cond``) only when some list cannot vouch for its answer (early
    generations, whose slots are still empty); the same neighbours either way.
    """
    s = basis_settings
    cond, valid = jnp.asarray(db.condition), jnp.asarray(db.valid)

    def whole(_=None):
        return select_neighbours(cond, valid, conditions.target, s.neighbours, s.radius, s.w_pos)

    if conditions.candidates is None:
        return whole()
    nb, exact = select_neighbours_among(
        cond, valid, conditions.target, conditions.candidates, s.neighbours, s.radius, s.w_pos
    )
    return jax.lax.cond(jnp.all(exact), lambda _: nb, whole, None)


def make_generation_step(*args, **kwargs):
    """One generation as one jitted function ``step(db, conditions, generation)``; arguments
    as `generation_stages` (``dyn, grid, lower, upper, n_human, basis_settings, optim_settings,
    settings``, keywords ``torque_limit``, ``velocity_limit``).

    ``db``: ``Database`` of capacity ``n_human + m`` (`init_evolved_slots`); ``conditions``:
    ``Conditions`` (m); ``generation``: int32 scalar, the index this step produces (1, 2, ...);
    traced, so every generation reuses one compilation. On CPU, for BFGS (``compiler.method:
    bfgs``), the step is compiled through `compiler.optimisation.cpu_fast_path`.
    Returns ``(db, GenerationStats)`` where the stats mean:

    - ``offspring_cost_mean``: eq. 5 cost averaged over the accepted offspring;
    - ``db_cost_mean``: eq. 5 cost averaged over the filled evolved slots after selection;
    - ``torque_sum_mean``: the paper's Fig. 5 quantity, time-averaged |tau| summed over joints
      [N m] (``motion.objective.torque_sum``), averaged over the filled evolved slots;
    - ``human_deviation_deg``: RMS joint-angle difference [deg] between each filled evolved slot
      and its condition's human-only interpolation, averaged over the slots;
    - ``n_replaced``: slots whose offspring won; ``n_rejected_*``: offspring discarded, each
      counted once, in this order: non-finite, outside the joint ranges, over a torque limit,
      over a velocity limit, missing the boundary conditions (each: but passing the tests
      before); ``n_valid``: filled evolved slots; ``n_short``: conditions with
      fewer than k neighbours within the radius;
    - ``bc_residual_max`` [rad], ``bc_velocity_residual_max`` [rad/s]: largest start/end
      joint-angle (velocity) error among the finite offspring;
    - ``converged_fraction``: offspring whose optimiser reported convergence.
    """
    step, options = generation_step(*args, **kwargs)
    return jax.jit(step, compiler_options=options)


class Staged(NamedTuple):
    """What `generation_stages`' ``prepare`` hands to ``finish``: ``short (m,)`` bool, conditions
    with fewer than k neighbours within the radius; ``prepared``: their
    `compiler.optimisation.Prepared`
    problems."""

    short: jnp.ndarray
    prepared: Prepared


def generation_stages(
    dyn: Dynamics,
    grid: TimeGrid,
    lower,
    upper,
    n_human: int,
    basis_settings: BasisSettings,
    optim_settings: OptimSettings,
    settings: EvolutionSettings,
    *,
    torque_limit=None,
    velocity_limit=None,
    short_run: bool = False,
):
    """``(prepare, finish, compiler_options)``: the un-jitted generation step in two stages,
    ``prepare(db, conditions) -> Staged`` (neighbours, PCA,
    `compiler.optimisation.prepare_optimisation`)
    and ``finish(db, conditions, generation, staged) -> (db, GenerationStats)`` (the optimiser,
    survivor selection, metrics), and the options of the top-level jits that must run them.
    ``finish(db, conditions, generation, prepare(db, conditions))`` is `generation_step`'s
    step. ``lower``, ``upper``: ``(J,)`` joint limits [rad] (-inf / +inf: none);
    ``torque_limit`` [N m], ``velocity_limit`` [rad/s]: ``(J,)`` (inf: none; None: none at all),
    e.g. `model.robot.Robot.torque_limit`. ``short_run``: the options of a program that runs a
    few tens of times (`compile_options.short_run`: `model.dynamics.is_short_run`)."""
    dyn, options = cpu_fast_path(dyn, optim_settings)
    options = short_run_options(options, short_run)
    lower, upper = checked_limits(lower, upper)
    n_joints = lower.shape[0]
    tau_max = validate_rate_limits(torque_limit, n_joints, "torque limits")
    qd_max = validate_rate_limits(velocity_limit, n_joints, "velocity limits")
    n_components = optim_settings.n_components

    def prepare(db: Database, conditions) -> Staged:
        nb = search_neighbours(db, conditions, basis_settings)
        basis = pca_basis(jnp.asarray(db.q), jnp.asarray(db.duration), nb, n_components)
        prep = prepare_optimisation(basis, conditions.boundary, dyn, grid, optim_settings)
        return Staged(short=nb.short, prepared=prep)

    def finish(db: Database, conditions, generation, staged: Staged):
        off = optimise_prepared(
            staged.prepared, conditions.boundary, dyn, grid, lower, upper, optim_settings,
            qd_max, tau_max,
        )  # fmt: skip
        finite = off.finite & jnp.isfinite(off.cost)
        in_range = finite & off.within_limits
        dtype = off.peak_torque.dtype
        under_torque = in_range & jnp.all(off.peak_torque <= jnp.asarray(tau_max, dtype), axis=-1)
        feasible = under_torque & jnp.all(off.peak_velocity <= jnp.asarray(qd_max, dtype), axis=-1)
        pos_err, vel_err = boundary_errors(grid, off.q, conditions.boundary)
        meets_bc = (pos_err <= settings.bc_tolerance) & (vel_err <= settings.bc_velocity_tolerance)
        accept = feasible & meets_bc

        sl = slice(n_human, None)
        sel = select_survivors(
            db.q[sl], db.cost[sl], db.valid[sl], db.generation[sl],
            off.q.astype(db.q.dtype), off.cost.astype(db.cost.dtype), accept, generation,
        )  # fmt: skip
        new_db = write_slots(db, n_human, sel)

        dur = new_db.duration[sl]
        tau = jax.vmap(lambda q, d: trajectory_torques(dyn, grid, q, d))(sel.q, dur)
        tsum = jax.vmap(lambda t: torque_sum(grid, t))(tau)
        dev = rms_deviation_deg(sel.q, conditions.human_q)
        stats = GenerationStats(
            offspring_cost_mean=masked_mean(off.cost, accept),
            db_cost_mean=masked_mean(sel.cost, sel.valid),
            torque_sum_mean=masked_mean(tsum, sel.valid),
            human_deviation_deg=masked_mean(dev, sel.valid),
            n_replaced=jnp.sum(sel.replaced).astype(jnp.int32),
            n_rejected_nonfinite=jnp.sum(~finite).astype(jnp.int32),
            n_rejected_limits=jnp.sum(finite & ~in_range).astype(jnp.int32),
            n_rejected_torque=jnp.sum(in_range & ~under_torque).astype(jnp.int32),
            n_rejected_velocity=jnp.sum(under_torque & ~feasible).astype(jnp.int32),
            n_rejected_bc=jnp.sum(feasible & ~accept).astype(jnp.int32),
            n_valid=jnp.sum(sel.valid).astype(jnp.int32),
            n_short=jnp.sum(staged.short).astype(jnp.int32),
            bc_residual_max=jnp.max(jnp.where(finite, pos_err, 0.0)),
            bc_velocity_residual_max=jnp.max(jnp.where(finite, vel_err, 0.0)),
            converged_fraction=jnp.mean(jnp.asarray(off.converged, jnp.float32)),
        )
        return new_db, stats

    return exact_matmuls(prepare), exact_matmuls(finish), options


def generation_step(*args, **kwargs):
    """``(step, compiler_options)``: the un-jitted `make_generation_step` (`generation_stages`
    as one function; same arguments) and the options of the top-level jit that must run it (JAX
    accepts them only there; `parallel` jits it with shardings, or inlines it per device)."""
    prepare, finish, options = generation_stages(*args, **kwargs)

    def step(db: Database, conditions, generation):
        return finish(db, conditions, generation, prepare(db, conditions))

    return step, options
