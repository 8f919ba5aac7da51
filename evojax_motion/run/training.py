"""The config-driven training run: the paper's offline process (sec. 3.1, Fig. 3; sec. 4.2-4.4).

``run_training(cfg, out_dir)`` builds the human database (synthetic demonstrations or
``demos_file``), draws the fixed condition set, and runs ``evolution.generations`` generations of
the jitted `evolution.step.make_generation_step`, compiled while generation 0 is made
(`run.compilation`). The run folder holds:

| path | content |
|---|---|
| ``config.yaml`` | the resolved config (a resumed run must match it) |
| ``robot.xml`` | the robot's MJCF |
| ``metrics.jsonl`` | one JSON object per generation (fields: `METRIC_FIELDS`) |
| ``checkpoints/<g>/`` | orbax checkpoint after generation g (0 = before the first; then every |
| | ``train.checkpoint_every``-th and the last): database, conditions, generation index; JSON: |
| | metrics so far, human-only baseline, checksum |
| ``db_initial.npz``, ``db_gen1.npz``, ``db_final.npz`` | databases
(``motion.database.save_database``) |
| ``plots/costs.png``, ``plots/joint_angles.png`` | Fig. 5 and Fig. 8 of the paper |
| ``summary.json`` | the summary `run_training` returns |

The generation step has no randomness (the condition set is drawn once, from ``seed``), so a
resumed run recomputes exactly what an uninterrupted one would: the final database is the same bit
for bit. Every file is written atomically (temporary file + ``os.replace``), so a run stopped by
a full disk, like a killed one, resumes. While a run is going, ``.lock`` names its process and a
second run of the folder is refused (`run_lock`).

A run can span several processes (``train --distributed``, docs/scaling.md): each computes every
generation on its share of the conditions; process 0 alone takes the lock and writes the files
above, orbax's checkpoints included (`run.processes`).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from evojax_motion.console import log
from evojax_motion.errors import UserError
from evojax_motion.evolution.stats import GenerationStats
from evojax_motion.run import compilation
from evojax_motion.run.atomic import atomic_write_text

if TYPE_CHECKING:
    from evojax_motion.settings import Config

# What the processes of one run must agree on (`run.processes.check_same`)
SHARED_FOLDER = "view of the run folder (it must be on a file system that all processes share)"
CONDITIONS_STREAM = 1  # fold_in index of the condition set's key (seed -> streams)
CONFIG_FILE, ROBOT_FILE, METRICS_FILE = "config.yaml", "robot.xml", "metrics.jsonl"
CHECKPOINT_DIR, PLOT_DIR, SUMMARY_FILE = "checkpoints", "plots", "summary.json"
DB_INITIAL, DB_GEN1, DB_FINAL = "db_initial.npz", "db_gen1.npz", "db_final.npz"
METRIC_FIELDS = (
    "generation",
    "seconds",  # wall time from the previous generation's result (or the loop's start) to this
    # one's: the generation's execution, overlapped with writing the previous one's files
    "finished_at",  # Unix time [s] at its end (time to first generation, gaps on resume)
    *GenerationStats._fields,  # `evolution.stats.GenerationStats`, in order
)


# ----------------------------------------------------------------------------- run folder checks


def _config_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted keys where two nested config dicts differ."""
    out = []
    for key in sorted(set(a) | set(b)):
        dotted = f"{prefix}{key}"
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _config_diff(va, vb, dotted + ".")
        elif va != vb:
            out.append(f"{dotted} ({va!r} there, {vb!r} here)")
    return out


def _temporaries(out: Path) -> list[Path]:
    """Temporary files of atomic writes (``.NAME.XXXX.tmp``) left by a killed run."""
    return [p for p in out.glob(".*.tmp") if p.is_file()] if out.is_dir() else []


