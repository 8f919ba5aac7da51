"""One generation with the condition set sharded over many devices, on one host or many.

The generation step (paper sec. 3.1, 4.3; `evolution.step.make_generation_step`) is independent per
condition once the database is fixed: condition c selects its neighbours (eq. 6) in the whole
database, builds its PCA basis, runs the compiler via optimisation (eq. 3-5) and competes with the
incumbent of its own slot ``n_human + c`` (survivor selection, a per-slot argmin). So the
conditions are split over a 1-D device mesh (axis ``"conditions"``) and the database is
replicated: each device searches the neighbours of its own conditions in the whole database, and
the new evolved slots are all-gathered so that every device holds the next generation's database.

`make_sharded_generation_step` runs the unchanged step of `evolution.step` per device inside
``jax.shard_map`` (not the automatic SPMD partitioner: it replicates ``lax.top_k``, i.e. would
all-gather the whole ``(m, N)`` distance matrix of the neighbour search). The compiled program
holds only these collectives: all-gathers of the new evolved slots and all-reduces of scalar
statistics (`combine_stats`). Each device's loops (the Newton iterations) run on their own until
its conditions are done.

Each device's local database is the whole global database (in its own order, so neighbour
indices and distance ties are those of one device) followed by copies of the device's incumbent
slots with a NaN condition: the step wants its incumbents last, and the NaN keeps the copies out
of the neighbour search. The price: the neighbour search of m/d conditions scans N + m/d entries
instead of N (see docs/scaling.md for the hook in `evolution.step` that would remove it).

Why the database stays replicated (not sharded and all-gathered for the neighbour search): every
condition needs distances to all N entries and the trajectories of any k of them, so a sharded
database would be all-gathered in full every generation anyway; replicated, it is sent once per
generation (the new slots) and every device can answer the next generation's neighbour queries.

Padding rule: the device count d must divide the condition axis, so m conditions are padded to
``d * ceil(m / d)`` (at most d - 1 extra) with copies of the last condition whose target is NaN
(the padding mark, `pad_conditions`), and the database gets as many extra evolved slots, empty and
with a NaN condition (`pad_database`). A NaN target has no neighbour, so its offspring is
non-finite and always rejected; its slot stays empty and, with a NaN condition, is nobody's
neighbour. The real conditions thus see the very database they see on one device; the padding is
dropped before the step returns (same shapes in and out as `make_generation_step`) and the
statistics are corrected for it (`unpad_stats`).

Equality with one device: each condition's neighbours, basis, optimisation and selection are the
same computation on the same inputs. Results can still differ in the last bits because XLA's
reductions are not batch-size invariant (summing the same ``(k, T, J)`` neighbour rows inside a
batch of 4 or of 6 conditions can round differently on a CPU, one device alone), and a short Adam
run can amplify such last-bit differences (its first steps are sign-like). See docs/scaling.md.

Multi-host: every process calls `initialize_distributed` (``jax.distributed.initialize``) before
any other JAX call; ``jax.devices()`` then lists all hosts' devices and the mesh spans them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from evojax_motion.compiler.optimisation import cpu_fast_path
from evojax_motion.errors import UserError
from evojax_motion.evolution.stats import GenerationStats
from evojax_motion.evolution.step import generation_stages, generation_step
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.motion.database import Database

CONDITION_AXIS = "conditions"


def resolve_devices(devices: int | Sequence | None = None) -> list:
    """The devices to shard over: ``None`` = all of ``jax.devices()``, an int n = the first n, or
    an explicit sequence of devices. Raises ``UserError`` when more are asked than JAX sees."""
    available = jax.devices()
    if devices is None:
        return list(available)
    if isinstance(devices, int):
        if not 1 <= devices <= len(available):
            kinds = "/".join(sorted({d.platform for d in available}))
            raise UserError(
                f"parallel.devices: expected 1 to {len(available)} (the {kinds} devices JAX "
                f"sees), got {devices}"
            )
        return list(available[:devices])
    return list(devices)


def condition_mesh(devices: int | Sequence | None = None) -> Mesh:
    """A 1-D mesh over `resolve_devices` with the single axis ``CONDITION_AXIS``."""
    devs = resolve_devices(devices)
    return Mesh(np.asarray(devs), (CONDITION_AXIS,), axis_types=(AxisType.Auto,))


def replicate(tree, devices: int | Sequence | None = None):
    """``tree`` placed whole on every device of `condition_mesh` (``devices``): the placement in
    which the sharded step (any device count) takes and returns its inputs, so that a database
    it returned goes back in without a copy, and conditions put there once stay there between
    generations (`run.compilation.generation_inputs`).

    A multi-process run: every process passes the same values (`same_on_every_process`) and each
    puts them on its own devices. Not compared here: ``jax.device_put``'s check of that calls a
    NaN (a condition's unreachable posture, say) different from itself."""
    sharding = NamedSharding(condition_mesh(devices), P())
    if sharding.is_fully_addressable:  # one process
        return jax.device_put(tree, sharding)

    def put(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree_util.tree_map(put, tree)


def padded_count(m: int, multiple: int) -> int:
    """The padding rule: the smallest multiple of ``multiple`` that is >= ``m``."""
    return -(-m // multiple) * multiple


def _pad_rows(a, extra: int):
    """``a`` with ``extra`` copies of its last row appended."""
    a = jnp.asarray(a)
    return jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)], axis=0)


