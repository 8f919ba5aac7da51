"""The fixed set of conditions the evolution optimises for (paper sec. 3.1 step 2 and 4.2).

"A set of 300 conditions is randomly created. Each condition contains the information of final joint
angle, velocity and final position and rotation of right hand" (sec. 4.2). The set is drawn once,
with an explicit PRNG key, from where the robot will work, and reused by every generation:

- target hand position: uniform in the bounding box of the demonstrations' hand positions (grown by
  ``region_margin``), kept only where at least ``min_neighbours`` demonstrations lie within the
  basis radius (rejection sampling over ``candidates_per_condition * m`` candidates, in key order);
- ``qf``: a human-like final posture, by IK of the target (``model.ik.solve_ik``) started from the
nearest
  neighbour's final posture and pulled toward the neighbours' mean final posture in the redundant
  directions; candidates the IK cannot reach within ``ik_tolerance`` are rejected. Neighbour means
  are taken on one branch (the database keeps continuous joints on the rest branch,
  `motion.database.on_robot_branch`), and a continuous joint of ``qf`` is kept within pi of the
  start;
- ``q0``: the neighbours' mean start posture (the synthetic demonstrations all start at the
  robot's rest; recorded people start where they stood), ``qd0 = qdf = 0``;
- duration: the neighbours' mean duration (each neighbour's as ``durations`` gives it: a run
  passes them slowed to the robot's velocity limits, ``EvolutionSettings.fit_speed``), or
  ``EvolutionSettings.duration``.

Each condition also carries its human-only reference: the movement compiler via interpolation
(eq. 1-2) on a basis of the human demonstrations alone. ``human_deviation_deg`` in the training
metrics measures how far evolved motions drift from it.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import one_shot
from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import Boundary, compile_interpolation
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.linalg.reductions import masked_row_mean
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.ik import solve_ik
from evojax_motion.model.robot import Robot
from evojax_motion.motion.angles import posture_on_rest_branch
from evojax_motion.motion.database import Database, human_mask
from evojax_motion.motion.timegrid import TimeGrid
from evojax_motion.run.cache import TracedProgram, traced_program
from evojax_motion.settings.compiler import BasisSettings

if TYPE_CHECKING:
    from evojax_motion.settings.evolution import EvolutionSettings

INTERP_COMPONENTS = 3  # eq. 1: three principal components + a constant


class Conditions(NamedTuple):
    """m conditions. ``target (m, 3)`` [m], ``boundary`` (``q0, qf, qd0, qdf (m, J)``,
    ``duration (m,)``), ``ik_error (m,)`` [m] of ``qf``, ``n_human_inside (m,)`` demonstrations
    within the basis radius, ``human_q (m, T, J)`` human-only interpolation (eq. 1-2);
    ``candidates (m, k + L)`` or None: the neighbour search's candidate lists in the run's
    database (`evolution.step.with_search_candidates`; derived, so not checkpointed)."""

    target: jnp.ndarray
    boundary: Boundary
    ik_error: jnp.ndarray
    n_human_inside: jnp.ndarray
    human_q: jnp.ndarray
    candidates: jnp.ndarray | None = None


def sampling_box(db: Database, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """``(lo (3,), hi (3,))``: the demonstrations' hand-position box grown by ``margin``."""
    pos = np.asarray(db.condition)[human_mask(db)]
    if pos.shape[0] == 0:
        raise UserError("demonstrations: expected at least one valid human primitive, got none")
    lo, hi = pos.min(axis=0) - margin, pos.max(axis=0) + margin
    if not (hi > lo).all():
        raise UserError(
            f"evolution.region_margin: {margin} m leaves an empty region "
            f"(demonstration extent {np.round(pos.max(0) - pos.min(0), 3).tolist()} m)"
        )
    return lo.astype(np.float32), hi.astype(np.float32)


def _near_branch(q: np.ndarray, ref: np.ndarray, continuous: np.ndarray) -> np.ndarray:
    """Postures ``q (B, J)`` with continuous joints moved by whole turns to within pi of
    ``ref (B, J)`` (`motion.angles.posture_on_rest_branch`); other joints unchanged, bit for bit."""
    if not np.any(continuous):
        return q
    return np.where(continuous, posture_on_rest_branch(q, ref, continuous), q)


def _take(tree, idx: np.ndarray):
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[idx], tree)