def _with_new_keys(theirs: dict, resolved: dict, mine: dict) -> dict:
    """``theirs`` plus the keys of ``mine`` it lacks, at their values in ``resolved`` (``theirs``
    validated: the defaults of settings added since ``theirs`` was written)."""
    out = dict(theirs)
    for key, value in mine.items():
        if key not in out and key in resolved:
            out[key] = resolved[key]
        elif isinstance(out.get(key), dict) and isinstance(value, dict):
            out[key] = _with_new_keys(out[key], resolved.get(key) or {}, value)
    return out


def _refuse_a_file(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: expected a run directory, found a file")


def check_run_dir(out: Path, cfg_dict: dict, resume: bool) -> bool:
    """Refuse a folder that is not this run's; True when ``out`` already holds this run.

    Raises ``UserError`` (nothing written) when: ``out`` is a file; without ``resume``, ``out`` is
    not empty (its lock file aside); with ``resume``, ``out`` holds no run; ``out`` holds another
    config's run.
    """
    import yaml

    from evojax_motion.run.lock import LOCK_FILE
    from evojax_motion.settings import config_from_dict, config_to_dict

    _refuse_a_file(out)
    leftovers = {p.name for p in _temporaries(out)}  # never read; removed when the run starts
    leftovers.add(LOCK_FILE)  # this run's, or one a killed run left
    names = (p.name for p in out.iterdir()) if out.is_dir() else ()
    entries = sorted(n for n in names if n not in leftovers)
    cfg_path = out / CONFIG_FILE
    if cfg_path.is_file():
        try:
            theirs = yaml.safe_load(cfg_path.read_text())
        except yaml.YAMLError:
            theirs = None
        if not isinstance(theirs, dict):
            raise UserError(f"{cfg_path}: unreadable; {out} does not hold a run of this config")
        with contextlib.suppress(UserError):  # keys added since that run, at their defaults
            theirs = _with_new_keys(theirs, config_to_dict(config_from_dict(theirs)), cfg_dict)
        # The device count may change between a run and its resume (results then agree up to
        # floating-point reduction order; docs/scaling.md).
        mine = {k: v for k, v in cfg_dict.items() if k != "parallel"}
        diff = _config_diff({k: v for k, v in theirs.items() if k != "parallel"}, mine)
        if diff:
            shown = "; ".join(diff[:3]) + (f"; ... ({len(diff)} keys)" if len(diff) > 3 else "")
            raise UserError(f"{out}: holds the run of another config: {shown}")
    if resume:
        if not cfg_path.is_file():
            raise UserError(f"{out}: --resume: no run to resume here (no {CONFIG_FILE})")
        return True
    if entries:
        hint = "pass --resume to continue it" if cfg_path.is_file() else "choose an empty folder"
        raise UserError(f"{out}: not empty ({hint})")
    return False


# ------------------------------------------------------------------------------------ helpers


def _json_value(x) -> Any:
    x = np.asarray(x).item() if np.ndim(x) == 0 else x
    if isinstance(x, float) and not math.isfinite(x):
        return None  # strict JSON: NaN/inf (e.g. a mean over no slot) become null
    return x


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.4g}"


def _metrics_text(rows: list[dict]) -> str:
    return "".join(json.dumps(r, allow_nan=False) + "\n" for r in rows)


def _state_tree(db, conditions, generation: int) -> dict:
    from evojax_motion.evolution.conditions import conditions_to_tree

    return {
        "db": {k: np.asarray(v) for k, v in db._asdict().items()},
        "conditions": None if conditions is None else conditions_to_tree(conditions),
        "generation": np.asarray(generation, np.int32),
    }


def _from_state_tree(tree: dict):
    from evojax_motion.evolution.conditions import conditions_from_tree
    from evojax_motion.motion.database import Database

    return Database(**tree["db"]), conditions_from_tree(tree["conditions"]), int(tree["generation"])