def pad_conditions(conditions, multiple: int):
    """Pad a ``Conditions`` of m to ``padded_count(m, multiple)``: ``(padded, n_real=m)``.

    The extra conditions copy the last one with a NaN ``target`` (the mark `is_padding` reads): no
    database entry lies at a finite distance from it, so it has no neighbour, its offspring is
    non-finite and always rejected. Static shapes: usable inside jit. ``multiple`` >= 1.
    """
    m = conditions.target.shape[0]
    extra = padded_count(m, multiple) - m
    if extra == 0:
        return conditions, m
    padded = jax.tree_util.tree_map(lambda a: _pad_rows(a, extra), conditions)
    real = jnp.arange(m + extra) < m
    return padded._replace(target=jnp.where(real[:, None], padded.target, jnp.nan)), m


def is_padding(conditions) -> jnp.ndarray:
    """``(m,)`` bool: the conditions `pad_conditions` added (non-finite target)."""
    return ~jnp.all(jnp.isfinite(jnp.asarray(conditions.target)), axis=-1)


def pad_database(db: Database, extra: int) -> Database:
    """``db`` with ``extra`` slots appended for the padded conditions: empty (``valid=False``,
    ``cost=inf``, generation 0) and with a NaN condition, so never anyone's neighbour."""
    if extra == 0:
        return db
    grown = Database(*(_pad_rows(a, extra) for a in db))
    new = jnp.arange(grown.q.shape[0]) >= db.q.shape[0]
    empty: dict[str, Any] = {
        "condition": jnp.where(new[:, None], jnp.nan, grown.condition),
        "cost": jnp.where(new, jnp.inf, grown.cost),
        "valid": grown.valid & ~new,
        "generation": jnp.where(new, 0, grown.generation),
    }
    return grown._replace(**empty)