class ConditionPrograms(NamedTuple):
    """The condition draw's three compiled stages (`condition_programs`), around its
    data-dependent choices: ``candidates(key, lo, hi, condition (N, 3), human (N,))`` draws
    and finds the candidates' neighbours, ``reach(cand, nb, q)`` solves the IK of m of them,
    ``finish(target, nb, qf, ik_error, q, duration)`` makes the m conditions."""

    candidates: TracedProgram
    reach: TracedProgram
    finish: TracedProgram
    conditions: int  # m

    def precompile(self, n_human: int, samples: int, joints: int) -> None:
        """Compile the three for a database of ``n_human`` demonstrations of ``samples`` x
        ``joints`` before it exists (float32, as `make_conditions` passes them)."""
        f32 = np.dtype(np.float32)

        def shape(*s, dtype=f32):
            return jax.ShapeDtypeStruct(s, dtype)

        key = jax.eval_shape(jax.random.key, 0)
        drawn = self.candidates.precompile(
            key, shape(3), shape(3), shape(n_human, 3), shape(n_human, dtype=np.dtype(bool))
        ).out_info
        m = self.conditions
        cand, nb = jax.tree_util.tree_map(lambda a: shape(m, *a.shape[1:], dtype=a.dtype), drawn)
        q = shape(n_human, samples, joints)
        self.reach.precompile(cand, nb, q)
        self.finish.precompile(cand, nb, shape(m, joints), shape(m), q, shape(n_human))


def condition_programs(
    dyn: Dynamics,
    robot: Robot,
    settings: EvolutionSettings,
    basis: BasisSettings,
    grid: TimeGrid,
    cache_parts: Any = None,
) -> ConditionPrograms:
    """The programs `make_conditions` runs for ``settings`` (``EvolutionSettings``): built
    before the demonstrations exist, so that they can be compiled meanwhile
    (`ConditionPrograms.precompile`). ``cache_parts``: what `run.cache.traced_program`
    keys them by besides their arguments (the config sections and robot model behind ``dyn``,
    ``robot``, ``settings`` and ``basis``); None compiles them in this process only."""
    m = settings.conditions
    n_cand = m * settings.candidates_per_condition

    # Jitted stages around the data-dependent choices (eager PCA is ~100x slower); the data are
    # arguments, not constants, so that a later run with other demonstrations reuses them.
    options = one_shot()  # run once a run
    jit_once = functools.partial(jax.jit, compiler_options=options)

    @jit_once
    def candidates(key, lo, hi, condition, human):
        cand = jax.random.uniform(key, (n_cand, 3), condition.dtype, lo, hi)
        nb = select_neighbours(condition, human, cand, basis.neighbours, basis.radius, basis.w_pos)
        return cand, nb

    @jit_once
    @exact_matmuls
    def reach(cand, nb, q):
        final = q[nb.index, -1]  # (m, k, J) the neighbours' final postures
        lower, upper = jnp.asarray(robot.lower, q.dtype), jnp.asarray(robot.upper, q.dtype)
        return solve_ik(
            dyn, cand, final[:, 0], lower, upper, q_pref=masked_row_mean(final, nb.mask)
        )

    @jit_once
    @exact_matmuls
    def finish(target, nb, qf, ik_error, q, duration):
        j = q.shape[-1]
        if settings.duration is None:
            dur = masked_row_mean(duration[nb.index], nb.mask)
        else:
            dur = jnp.full((m,), settings.duration, q.dtype)
        zeros = jnp.zeros((m, j), q.dtype)
        # The neighbours' mean start, as an offset from the nearest one's: exactly the shared
        # start where they have one (synthetic demonstrations start at the robot's rest).
        start = q[nb.index, 0]  # (m, k, J)
        q0 = start[:, 0] + masked_row_mean(start - start[:, :1], nb.mask)
        boundary = Boundary(q0=q0, qf=qf, qd0=zeros, qdf=zeros, duration=dur)
        ref_basis = pca_basis(q, duration, nb, INTERP_COMPONENTS)
        ref = compile_interpolation(ref_basis, boundary, grid, n_components=INTERP_COMPONENTS)
        f32 = jnp.float32  # fixed dtypes: checkpoints restore into `conditions_template`
        return Conditions(
            target=target.astype(f32),
            boundary=jax.tree_util.tree_map(lambda a: a.astype(f32), boundary),
            ik_error=ik_error.astype(f32),
            n_human_inside=nb.n_inside.astype(jnp.int32),
            human_q=ref.q.astype(f32),
        )

    return ConditionPrograms(
        candidates=traced_program(candidates, cache_parts, options),
        reach=traced_program(reach, cache_parts, options),
        finish=traced_program(finish, cache_parts, options),
        conditions=m,
    )