def human_only_baseline(costs, conditions) -> dict:
    """Eq. 5 cost and Fig. 5 torque sum of the human-only interpolations, averaged over the
    conditions: what the demonstrations alone give before any evolution (``conditions.human_q``).
    ``costs``: `motion.objective.CostProgram`.
    """
    measured = costs(conditions.human_q, conditions.boundary.duration)
    return {
        "human_only_cost_mean": _json_value(np.mean(np.asarray(measured.cost, np.float64))),
        "human_only_torque_sum_mean": _json_value(
            np.mean(np.asarray(measured.torque_sum, np.float64))
        ),
    }


def _numpy_db(db):
    from evojax_motion.motion.database import Database

    return Database(*(np.asarray(a) for a in db))


# ---------------------------------------------------------------------------------- the run


def neighbour_durations(cfg: Config, robot, duration, peak_velocity) -> np.ndarray | None:
    """The demonstrations' durations ``(n,)`` [s] as the condition draw counts them
    (`evolution.conditions.make_conditions`'s ``durations``): slowed to the robot's velocity
    limits less ``compiler.limit_headroom`` with ``evolution.fit_speed`` (logged when any is),
    None (the recorded ones) without it or with a fixed ``evolution.duration``.
    ``peak_velocity (n, J)`` [rad/s]: each demonstration's peak joint speeds."""
    from evojax_motion.motion.feasibility import slowed_line, slowed_to_velocity_limits

    evo, headroom = cfg.evolution, cfg.compiler.limit_headroom
    if not evo.fit_speed or evo.duration is not None:
        return None
    slowed, factor = slowed_to_velocity_limits(
        duration, peak_velocity, robot.velocity_limit, headroom
    )
    line = slowed_line(factor, headroom)
    if line is not None:
        log(line)
    return slowed


def initial_state(
    cfg: Config, robot, dyn, setup: compilation.SetupPrograms | None = None, on_traced=None
):
    """Generation 0 of ``cfg``: ``(db, conditions, meta, baseline, timings)``.

    The human database (``demos_file`` or synthetic demonstrations), each primitive's eq. 5 cost
    with this run's dynamics, the condition set drawn with the key ``fold_in(key(seed), 1)``, the
    database of capacity ``n_human + m`` with empty evolved slots, and `human_only_baseline`;
    logs how many demonstrations are over a limit of the robot (from the costs' own torques).
    ``setup``: `run.compilation.setup_programs` made (and perhaps being compiled) beforehand,
    used where its sizes are the demonstrations'. ``on_traced()``: called once, when the
    synthesis of the demonstrations is traced, else once they are read and checked
    (`run.workflow.demonstrations`, `run.workflow.check_samples`).
    Writes nothing.
    """
    import jax

    from evojax_motion.evolution.conditions import make_conditions
    from evojax_motion.evolution.step import init_evolved_slots, with_search_candidates
    from evojax_motion.motion.database import Database, nonfinite_rows
    from evojax_motion.motion.feasibility import count_over_limits, over_limits_line
    from evojax_motion.run.workflow import cache_parts, check_samples, demonstrations

    t0 = time.perf_counter()
    # First: a key is a few tiny XLA programs, compiled in no time before other compiles start
    # to share the cores (then a second each).
    key = jax.random.fold_in(jax.random.key(cfg.seed), CONDITIONS_STREAM)
    called: list[bool] = []

    def traced():
        if on_traced is not None and not called:
            called.append(True)
            on_traced()

    synthesis_costs = None if setup is None else setup.costs  # rows >= demos.count
    humans, meta = demonstrations(
        cfg, robot, dyn, cache_parts(cfg, robot, dyn), traced, synthesis_costs
    )
    check_samples(cfg, humans.q.shape[1])
    traced()
    if setup is None or humans.q.shape != setup.sizes:
        setup = compilation.setup_programs(cfg, robot, dyn, humans.q.shape)
    grid, costs = setup.grid, setup.costs
    measured = costs(humans.q, humans.duration)
    humans = humans._replace(cost=measured.cost.astype(np.float32))
    bad = nonfinite_rows(humans)  # a numerical failure drops that demonstration, not the run
    for i in bad:
        msg = f"demonstration {i}: NaN/inf in its trajectory, condition or cost; not used"
        log(f"warning: {msg}")
    if bad.size == humans.valid.size:
        raise UserError("demonstrations: expected at least one finite demonstration, got none")
    humans = Database(*(np.delete(np.asarray(a), bad, axis=0) for a in humans))
    peaks = [np.delete(p, bad, axis=0) for p in (measured.peak_velocity, measured.peak_torque)]
    log(over_limits_line(count_over_limits(humans, robot, dyn, peaks=peaks)))
    durations = neighbour_durations(cfg, robot, humans.duration, peaks[0])
    t1 = time.perf_counter()
    conditions = make_conditions(
        humans, dyn, robot, cfg.evolution, cfg.basis, grid, key, programs=setup.conditions,
        durations=durations,
    )  # fmt: skip
    conditions = jax.tree_util.tree_map(np.asarray, conditions)
    db = _numpy_db(init_evolved_slots(humans, conditions))
    conditions = with_search_candidates(db, conditions, cfg.basis)
    baseline = human_only_baseline(costs, conditions)
    timings = {"demos_seconds": t1 - t0, "conditions_seconds": time.perf_counter() - t1}
    return db, conditions, meta, baseline, timings