# How the per-device statistics combine into those of the whole condition set. Every field of
# `GenerationStats` needs a rule: a new statistic without one fails at import, not silently.
# Counts are the fields named ``n_*``, maxima those named ``*_max``; the offspring rejections
# (``n_rejected_*``) exclude each other, so the accepted offspring are the rest.
_SUMS = tuple(f for f in GenerationStats._fields if f.startswith("n_"))
_REJECTIONS = tuple(f for f in _SUMS if f.startswith("n_rejected_"))
_MAXIMA = tuple(f for f in GenerationStats._fields if f.endswith("_max"))
_MEAN_OVER_ACCEPTED = ("offspring_cost_mean",)
_MEAN_OVER_VALID = ("db_cost_mean", "torque_sum_mean", "human_deviation_deg")
_MEAN_OVER_ALL = ("converged_fraction",)
_RULES = _SUMS + _MAXIMA + _MEAN_OVER_ACCEPTED + _MEAN_OVER_VALID + _MEAN_OVER_ALL
if sorted(_RULES) != sorted(GenerationStats._fields):
    raise ImportError(
        "evojax_motion.evolution.sharding: GenerationStats fields without a combination rule: "
        f"{sorted(set(GenerationStats._fields) ^ set(_RULES))}"
    )


def combine_stats(stats: GenerationStats, n_local: int, axis: str = CONDITION_AXIS):
    """The statistics of all devices' conditions from each device's own (inside ``shard_map``).

    Counts add up; maxima take the largest; a masked mean is weighted by its count (accepted
    offspring ``n_local - n_rejected_*``, or filled slots ``n_valid``) and is NaN where no device
    has any; ``converged_fraction`` is a mean over equal-sized local sets (``n_local`` each).
    """
    out = {name: jax.lax.psum(getattr(stats, name), axis) for name in _SUMS}
    out.update({name: jax.lax.pmax(getattr(stats, name), axis) for name in _MAXIMA})
    out.update({name: jax.lax.pmean(getattr(stats, name), axis) for name in _MEAN_OVER_ALL})
    accepted = n_local - sum(getattr(stats, name) for name in _REJECTIONS)
    counts = {name: accepted for name in _MEAN_OVER_ACCEPTED}
    counts.update({name: stats.n_valid for name in _MEAN_OVER_VALID})
    for name, count in counts.items():
        mean = getattr(stats, name)
        w = count.astype(mean.dtype)
        total = jax.lax.psum(jnp.where(count > 0, mean * w, 0.0), axis)
        n = jax.lax.psum(w, axis)
        out[name] = jnp.where(n > 0, total / jnp.maximum(n, 1.0), jnp.nan).astype(mean.dtype)
    return GenerationStats(**out)


def unpad_stats(stats: GenerationStats, m: int, extra: int) -> GenerationStats:
    """The statistics of the m real conditions from those of the m + ``extra`` padded ones.

    A padded condition has no neighbour (``n_short`` +1) and a non-finite offspring
    (``n_rejected_nonfinite`` +1); it is never accepted, replaced or valid, so the means over
    accepted offspring or filled slots and the residual maxima (over finite offspring) exclude it
    already. A non-finite problem does not report convergence (newton, adam), so
    ``converged_fraction``, a mean over m + extra, is rescaled to m through its integer count.
    """
    if extra == 0:
        return stats
    count = jnp.round(stats.converged_fraction * (m + extra))
    return stats._replace(
        n_rejected_nonfinite=stats.n_rejected_nonfinite - extra,
        n_short=stats.n_short - extra,
        converged_fraction=(count / m).astype(stats.converged_fraction.dtype),
    )


def _placed(fn, mesh: Mesh, options: dict | None):
    """``fn`` jitted with its inputs and outputs replicated over ``mesh`` (on one device: placed
    there) and the program ``options``."""
    replicated = NamedSharding(mesh, P())
    return jax.jit(fn, in_shardings=replicated, out_shardings=replicated, compiler_options=options)


def one_device_stages(*args, devices: int | Sequence | None = None, **limits):
    """``(prepare, finish, compiler_options)``: `evolution.step.generation_stages` (same arguments)
    jitted and placed on the one device that ``devices`` names (`resolve_devices`), as
    `sharded_generation_step` places the one-device step; ``finish(db, conditions, generation,
    prepare(db, conditions))`` is that step. `UserError` where ``devices`` names several."""
    mesh = condition_mesh(devices)
    if mesh.devices.size != 1:
        raise UserError(
            f"parallel.devices: the generation's two stages run on one device, got "
            f"{mesh.devices.size}"
        )
    prepare, finish, options = generation_stages(*args, **limits)
    return _placed(prepare, mesh, options), _placed(finish, mesh, options), options