def make_conditions(
    db: Database,
    dyn: Dynamics,
    robot: Robot,
    settings: EvolutionSettings,
    basis: BasisSettings,
    grid: TimeGrid,
    key: jax.Array,
    cache_parts: Any = None,
    programs: ConditionPrograms | None = None,
    durations: np.ndarray | None = None,
) -> Conditions:
    """Draw the m conditions of ``settings`` (``EvolutionSettings``) from human demonstrations.

    ``db``: the database; only its valid human rows are used. ``key``: the only randomness.
    ``cache_parts``: see `condition_programs`; ``programs``: those already made (and perhaps
    compiled) for the same arguments, else made here. ``durations (N,)`` [s]: each row's
    duration as a neighbour counts it (None: ``db.duration``).
    Raises ``UserError`` when fewer than m candidates qualify.
    """
    m = settings.conditions
    lo, hi = sampling_box(db, settings.region_margin)
    n_human = int(human_mask(db).sum())
    if settings.min_neighbours > n_human:
        raise UserError(
            f"evolution.min_neighbours: expected <= the {n_human} demonstrations, "
            f"got {settings.min_neighbours}"
        )
    n_cand = m * settings.candidates_per_condition
    q = np.asarray(db.q)  # numpy: a jax copy is one more XLA program (seconds while others compile)
    if programs is None:
        programs = condition_programs(dyn, robot, settings, basis, grid, cache_parts)
    candidates, reach, finish = programs.candidates, programs.reach, programs.finish
    condition = np.asarray(db.condition, q.dtype)
    cand, nb = candidates(key, lo, hi, condition, human_mask(db))
    # In key order, the first m candidates with enough neighbours whose IK reaches them. The IK
    # (the costly part) runs on m candidates at a time, as many times as that takes: usually
    # once or twice, where all n_cand of them would be 8x the work at the default oversampling.
    near = np.flatnonzero(np.asarray(nb.n_inside) >= settings.min_neighbours)
    chosen, qf, ik_error = [], [], []
    for start in range(0, near.size, m):
        idx = near[start : start + m]
        padded = np.concatenate([idx, np.full(m - idx.size, idx[-1])])  # one program shape
        ik = reach(*_take((cand, nb), padded), q)
        ok = np.flatnonzero(np.asarray(ik.pos_error)[: idx.size] <= settings.ik_tolerance)
        chosen.append(idx[ok])
        # The IK starts at the nearest neighbour's final posture: a continuous joint that
        # turned past a half turn from there goes back by whole turns (the same posture).
        start = q[np.asarray(nb.index)[idx[ok], 0], -1]
        qf.append(_near_branch(np.asarray(ik.q)[ok], start, robot.continuous))
        ik_error.append(np.asarray(ik.pos_error)[ok])
        if sum(c.size for c in chosen) >= m:
            break
    n_chosen = sum(c.size for c in chosen)
    if n_chosen < m:
        raise UserError(
            f"evolution.conditions: only {n_chosen} of {n_cand} candidate targets have "
            f">= {settings.min_neighbours} demonstrations within {basis.radius} m and an IK "
            f"posture within {settings.ik_tolerance} m ({near.size} pass the first test); "
            f"expected {m}: raise evolution.candidates_per_condition, lower "
            f"evolution.min_neighbours or shrink evolution.region_margin"
        )
    chosen_nb, target = _take((nb, cand), np.concatenate(chosen)[:m])
    qf_m, ik_error_m = np.concatenate(qf)[:m], np.concatenate(ik_error)[:m]
    durations = db.duration if durations is None else durations
    return finish(target, chosen_nb, qf_m, ik_error_m, q, np.asarray(durations, q.dtype))


def conditions_to_tree(c: Conditions) -> dict:
    """Plain nested dict of numpy arrays (checkpoints); without the derived ``candidates``."""
    skip = ("boundary", "candidates")
    out: dict[str, Any] = {k: np.asarray(v) for k, v in c._asdict().items() if k not in skip}
    out["boundary"] = {k: np.asarray(v) for k, v in c.boundary._asdict().items()}
    return out


def conditions_from_tree(tree: dict) -> Conditions:
    """Inverse of `conditions_to_tree`."""
    fields = {k: v for k, v in tree.items() if k != "boundary"}
    return Conditions(boundary=Boundary(**tree["boundary"]), **fields)


def conditions_template(m: int, t: int, j: int) -> dict:
    """Zero arrays shaped like `conditions_to_tree` of m conditions (checkpoint restore)."""
    f = np.float32
    mj = np.zeros((m, j), f)
    return {
        "target": np.zeros((m, 3), f),
        "ik_error": np.zeros(m, f),
        "n_human_inside": np.zeros(m, np.int32),
        "human_q": np.zeros((m, t, j), f),
        "boundary": {"q0": mj, "qf": mj, "qd0": mj, "qdf": mj, "duration": np.zeros(m, f)},
    }