def shared_initial_state(
    cfg: Config, robot, dyn, setup: compilation.SetupPrograms | None = None, on_traced=None
):
    """`initial_state` (same arguments and result) made by process 0 and sent to the others;
    ``meta``, ``baseline`` and ``timings`` are process 0's to write (None, {}, {} elsewhere).

    The step's replicated inputs must be the same bits on every process (docs/scaling.md). The
    others wait rather than make the state too: JAX's persistent cache is written by process 0
    only, so they would compile its programs again in every run. They receive it into arrays
    shaped as `run.compilation.expected_inputs`; where process 0's differ (a non-finite
    demonstration dropped), they make the state themselves, then take process 0's bits. With one
    process: `initial_state`.
    """
    from evojax_motion.evolution.sharding import same_on_every_process
    from evojax_motion.run import processes
    from evojax_motion.run.cache import signature

    args = (cfg, robot, dyn, setup, on_traced)
    primary = processes.is_primary()
    made = processes.together(lambda: initial_state(*args) if primary else None)
    inputs = made[:2] if made is not None else compilation.expected_inputs(cfg, robot)
    if processes.first_different(repr(None if inputs is None else signature(inputs))) is not None:
        made = made or initial_state(*args)
        inputs = made[:2]
    db, conditions = same_on_every_process(inputs)
    meta, baseline, timings = (None, {}, {}) if made is None else made[2:]
    return db, conditions, meta, baseline, timings


def _restore(out: Path, manager, cfg: Config, robot):
    """The newest usable checkpoint of the run in ``out`` (or None), with the problems met.

    Damaged steps newer than the one restored are deleted (new saves would collide with them).
    Every process of a run restores the same step (`run.processes.check_same`; the checksum
    vouches for its bits).
    """
    from evojax_motion.motion.database import load_database
    from evojax_motion.run import checkpoint as ck
    from evojax_motion.run.processes import check_same
    from evojax_motion.run.workflow import check_database_matches_robot

    steps = manager.all_steps()  # every process restores (orbax): they must see the same steps
    check_same(repr(((out / DB_INITIAL).is_file(), steps)), SHARED_FOLDER)
    if not ((out / DB_INITIAL).is_file() and steps):
        return None, []
    db_init, meta = load_database(out / DB_INITIAL)
    check_database_matches_robot(meta, robot, str(out / DB_INITIAL))
    restored, problems = ck.restore_latest(manager, checkpoint_template(cfg, db_init))
    check_same(repr(None if restored is None else restored.step), SHARED_FOLDER)
    for p in problems:
        log(f"warning: {p}")
    if restored is None:
        log("warning: no usable checkpoint; starting the run again from generation 0")
    else:
        log(f"resuming after generation {restored.step} (checkpoint {restored.step})")
    for step in manager.all_steps():
        if restored is None or step > restored.step:
            manager.delete(step)
    return restored, problems


