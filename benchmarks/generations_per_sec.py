"""Generations per second of the evolution, with the quality of the same run, against a baseline.

What one run measures (all figures from the same process, so ratios are meaningful):

- ``ours``: the end-to-end generation step (neighbours + PCA + optimisation + survivor selection,
  one jit) at each swept number of conditions / samples: compile time (ahead of time), then the
  mean wall time of ``--generations`` generations after compilation -> generations/s; peak memory
  (device allocator on GPU, max RSS on CPU);
- ``gap``: on the first ``--gap-conditions`` conditions of generation 1, the relative gap of our
  offspring's eq. 5 cost to a float64 SciPy SLSQP solve of the same problem (same basis, BCs,
  objective, start; ``slsqp_reference.py``): median / p95 / max;
- ``baseline``: what a user would write: SLSQP per condition (float64), torques from C MuJoCo
  ``mj_inverse`` with finite-difference gradients, and with analytic (float64 JAX) gradients;
  sequential and with a process pool over all cores, each solver compiled and warmed up before
  its clock starts (as ours is timed after compilation); timed on ``--baseline-conditions``
  conditions and scaled to the full condition count -> generations/s and ours/baseline ratios;
- ``first_generation``: ``evojax-motion train`` of one generation in a fresh process, from launch
  to the end of generation 1 (imports, demonstrations, conditions, compile, the generation), with
  an empty compilation cache and again with the cache the first run filled.

Usage (CPU, paper scale):
    python benchmarks/generations_per_sec.py --config configs/catch_ball.yaml
GPU sweep:
    python benchmarks/generations_per_sec.py --sweep-conditions 1000,10000,100000 \
        --baseline-conditions 0 --gap-conditions 0
Writes ``benchmarks/results/generations_per_sec_<tag>.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import multiprocessing as mp
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402  (one definition for all benchmarks)
from make_report import machine_label  # noqa: E402
from result_files import write_result  # noqa: E402

from evojax_motion.compiler.basis import pca_basis, select_neighbours, select_neighbours_among  # noqa: E402
from evojax_motion.compiler.optimisation import make_optimisation_compiler  # noqa: E402
from evojax_motion.evolution import step as evolution  # noqa: E402
from evojax_motion.evolution.step import make_generation_step  # noqa: E402
from evojax_motion.motion.database import count_human  # noqa: E402
from evojax_motion.motion.timegrid import make_time_grid  # noqa: E402
from evojax_motion.run.compilation import compile_generation_step, generation_inputs  # noqa: E402
from evojax_motion.run.training import initial_state  # noqa: E402
from evojax_motion.run.workflow import make_robot_dynamics  # noqa: E402
from evojax_motion.settings import config_from_dict, config_to_dict, load_config  # noqa: E402


def peak_memory_bytes() -> int:
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return int(stats["peak_bytes_in_use"])
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB


def build(cfg, conditions: int):
    """Robot, dynamics, the generation-0 database and condition set for ``conditions``."""
    cfg = config_from_dict(config_to_dict(cfg), [f"evolution.conditions={conditions}"])
    robot, dyn = make_robot_dynamics(cfg)
    db, conds, _meta, _baseline, _t = initial_state(cfg, robot, dyn)
    return cfg, robot, dyn, db, conds


def exact_lists(cfg, db, conds, valid: list) -> list[float] | None:
    """Per generation, the fraction of conditions whose candidate lists vouched for their
    neighbours in the database it read (`compiler.basis.select_neighbours_among`); the step
    searches the
    whole database in a generation where one does not. None without lists."""
    if conds.candidates is None:
        return None
    b = cfg.basis
    among = jax.jit(lambda v: select_neighbours_among(
        db.condition, v, conds.target, conds.candidates, b.neighbours, b.radius, b.w_pos
    )[1].mean())  # fmt: skip
    return [float(among(v)) for v in valid]


def run_generations(compiled, db, conds, first: int, n: int):
    """Generations ``first .. first + n - 1`` of the compiled step, each timed to its end:
    ``(db, seconds, stats, valid)``, ``valid`` the ``db.valid`` each generation read."""
    seconds, stats, valid = [], [], []
    for g in range(first, first + n):
        valid.append(db.valid)
        t0 = time.perf_counter()
        db, st = compiled(db, conds, np.asarray(g, np.int32))
        jax.block_until_ready(db)
        seconds.append(time.perf_counter() - t0)
        stats.append(st)
    return db, seconds, stats, valid


def compile_one_program(cfg, robot, dyn, db, conds):
    """The generation step as one XLA program (`evolution.step.make_generation_step`, as the sharded
    step runs it on each device), compiled for ``db`` and ``conds``; `train` compiles two on one
    device (`run.compilation.compile_generation_step`)."""
    grid = make_time_grid(db.q.shape[1])
    step = make_generation_step(dyn, grid, robot.lower, robot.upper, count_human(db),
                                cfg.basis, cfg.compiler, cfg.evolution)  # fmt: skip
    return step.lower(db, conds, np.asarray(1, np.int32)).compile()


def time_generations(cfg, robot, dyn, db, conds, generations: int, one_program=False) -> dict:
    """Compile the generation step ahead of time (as `train` does: with JAX's persistent cache on,
    the traced program is reused too; or as one program, `compile_one_program`), then time
    ``generations`` generations."""
    t0 = time.perf_counter()
    compile_step = compile_one_program if one_program else compile_generation_step
    compiled = compile_step(cfg, robot, dyn, db, conds)
    compile_s = time.perf_counter() - t0
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    db, conds = generation_inputs(cfg, db, conds)  # as `train` runs its generations
    db, seconds, stats, valid = run_generations(compiled, db, conds, 1, generations)
    costs = [float(st.db_cost_mean) for st in stats]
    # Generation 1 fills empty slots (different work than later ones): report both.
    later = seconds[1:] or seconds
    return {
        "conditions": int(conds.target.shape[0]),
        "samples": int(db.q.shape[1]),
        "compile_s": compile_s,
        "seconds_per_generation": float(np.median(later)),
        "first_generation_s": seconds[0],
        "generations_per_s": 1.0 / float(np.median(later)),
        "seconds": seconds,
        "db_cost_mean": costs,
        "search": "whole database" if conds.candidates is None else "candidate lists",
        "exact_lists": exact_lists(cfg, db, conds, valid),
        "flops_per_generation": float((cost or {}).get("flops", float("nan"))),
        "peak_memory_bytes": peak_memory_bytes(),
    }


def generation1_problems(cfg, robot, dyn, db, conds, n: int):
    """Bases and boundaries of the first ``n`` conditions at generation 1 (the initial database).
    Their products are full precision whatever the caller's default (`basis` sets it on each)."""
    grid = make_time_grid(db.q.shape[1])
    b = cfg.basis
    nb = select_neighbours(
        db.condition, db.valid, conds.target[:n], b.neighbours, b.radius, b.w_pos
    )
    basis = pca_basis(db.q, db.duration, nb, cfg.compiler.n_components)
    boundary = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], conds.boundary)
    return grid, jax.tree_util.tree_map(np.asarray, basis), boundary