def make_sharded_generation_step(*args, **kwargs):
    """The jitted step of `sharded_generation_step` (same arguments)."""
    return sharded_generation_step(*args, **kwargs)[0]


def sharded_generation_step(
    dyn,
    grid,
    lower,
    upper,
    n_human: int,
    basis_settings,
    optim_settings,
    settings,
    devices: int | Sequence | None = None,
    *,
    torque_limit=None,
    velocity_limit=None,
):
    """``(step, compiler_options)``: `evolution.step.make_generation_step` with the conditions
    sharded over ``devices``, and the compiler options its jit carries
    (`compiler.optimisation.cpu_fast_path`; needed again by whoever compiles the step another
    way, e.g. `run.cache.compile_traced`).

    Same arguments (``torque_limit``, ``velocity_limit`` as keywords) plus ``devices``
    (`resolve_devices`: ``None`` = all, an int = the first n, or a sequence); same contract: a
    jitted ``step(db, conditions, generation) -> (db, GenerationStats)``
    with ``db`` of capacity ``n_human + m`` and ``conditions`` of any m >= 1 (the padding is
    internal). Inputs may be numpy arrays: they are replicated to every device (in a multi-host run
    every process must pass the same values), every call again; put them there once instead
    (`replicate`): at 100,000 conditions on one H200 the numpy round trip of database and
    conditions cost 0.25 s a generation beside the step's 0.46 s. Outputs are replicated, so
    they go back in as they are, and ``np.asarray`` works on every process.
    ``step.lower(...).compile()`` works as on the plain step.

    Per device, inside ``shard_map``, the unchanged step runs on the device's m / d conditions
    against its local database (module docstring); the new slots, the rows after the global
    database, are all-gathered and written back, the statistics combined (`combine_stats`,
    `unpad_stats`). With one device: the plain step, placed on it.
    """
    mesh = condition_mesh(devices)
    n_dev = mesh.devices.size
    replicated = NamedSharding(mesh, P())
    fixed = (dyn, grid, lower, upper)
    stage_settings = (basis_settings, optim_settings, settings)
    limits = {"torque_limit": torque_limit, "velocity_limit": velocity_limit}
    # The step's program options (CPU fast path) go on the top-level jit that runs or inlines it.
    if n_dev == 1:
        plain, options = generation_step(*fixed, n_human, *stage_settings, **limits)
        return _placed(plain, mesh, options), options
    _, options = cpu_fast_path(dyn, optim_settings)  # the inner steps are built when traced

    def step(db: Database, conditions, generation):
        m = conditions.target.shape[0]
        padded, _ = pad_conditions(conditions, n_dev)
        m_pad = padded.target.shape[0]
        full = pad_database(db, m_pad - m)
        n_full, n_local = n_human + m_pad, m_pad // n_dev
        inner, _ = generation_step(*fixed, n_full, *stage_settings, **limits)

        def local(full, slots, cond, generation):
            copies = slots._replace(condition=jnp.full_like(slots.condition, jnp.nan))
            view = Database(*(jnp.concatenate([a, b]) for a, b in zip(full, copies)))  # type: ignore[arg-type]
            new, stats = inner(view, cond, generation)
            return Database(*(a[n_full:] for a in new)), combine_stats(stats, n_local)

        slots = Database(*(a[n_human:] for a in full))
        # Pinned replicated, so each device slices its own conditions and slots locally at the
        # shard_map boundary (unpinned, the partitioner moves pieces of the padding around).
        full, slots, padded = jax.lax.with_sharding_constraint((full, slots, padded), replicated)
        new_slots, stats = jax.shard_map(
            local,
            mesh=mesh,
            in_specs=(P(), P(CONDITION_AXIS), P(CONDITION_AXIS), P()),
            out_specs=(P(CONDITION_AXIS), P()),
            # The step's loops start from device-invariant constants and carry per-condition
            # (device-varying) values; the statistics leave replicated through psum/pmax.
            check_vma=False,
        )(full, slots, padded, generation)
        new_slots = jax.lax.with_sharding_constraint(new_slots, replicated)  # the all-gather
        # Every field of the new slots but ``condition`` (NaN in the copies; the step never
        # changes a slot's condition): the human rows pass through untouched.
        written: dict[str, Any] = {
            f: jnp.concatenate([getattr(db, f)[:n_human], getattr(new_slots, f)[:m]])
            for f in Database._fields
            if f != "condition"
        }
        new_db = db._replace(**written)
        return new_db, unpad_stats(stats, m, m_pad - m)

    jitted = jax.jit(
        exact_matmuls(step),
        in_shardings=replicated,
        out_shardings=replicated,
        compiler_options=options,
    )
    return jitted, options