def checkpoint_template(cfg: Config, db_initial) -> dict:
    """A state shaped and typed as a checkpoint of a run of ``cfg`` holds it (``db_initial``,
    the run's ``db_initial.npz``, and zero conditions): ``run.checkpoint.restore_latest``'s
    template."""
    from evojax_motion.evolution.conditions import conditions_template

    _, t, j = db_initial.q.shape
    template = _state_tree(db_initial, None, 0)
    template["conditions"] = conditions_template(cfg.evolution.conditions, t, j)
    return template


def run_training(
    cfg: Config, out_dir: str | Path, resume: bool = False, progress: bool = True
) -> dict:
    """Evolve the database of ``cfg`` into ``out_dir``; resume the run there with ``resume``.

    Returns the summary (also written to ``summary.json`` and printed): generations, eq. 5 cost
    and torque sum of generation 1 and of the last one with the reduction in %, the final
    ``human_deviation_deg``, the human-only baseline (`human_only_baseline`), seconds per
    generation (wall time from one generation's result to the next: its execution, overlapped
    with the previous generation's files; compile and setup times separate), paths.
    Raises ``UserError`` before writing anything when ``out_dir`` is not usable (see
    `check_run_dir`) or in use by another run (`run_lock`), the demonstrations cannot be read or
    the condition set cannot be drawn; ``OSError`` naming the file or folder where the file
    system refuses a write (the run then resumes once there is room: files are atomic).

    After ``jax.distributed.initialize`` (`evolution.sharding.initialize_distributed`), every
    process of the run calls it alike: the conditions are sharded over all their devices,
    process 0's initial state is everyone's, and process 0 alone writes files and prints
    (`run.processes`); where the processes differ in ``cfg`` or ``resume``, every one raises
    ``UserError``.
    """
    import jax

    from evojax_motion.run import processes
    from evojax_motion.run.lock import hold_run_folder
    from evojax_motion.settings import config_to_yaml

    out = Path(out_dir)
    _refuse_a_file(out)  # before the lock, which makes the folder
    processes.check_same(config_to_yaml(cfg) + f"resume: {resume}\n", "config or --resume")
    with contextlib.ExitStack() as stack:
        # process 0 alone holds the lock; a refusal stops every process
        primary = processes.is_primary()
        processes.together(lambda: primary and stack.enter_context(hold_run_folder(out)))
        stack.enter_context(processes.quiet_unless_primary())
        # On GPUs float32 matrix products default to TF32 (10-bit mantissa); the time grid's
        # derivative operators would lose accelerations to it. Full precision, scoped to the run.
        stack.enter_context(jax.default_matmul_precision("highest"))
        return _run_training(cfg, out, resume, progress and primary)