def optimality_gap(cfg, robot, dyn, db, conds, n: int) -> dict:
    """Our optimiser vs float64 SLSQP on the same ``n`` problems of generation 1."""
    from slsqp_reference import solve_reference, torque_costs_f64

    grid, basis, boundary = generation1_problems(cfg, robot, dyn, db, conds, n)
    ours = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, cfg.compiler)(
        basis, boundary
    )
    ref = solve_reference(robot, grid, basis, boundary, cfg.compiler, gradient="jax")
    ours_cost = torque_costs_f64(robot, grid, np.asarray(ours.q), boundary.duration)
    ok = np.asarray(ours.within_limits) & np.asarray(ours.finite)
    gap = (ours_cost - ref.cost) / ref.cost
    return {
        "conditions": n,
        "compared": int(ok.sum()),
        "median_gap": float(np.median(gap[ok])),
        "p75_gap": float(np.percentile(gap[ok], 75)),
        "p90_gap": float(np.percentile(gap[ok], 90)),
        "p95_gap": float(np.percentile(gap[ok], 95)),
        "max_gap": float(np.max(gap[ok])),
        "min_gap": float(np.min(gap[ok])),
        "ours_iterations_median": float(np.median(np.asarray(ours.iterations))),
        "slsqp_iterations_median": float(np.median(ref.iterations)),
    }


_SOLVER = None  # a pool worker's `slsqp_reference.ReferenceSolver`, made by `_warm_worker`


def _solve_timed(solver, basis, boundary) -> float:
    t0 = time.perf_counter()
    solver(basis, boundary)
    return time.perf_counter() - t0


def _warm_worker(make, warm, ready):
    """Pool initializer: this worker's solver, warmed up on one condition (its compiles)."""
    global _SOLVER
    from slsqp_reference import ReferenceSolver

    _SOLVER = ReferenceSolver(*make)
    _solve_timed(_SOLVER, *warm)
    with ready.get_lock():
        ready.value += 1