# The variables that name a plain launch's processes (`initialize_distributed`); JAX reads the
# first itself. Under SLURM or Open MPI, JAX finds all three in the launcher's own variables.
COORDINATOR_ENV = "JAX_COORDINATOR_ADDRESS"  # "host:port" of process 0
NUM_PROCESSES_ENV, PROCESS_ID_ENV = "EVOJAX_NUM_PROCESSES", "EVOJAX_PROCESS_ID"


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> dict:
    """Join a multi-host run (``jax.distributed.initialize``); call before any other JAX call.

    Under SLURM, Open MPI's ``mpirun``, Kubernetes or Cloud TPU, JAX detects everything. Elsewhere
    give ``coordinator_address`` ("host:port" of process 0), ``num_processes`` and ``process_id``,
    or set ``JAX_COORDINATOR_ADDRESS``, ``EVOJAX_NUM_PROCESSES`` and ``EVOJAX_PROCESS_ID``.
    Returns this process's index, the process count, and the local and global device counts.
    Raises `UserError` (one line, naming the variables not set) where a setting is missing or
    wrong.
    """
    import os

    def from_env(value, name):
        raw = os.environ.get(name)
        if value is not None or raw is None:
            return value
        if not raw.strip().isdigit():
            raise UserError(f"{name}: expected a non-negative integer, got {raw!r}")
        return int(raw)

    given = {
        COORDINATOR_ENV: coordinator_address or os.environ.get(COORDINATOR_ENV) or None,
        NUM_PROCESSES_ENV: from_env(num_processes, NUM_PROCESSES_ENV),
        PROCESS_ID_ENV: from_env(process_id, PROCESS_ID_ENV),
    }
    try:
        jax.distributed.initialize(*given.values())
    except (ValueError, TypeError) as e:  # a setting JAX found neither given nor detected
        unset = [name for name, value in given.items() if value is None]
        hint = (
            f"set {', '.join(unset)} (or launch under SLURM or Open MPI)"
            if unset
            else f"check {', '.join(given)}"
        )
        lines = str(e).strip().splitlines()
        reason = lines[0].rstrip(".") if lines else type(e).__name__
        raise UserError(f"jax.distributed.initialize: {reason}; {hint}") from None
    return {
        "process_index": jax.process_index(),
        "process_count": jax.process_count(),
        "local_devices": jax.local_device_count(),
        "devices": jax.device_count(),
    }


def same_on_every_process(tree):
    """Process 0's values of a pytree of host arrays, on every process (numpy leaves).

    The sharded step takes replicated inputs that each process supplies itself. The database and
    the condition set are drawn from the seed, but GPU kernels picked by autotuning may differ
    between hosts, so a multi-host run broadcasts them once from process 0 rather than trusting
    every host to recompute the same bits. With one process: the tree as numpy arrays.
    """
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(tree)