def _run_training(cfg: Config, out: Path, resume: bool, progress: bool) -> dict:
    import jax

    from evojax_motion.model.dynamics import slow_cpu_layout_note, training_dynamics
    from evojax_motion.run import processes
    from evojax_motion.run.cache import signature
    from evojax_motion.run.workflow import (
        check_run_memory,
        check_settings,
        make_robot_dynamics,
        synthesises,
    )
    from evojax_motion.settings import config_to_dict, config_to_yaml

    t_start = time.perf_counter()
    evo, tr = cfg.evolution, cfg.train
    check_settings(cfg)
    processes.check_devices(cfg.parallel.devices)
    resume = processes.together(lambda: check_run_dir(out, config_to_dict(cfg), resume))
    robot, dyn = make_robot_dynamics(cfg)
    dyn, short = training_dynamics(dyn, evo.generations, evo.conditions)
    note = slow_cpu_layout_note(dyn)
    if note and processes.is_primary():
        log(note)
    check_run_memory(cfg, robot)  # sizes that cannot fit: refused before any work
    resuming = resume and (out / CHECKPOINT_DIR).is_dir()
    processes.check_same(repr(resuming), SHARED_FOLDER)
    primary = processes.is_primary()  # writes the files; the others compute and checkpoint
    # A new run compiles its step and setup programs in background threads: from now on, or,
    # where the demonstrations are synthesised, once their synthesis is traced. (Nothing for a
    # demonstrations file that `initial_state` will refuse: `run.compilation.expected_sizes`.)
    early = None if resuming or not primary else compilation.EarlyCompile(cfg, robot, dyn, short)
    if early is not None and not synthesises(cfg, robot, dyn):
        early.start()
    try:
        from tqdm.auto import tqdm

        from evojax_motion.evolution.step import with_search_candidates
        from evojax_motion.motion.database import save_database
        from evojax_motion.run import checkpoint as ck

        restored, problems, manager = None, [], None
        if resuming:
            manager = ck.open_manager(out / CHECKPOINT_DIR, tr.max_to_keep)
            restored, problems = _restore(out, manager, cfg, robot)
        timings: dict = {}
        if restored is not None:
            db, conditions, start = _from_state_tree(restored.state)
            conditions = with_search_candidates(db, conditions, cfg.basis)
            meta = meta_of(out)
            metrics = [dict(r) for r in restored.meta.get("metrics", [])][:start]
            baseline = dict(restored.meta.get("baseline", {}))
        else:  # every UserError of the inputs is raised here, before anything is written
            setup, cue = (None, None) if early is None else (early.setup, early.start)
            made = shared_initial_state(cfg, robot, dyn, setup, cue)
            db, conditions, meta, baseline, timings = made
            start, metrics = 0, []
    except BaseException:
        if early is not None:
            early.wait()  # its thread ends before the error reaches the user
        raise
    early_step, waited = compilation.wait_for_step(early)

    if primary:
        out.mkdir(parents=True, exist_ok=True)
        for leftover in _temporaries(out):  # of a run killed in the middle of a write
            leftover.unlink(missing_ok=True)
        atomic_write_text(out / CONFIG_FILE, config_to_yaml(cfg))
        atomic_write_text(out / ROBOT_FILE, robot.mjcf)
    # Checkpoints: every process calls orbax alike (it synchronises them; process 0 writes).
    if manager is None:
        manager = ck.open_manager(out / CHECKPOINT_DIR, tr.max_to_keep)
    if restored is None:
        if primary:
            save_database(out / DB_INITIAL, db, meta)
        ck.save_checkpoint(manager, 0, _state_tree(db, conditions, 0), _meta([], baseline))
    if primary:
        atomic_write_text(out / METRICS_FILE, _metrics_text(metrics))

    t0 = time.perf_counter()
    if start < evo.generations:  # ahead of time, so that "seconds" per generation is execution
        if early_step is not None and early_step[0] == signature((db, conditions)):
            compiled = early_step[1]
        else:
            compiled = compilation.compile_generation_step(
                cfg, robot, dyn, db, conditions, short_run=short
            )
    # What the demonstrations and conditions did not hide: the wait for the early compile, or
    # the compile here where there was none (or its program does not fit).
    timings["compile_seconds"] = waited + time.perf_counter() - t0

    bar = tqdm(
        total=evo.generations, initial=start, disable=not progress, desc="evolution", unit="gen"
    )
    db_in, conditions_in = compilation.generation_inputs(cfg, db, conditions)

    def launch(g: int, db_in) -> tuple:
        """``(pending, error)``: generation ``g`` queued on the device (``(db, stats)``, not
        waited for; None past the last generation) or the error queueing it raised."""
        if g > evo.generations:
            return None, None
        try:
            return compiled(db_in, conditions_in, np.asarray(g, np.int32)), None
        except Exception as e:  # raised by the caller once the previous generation is saved
            return None, e

    try:
        # Generation g + 1 is queued before generation g's files are written: the device
        # computes it while the host writes (on a GPU, a paper-scale generation takes less time
        # than its files). An error queueing it is raised once g's files are written.
        pending, failed = launch(start + 1, db_in)
        t0 = time.perf_counter()
        for g in range(start + 1, evo.generations + 1):
            if failed is not None:
                raise failed
            db_new, stats = pending
            db_new = jax.block_until_ready(db_new)
            pending, failed = launch(g + 1, db_new)
            db = _numpy_db(db_new)  # for the files
            now = time.perf_counter()
            row = {
                "generation": g,
                "seconds": round(now - t0, 4),
                "finished_at": round(time.time(), 3),
            }
            t0 = now
            row.update({k: _json_value(v) for k, v in stats._asdict().items()})
            metrics.append(row)
            if g == 1 and primary:  # kept for Fig. 8 (first vs last); written before checkpoint 1
                save_database(out / DB_GEN1, db, meta)
            if g % tr.checkpoint_every == 0 or g == evo.generations:
                tree, meta_g = _state_tree(db, conditions, g), _meta(metrics, baseline)
                ck.save_checkpoint(manager, g, tree, meta_g)
            if primary:
                atomic_write_text(out / METRICS_FILE, _metrics_text(metrics))
            bar.update(1)
            bar.set_postfix(
                cost=_fmt(row["db_cost_mean"]),
                torque=_fmt(row["torque_sum_mean"]),
                replaced=row["n_replaced"],
                dev_deg=_fmt(row["human_deviation_deg"]),
            )
    finally:
        bar.close()
        manager.close()

    told = rejections_line(metrics[-1], evo.conditions) if metrics and primary else None
    if told is not None:
        log(told)
    plot_paths = []
    if primary:
        save_database(out / DB_FINAL, db, meta)
        if tr.plots:
            plot_paths = _write_plots(out, cfg, robot, db, conditions, metrics, baseline)
    timings["total_seconds"] = time.perf_counter() - t_start
    summary = _summary(out, metrics, baseline, timings, plot_paths)
    summary["checkpoint_problems"] = problems
    summary["resumed_from"] = None if restored is None else int(restored.step)
    if primary:
        text = json.dumps(summary, indent=2, allow_nan=False) + "\n"
        atomic_write_text(out / SUMMARY_FILE, text)
    print_summary(summary)
    return summary