def _baseline_worker(part) -> float:
    return _solve_timed(_SOLVER, *part)


def _slices(tree, parts: int):
    n = jax.tree_util.tree_leaves(tree)[0].shape[0]
    bounds = np.linspace(0, n, parts + 1).astype(int)
    return [jax.tree_util.tree_map(lambda a, lo=lo, hi=hi: a[lo:hi], tree)
            for lo, hi in itertools.pairwise(bounds)]  # fmt: skip


# Math libraries single-threaded in the pool's workers: with their default (a thread per core),
# two workers' OpenBLAS threads contend for 2 cores and the pool ran ~2x slower than one process
# (2 CPU cores, 32 conditions: analytic SLSQP 0.068 s per condition pooled against
# 0.034 sequential; single-threaded 0.0122 against 0.0241), as a user tuning a pool sets them.
WORKER_THREADS_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def _worker_environment():
    """``WORKER_THREADS_ENV`` (where not set already) for the processes started inside."""
    added = {k: v for k, v in WORKER_THREADS_ENV.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            del os.environ[k]


def baseline(cfg, robot, dyn, db, conds, n: int, workers: int) -> dict:
    """SLSQP per condition (C MuJoCo FD gradients; analytic JAX gradients), sequential and pooled.

    Each mode times solves only, as ours is timed after compilation: the sequential solver and
    every pool worker's own are warmed up on one condition first (imports, JAX compiles; the
    solver compiles nothing after that, `slsqp_reference.ReferenceSolver`); the workers' math
    libraries run single-threaded (``WORKER_THREADS_ENV``). Seconds are for
    ``n`` conditions; ``per_condition_s`` scales to any count.
    """
    from slsqp_reference import ReferenceSolver

    grid, basis, boundary = generation1_problems(cfg, robot, dyn, db, conds, n)
    warm = jax.tree_util.tree_map(lambda a: a[:1], (basis, boundary))
    out = {}
    ctx = mp.get_context("spawn")
    for gradient in ("mujoco-fd", "jax"):
        make = (robot, grid, cfg.compiler, gradient)
        solver = ReferenceSolver(*make)
        _solve_timed(solver, *warm)
        seq = _solve_timed(solver, basis, boundary)
        ready = ctx.Value("i", 0)
        # Every worker warms up in its initializer; the clock starts once all have (a warm-up
        # by `map` may hand every warm-up task to one worker and time the other one's start).
        with (
            _worker_environment(),
            ctx.Pool(workers, initializer=_warm_worker, initargs=(make, warm, ready)) as pool,
        ):
            while ready.value < workers:
                time.sleep(0.05)
            t0 = time.perf_counter()
            pool.map(_baseline_worker, _slices((basis, boundary), workers), chunksize=1)
            pooled = time.perf_counter() - t0
        out[gradient] = {
            "conditions_timed": n,
            "sequential_per_condition_s": seq / n,
            "pool_per_condition_s": pooled / n,
            "workers": workers,
        }
    return out


def first_generation_times(
    config: str,
    conditions: int,
    overrides: list[str],
    demos_from_file: bool = False,
    warm_runs: int = 3,
) -> dict:
    """What a user waits for: ``evojax-motion train`` of one generation in a fresh process, from
    launching it to the end of generation 1 (imports, demonstrations, conditions, compile, the
    generation; ``process_s`` adds the run folder's last files and the exit), first with an
    empty compilation cache, then ``warm_runs`` times with the cache the first run filled (this
    machine is noisy: ``warm_median_s`` is their median). Breakdown: the run's
    ``summary.json`` and ``metrics.jsonl``. ``demos_from_file``: as a user with recorded
    demonstrations: the config's demonstrations are first written to a file (``evojax-motion
    demos``, not timed) and the runs read them (``demos_file``) instead of synthesising them."""
    with tempfile.TemporaryDirectory() as tmp:
        out = {}
        env = dict(os.environ, EVOJAX_MOTION_JAX_CACHE=str(Path(tmp) / "cache"))
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
        if demos_from_file:
            demos = Path(tmp) / "demos.npz"
            cmd = [sys.executable, "-m", "evojax_motion.cli", "demos", "--config", config,
                   "--out", str(demos), "--quiet", *(f"--set={o}" for o in overrides)]  # fmt: skip
            subprocess.run(cmd, capture_output=True, text=True, check=True, env=env, cwd=ROOT)
            overrides = [*overrides, f"demos_file={demos}"]
            shutil.rmtree(Path(tmp) / "cache", ignore_errors=True)  # the runs start cold
        warm = ["warm_cache", *(f"warm_cache_{i}" for i in range(2, warm_runs + 1))]
        for label in ["cold", *warm]:
            run = Path(tmp) / label
            cmd = [sys.executable, "-m", "evojax_motion.cli", "train", config, "--out", str(run),
                   "--quiet", "--set", "evolution.generations=1", "--set", "train.plots=false",
                   "--set", f"evolution.conditions={conditions}"]  # fmt: skip
            cmd += [f"--set={o}" for o in overrides]
            launched = time.time()
            subprocess.run(cmd, capture_output=True, text=True, check=True, env=env, cwd=ROOT)
            process_s = time.time() - launched
            summary = json.loads((run / "summary.json").read_text())
            metrics = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
            out[label] = {
                # from launching the process to the end of generation 1 (the metrics row's clock)
                "to_first_generation_s": metrics[0]["finished_at"] - launched,
                "process_s": process_s,  # to its exit: + the run folder's last files
                "demos_s": summary["demos_seconds"],
                "conditions_s": summary["conditions_seconds"],
                # the part of the compile not hidden behind the demonstrations and conditions
                "compile_wait_s": summary["compile_seconds"],
                "first_generation_s": metrics[0]["seconds"],
                "run_total_s": summary["total_seconds"],
            }
            print(json.dumps({label: out[label]}))
        out["warm_median_s"] = float(np.median([out[k]["to_first_generation_s"] for k in warm]))
        return out


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        f"Machine: {m['device_kind']} ({m['platform']}, {machine_label(m)}), jax {m['jax']}, "
        f"{m['date']}. Command: `{m['command']}`",
    ]
    if m.get("xla_flags"):
        lines[0] += f" XLA_FLAGS: `{m['xla_flags']}`."
    if result.get("one_program"):
        lines[0] += (" The step compiled as one XLA program "
                     "(`evolution.step.make_generation_step`), "
                     "not as `train`'s two.")  # fmt: skip
    if result["sweep"]:
        lines += [
            "",
            "| conditions | T | compile s | s / generation | generations / s | peak MiB | "
            "neighbour search |",
            "|---:|---:|---:|---:|---:|---:|---|",
        ]
    for r in result["sweep"]:
        lists = r.get("exact_lists")
        search = r.get("search", "whole database")
        if lists:  # the timed generations: 2.. (1 fills the empty slots)
            search += ", exact " + " / ".join(f"{100 * x:.1f} %" for x in lists[1:] or lists)
        lines.append(
            f"| {r['conditions']} | {r['samples']} | {r['compile_s']:.1f} | "
            f"{r['seconds_per_generation']:.4g} | {r['generations_per_s']:.3g} | "
            f"{r['peak_memory_bytes'] / 2**20:.0f} | {search} |"
        )
    if "gap" in result:
        g = result["gap"]
        lines += ["", f"Optimality gap vs float64 SLSQP ({g['compared']} conditions): median "
                  f"{100 * g['median_gap']:.4f} %, p95 {100 * g['p95_gap']:.4f} %, "
                  f"max {100 * g['max_gap']:.3f} %"]  # fmt: skip
    if "baseline" in result:
        lines += ["", "| baseline (SLSQP per condition) | s / generation | ours / baseline |",
                  "|---|---:|---:|"]  # fmt: skip
        for name, r in result["baseline_ratios"].items():
            lines.append(f"| {name} | {r['seconds_per_generation']:.4g} | {r['speedup']:.1f}x |")
    if "first_generation" in result:
        source = "read from a file" if result.get("demos_from_file") else "synthesised"
        lines += ["", f"Time to first generation, demonstrations {source}:", "",
                  "| `train`, one generation, fresh process | to first generation s | "
                  "demonstrations s | conditions s | compile wait s | generation s |",
                  "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
        for k, v in result["first_generation"].items():
            if not isinstance(v, dict):
                continue
            lines.append(
                f"| {k.replace('_', ' ')} | {v['to_first_generation_s']:.1f} | {v['demos_s']:.1f} "
                f"| {v['conditions_s']:.1f} | {v['compile_wait_s']:.1f} | "
                f"{v['first_generation_s']:.2f} |"
            )
        if "warm_median_s" in result["first_generation"]:
            median = result["first_generation"]["warm_median_s"]
            lines += ["", f"Median of the warm runs: {median:.1f} s to first generation."]
    return "\n".join(lines)


def main(argv=None) -> None:
    # No TF32 on GPUs for anything traced outside the package's entry points (`precision`); set
    # here, not on import, so that importing `build` changes no caller's configuration.
    jax.config.update("jax_default_matmul_precision", "highest")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--conditions", type=int, default=300, help="paper scale: 300")
    p.add_argument(
        "--sweep-conditions", default="", help="e.g. 30,100,1000 (default: --conditions)"
    )
    p.add_argument("--sweep-samples", default="", help="e.g. 50,200: extra runs at other T")
    p.add_argument("--generations", type=int, default=4, help="timed generations per point")
    p.add_argument("--gap-conditions", type=int, default=100, help="0 = skip the gap")
    p.add_argument("--baseline-conditions", type=int, default=32, help="0 = skip the baseline")
    p.add_argument("--workers", type=int, default=os.cpu_count())
    p.add_argument("--no-first-generation", action="store_true")
    p.add_argument("--warm-runs", type=int, default=3, help="first generation, warm cache")
    p.add_argument(
        "--first-generation-only", action="store_true", help="only the time to first generation"
    )
    p.add_argument(
        "--demos-from-file",
        action="store_true",
        help="time to first generation reading the demonstrations from a file (recorded data)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. compiler.method=bfgs (repeatable)",
    )
    p.add_argument(
        "--whole-search",
        action="store_true",
        help="search each condition's neighbours in the whole database at every size "
        "(default: candidate lists from evolution.SEARCH_CANDIDATES_MIN_CONDITIONS conditions)",
    )
    p.add_argument(
        "--one-program",
        action="store_true",
        help="time the step compiled as one XLA program (evolution.make_generation_step) "
        "instead of train's two (prepare, finish)",
    )
    p.add_argument("--tag", default="", help="suffix of the JSON name (default: platform)")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    if args.warm_runs < 1:
        p.error(f"--warm-runs: expected an integer >= 1, got {args.warm_runs}")
    result = {"machine": machine_info(), "config": args.config, "overrides": args.set,
              "sweep": [], "demos_from_file": args.demos_from_file,
              "one_program": args.one_program}  # fmt: skip
    if args.first_generation_only:
        result["first_generation"] = first_generation_times(
            args.config, args.conditions, args.set, args.demos_from_file, args.warm_runs
        )
        _write(result, args)
        return

    cfg = load_config(args.config, args.set)
    if args.whole_search:
        evolution.SEARCH_CANDIDATES_MIN_CONDITIONS = sys.maxsize
    counts = [int(x) for x in args.sweep_conditions.split(",") if x] or [args.conditions]
    paper = None
    for c in counts:
        state = build(cfg, c)
        r = time_generations(*state, args.generations, args.one_program)
        result["sweep"].append(r)
        print(json.dumps({k: v for k, v in r.items() if k not in ("seconds", "db_cost_mean")}))
        if c == args.conditions or paper is None:
            paper = state
    for t in [int(x) for x in args.sweep_samples.split(",") if x]:
        cfg_t = config_from_dict(config_to_dict(cfg), [f"demos.samples={t}"])
        r = time_generations(*build(cfg_t, args.conditions), args.generations, args.one_program)
        result["sweep"].append(r)
        print(json.dumps({k: v for k, v in r.items() if k not in ("seconds", "db_cost_mean")}))
    ours_s = next(
        (r["seconds_per_generation"] for r in result["sweep"]
         if r["conditions"] == args.conditions and r["samples"] == cfg.demos.samples),
        result["sweep"][0]["seconds_per_generation"],
    )  # fmt: skip
    m = int(paper[4].target.shape[0])
    if args.gap_conditions:
        result["gap"] = optimality_gap(*paper, min(args.gap_conditions, m))
        print(json.dumps(result["gap"]))
    if args.baseline_conditions:
        result["baseline"] = baseline(*paper, min(args.baseline_conditions, m), args.workers)
        ratios = {}
        for grad, r in result["baseline"].items():
            for mode in ("sequential", "pool"):
                per_gen = r[f"{mode}_per_condition_s"] * m
                ratios[f"{grad}, {mode}"] = {"seconds_per_generation": per_gen,
                                             "speedup": per_gen / ours_s}  # fmt: skip
        result["baseline_ratios"] = ratios
        print(json.dumps(ratios))
    if not args.no_first_generation:
        result["first_generation"] = first_generation_times(
            args.config, args.conditions, args.set, args.demos_from_file, args.warm_runs
        )
    _write(result, args)


def _write(result: dict, args) -> None:
    tag = args.tag or result["machine"]["platform"]
    stem = Path(args.out_dir) / f"generations_per_sec_{tag}"
    write_result(stem, result, markdown(result))
    print(f"\nwritten: {stem}.json")


if __name__ == "__main__":
    main()