def meta_of(out: Path):
    """The ``DatabaseMeta`` of a run (read back from its ``db_initial.npz``)."""
    from evojax_motion.motion.database import load_database

    return load_database(out / DB_INITIAL)[1]


def _write_plots(out, cfg, robot, db, conditions, metrics, baseline) -> list[str]:
    from evojax_motion.motion.database import count_human, load_database
    from evojax_motion.report.plots import plot_costs, plot_joint_angles

    paths = []
    if metrics:
        paths.append(str(plot_costs(metrics, out / PLOT_DIR / "costs.png", baseline=baseline)))
    if not (out / DB_GEN1).is_file():
        return paths
    first, _ = load_database(out / DB_GEN1)
    n_human = count_human(db)
    both = np.asarray(first.valid[n_human:]) & np.asarray(db.valid[n_human:])
    c = cfg.train.plot_condition
    if c is None and both.any():  # the condition that changed most: the most telling Fig. 8
        drop = np.full(both.shape, -np.inf)  # slots empty in either have cost inf: left out
        drop[both] = np.asarray(first.cost[n_human:])[both] - np.asarray(db.cost[n_human:])[both]
        c = int(np.argmax(drop))
    if c is None or not both[c]:
        return paths
    slot = n_human + c
    target = [round(float(x), 3) for x in np.asarray(conditions.target[c])]
    path = plot_joint_angles(
        first.q[slot],
        db.q[slot],
        float(db.duration[slot]),
        robot.joint_names,
        out / PLOT_DIR / "joint_angles.png",
        q_human=np.asarray(conditions.human_q[c]),
        last_label=f"generation {len(metrics)}",
        title=f"condition {c}: hand target {target} m (Fig. 8)",
    )
    return [*paths, str(path)]


def _meta(metrics: list[dict], baseline: dict) -> dict:
    """JSON beside a checkpoint's arrays: the metrics so far and the human-only baseline."""
    return {"metrics": metrics, "baseline": baseline}


# metrics.jsonl's rejection counts: the reason each names, and what helps against it
_REJECTIONS = {
    "n_rejected_velocity": (
        "velocity limit",
        "longer durations help (evolution.fit_speed, evolution.duration)",
    ),
    "n_rejected_torque": (
        "torque limit",
        "slower motions (evolution.duration) lower the dynamic torques, not gravity's",
    ),
    "n_rejected_limits": (
        "joint range",
        "conditions near a range's end are hard to reach (evolution.region_margin)",
    ),
    "n_rejected_bc": (
        "boundary conditions",
        "see evolution.bc_tolerance and bc_velocity_tolerance",
    ),
    "n_rejected_nonfinite": ("not finite", "a numerical failure of the optimiser"),
}
REJECTED_WARN_FRACTION = 0.25  # a generation discarding this share of its offspring is told


def rejections_line(row: dict, conditions: int) -> str | None:
    """A warning on one ``metrics.jsonl`` row when its generation discarded at least
    `REJECTED_WARN_FRACTION` of its ``conditions`` offspring: how many, for what, and what helps
    against the most common reason; None otherwise."""
    counts = {k: int(row.get(k) or 0) for k in _REJECTIONS}
    total = sum(counts.values())
    if conditions <= 0 or total < REJECTED_WARN_FRACTION * conditions:
        return None
    parts = ", ".join(f"{_REJECTIONS[k][0]} {n}" for k, n in counts.items() if n)
    top = max(counts, key=lambda k: counts[k])
    return (
        f"warning: generation {row.get('generation')} discarded {total} of {conditions} "
        f"offspring ({parts}; metrics.jsonl n_rejected_*): "
        f"{_REJECTIONS[top][1]}"
    )


def _summary(out: Path, metrics: list[dict], baseline: dict, timings: dict, plots) -> dict:
    first, last = (metrics[0], metrics[-1]) if metrics else ({}, {})

    def reduction(name):
        a, b = first.get(name), last.get(name)
        return None if a in (None, 0) or b is None else round(100.0 * (a - b) / a, 3)

    secs = [r["seconds"] for r in metrics]
    summary = {
        "generations": len(metrics),
        "db_cost_gen1": first.get("db_cost_mean"),
        "db_cost_last": last.get("db_cost_mean"),
        "db_cost_reduction_pct": reduction("db_cost_mean"),
        "torque_sum_gen1": first.get("torque_sum_mean"),
        "torque_sum_last": last.get("torque_sum_mean"),
        "torque_sum_reduction_pct": reduction("torque_sum_mean"),
        "human_deviation_deg": last.get("human_deviation_deg"),
        "n_valid": last.get("n_valid"),
        **baseline,
        "seconds_per_generation": round(float(np.mean(secs)), 4) if secs else None,
    }
    summary.update({k: round(v, 3) for k, v in timings.items()})
    summary.update(
        run_dir=str(out),
        db_final=str(out / DB_FINAL),
        metrics=str(out / METRICS_FILE),
        plots=list(plots),
    )
    return summary


def print_summary(summary: dict) -> None:
    """The summary as an aligned two-column table on stdout."""
    keys = [k for k in summary if k not in ("checkpoint_problems",)]
    width = max(len(k) for k in keys)
    for k in keys:
        v = summary[k]
        if isinstance(v, float):
            v = f"{v:.6g}"
        elif isinstance(v, list):
            v = ", ".join(map(str, v)) if v else "-"
        print(f"{k:<{width}}  {v}")
