"""How close the optimisation compiler (paper sec. 2.2, eq. 3-5) gets to a float64 SLSQP solve.

The problems are generation 1 of a config's run (``--config``, default the paper's
``configs/catch_ball.yaml``: its demonstrations, condition set and bases, the first
``--conditions`` of them). Each optimiser variant runs on the same bases and boundaries as the
float64 SciPy SLSQP reference (``slsqp_reference``, same reduced problem, same start; solved with
the config's compiler settings). The gap of a condition is ``(ours - ref) / ref`` on the float64
eq. 5 cost of the returned trajectories (negative: we found a lower minimum, allowed). The
variant ``shipped`` is the config's own compiler; its figures are also under the report's key
``shipped``: ``gap.median``, ``gap.p95``, ``frac_above_1pct`` (gap > 1 %),
``frac_within_0.1pct`` (gap <= 0.1 %),
``frac_better_than_reference`` (gap < -0.1 %), ``outside_limits`` (motions outside the joint
limits) and, against the interpolation compiler's answer on the same basis and BCs (eq. 1-2),
``above_interpolation`` (cost more than 0.1 % above it). Velocity and torque limits are left
out, as in the reference. Writes ``benchmarks/results/optimality_<platform>.json`` and prints a
markdown table. Compile and run times are measured separately (best of ``--repeats`` calls, no
compile).

    python benchmarks/optimality.py --variants shipped --conditions 300   # the paper's problems
    python benchmarks/optimality.py --variants shipped,shipped-4starts --conditions 300 \
        --repeats 5 --evolution 10   # and 10 generations of the evolution with each
    python benchmarks/optimality.py --variants newton,adam-200 --conditions 300
    python benchmarks/optimality.py --synthetic  # without evojax_motion.demonstrations.synthetic
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # generations_per_sec's own imports

from dynamics_throughput import machine_info

from benchmarks.slsqp_reference import solve_reference, torque_costs_f64
from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import Boundary, compile_interpolation
from evojax_motion.compiler.optimisation import make_optimisation_compiler
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.database import make_database
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.compiler import BasisSettings, OptimSettings

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
# Optimiser variants compared (name -> OptimSettings overrides); the default is "newton".
VARIANTS: dict[str, dict | None] = {
    "shipped": None,  # the config's compiler settings
    # the config's settings with 4 (8, 16) starts, all but one random at 0.3 rad RMS
    "shipped-4starts": {"n_starts": 4, "start_scale": 0.3},
    "shipped-8starts": {"n_starts": 8, "start_scale": 0.3},
    "shipped-16starts": {"n_starts": 16, "start_scale": 0.3},
    # 4 starts at the spread that was the default before 0.3
    "shipped-4starts-wide": {"n_starts": 4, "start_scale": 1.0},
    "newton": {},
    # configs/catch_ball.yaml: eq. 5 integrated on every 4th sample, 2 free directions per joint
    "newton-s4f2": {"search_stride": 4, "max_free_per_joint": 2},
    "newton-2starts": {"n_starts": 2},
    "newton-4starts": {"n_starts": 4},
    "newton-h2": {"hessian_every": 2, "max_iters": 30},
    "bfgs": {"method": "bfgs", "max_iters": 100},
    "bfgs-4starts": {"method": "bfgs", "max_iters": 100, "n_starts": 4},
    "adam-200": {"method": "adam", "max_iters": 200, "learning_rate": 0.1},
    "adam-1000": {"method": "adam", "max_iters": 1000, "learning_rate": 0.03},
    "lbfgs-60": {"method": "lbfgs", "max_iters": 60},
}


def synthetic_database(robot, dyn, n, t, key):
    """Fallback demonstrations: minimum-jerk rest-to-rest motions to random in-range postures."""
    k1, k2 = jax.random.split(key)
    lo, hi = np.asarray(robot.lower), np.asarray(robot.upper)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    final = mid + 0.6 * half * np.asarray(jax.random.uniform(k1, (n, len(lo)), minval=-1, maxval=1))
    s = np.linspace(0.0, 1.0, t)[None, :, None]
    shape = s**3 * (10 - 15 * s + 6 * s**2)
    bump = (s * (1 - s)) ** 2 * np.asarray(jax.random.normal(k2, (n, 1, len(lo)))) * 0.5
    rest = np.asarray(robot.rest)[None, None]
    q = np.clip(rest + (final[:, None] - rest) * shape + bump, lo, hi).astype(np.float32)
    pos = np.asarray(jax.vmap(lambda qq: dyn.site_pose(qq)[0])(jnp.asarray(q[:, -1])))
    duration = np.full(n, 1.0, np.float32)
    return make_database(q, duration, pos)


def synthetic_conditions(db, robot, m, basis_settings, key):
    """Fallback conditions: a demonstration's final posture perturbed, from rest, at rest."""
    idx = np.asarray(jax.random.choice(key, db.q.shape[0], (m,), replace=False))
    noise = 0.05 * np.asarray(jax.random.normal(jax.random.fold_in(key, 1), (m, db.q.shape[2])))
    lo, hi = np.asarray(robot.lower) + 0.05, np.asarray(robot.upper) - 0.05
    qf = np.clip(db.q[idx, -1] + noise, lo, hi).astype(np.float32)
    z = np.zeros_like(qf)
    rest = np.broadcast_to(np.asarray(robot.rest, np.float32), qf.shape)
    return db.condition[idx], Boundary(rest, qf, z, z, db.duration[idx])


def build_problem(args, cfg):
    if not args.synthetic:  # generation 1 of the config's run
        from benchmarks.generations_per_sec import build, generation1_problems

        cfg, robot, dyn, db, conds = build(cfg, args.conditions)
        grid, basis, boundary = generation1_problems(cfg, robot, dyn, db, conds, args.conditions)
        as_jnp = functools.partial(jax.tree_util.tree_map, jnp.asarray)
        return robot, dyn, grid, as_jnp(basis), as_jnp(boundary)
    robot = load_robot(args.robot)
    dyn = make_dynamics(robot, "rnea")
    grid = make_time_grid(args.samples)
    bs = BasisSettings()
    key = jax.random.key(args.seed)
    k_demo, k_cond = jax.random.split(key)
    db = synthetic_database(robot, dyn, args.demos, args.samples, k_demo)
    targets, boundary = synthetic_conditions(db, robot, args.conditions, bs, k_cond)
    nb = select_neighbours(
        jnp.asarray(db.condition), jnp.asarray(db.valid), jnp.asarray(targets),
        bs.neighbours, bs.radius, bs.w_pos,
    )  # fmt: skip
    basis = pca_basis(jnp.asarray(db.q), jnp.asarray(db.duration), nb, OptimSettings().n_components)
    boundary = jax.tree_util.tree_map(jnp.asarray, boundary)
    return robot, dyn, grid, basis, boundary


def stats(gap):
    return {
        "median": float(np.median(gap)),
        "p95": float(np.percentile(gap, 95)),
        "max": float(np.max(gap)),
        "min": float(np.min(gap)),
        "frac_above_1pct": float(np.mean(gap > 0.01)),
        "frac_within_0.1pct": float(np.mean(gap <= 1e-3)),  # cost <= SLSQP's + 0.1 %
    }


def run_variant(settings, robot, dyn, grid, basis, boundary, ref_cost, interp_cost, repeats=1):
    compile_fn = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, settings)
    t0 = time.perf_counter()
    compiled = compile_fn.lower(basis, boundary).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(basis, boundary))
        times.append(time.perf_counter() - t0)
    run_s = min(times)
    ours = torque_costs_f64(robot, grid, out.q, boundary.duration)
    gap = (ours - ref_cost) / ref_cost
    it = np.asarray(out.iterations)
    q = np.asarray(out.q, np.float64)
    outside = np.any((q < np.asarray(robot.lower)) | (q > np.asarray(robot.upper)), axis=(1, 2))
    return {
        "settings": {
            k: v
            for k, v in dataclasses.asdict(settings).items()
            if v != getattr(OptimSettings(), k)
        },
        "gap": stats(gap),
        "frac_better_than_reference": float(np.mean(gap < -1e-3)),
        "outside_limits": int(outside.sum()),
        "above_interpolation": int(np.sum(ours > 1.001 * interp_cost)),
        "iterations": {"median": float(np.median(it)), "max": int(it.max())},
        "converged": float(np.mean(np.asarray(out.converged))),
        "within_limits": float(np.mean(np.asarray(out.within_limits))),
        "finite": float(np.mean(np.asarray(out.finite))),
        "bc_residual_max": float(np.nanmax(np.asarray(out.bc_residual))),
        "compile_s": compile_s,
        "run_s": run_s,
        "gaps": gap.tolist(),
    }


def variant_settings(cfg, name: str) -> OptimSettings:
    """The compiler settings of variant ``name``: ``shipped*`` ones are ``cfg``'s with their
    overrides, the others `OptimSettings` defaults with theirs."""
    overrides = VARIANTS[name] or {}
    if name.startswith("shipped"):
        return dataclasses.replace(cfg.compiler, **overrides)
    return OptimSettings(**overrides)


def evolution_runs(report: dict, cfg, names: list, conditions: int, generations: int) -> None:
    """``generations`` generations of ``cfg``'s evolution (``conditions`` conditions, as `train`
    runs them) with the compiler of each ``shipped*`` variant of ``names``, one after another
    in this process: ``report["variants"][name]["evolution"]`` gets the seconds per generation
    (median after the first) and the database's mean cost after each generation."""
    from benchmarks.generations_per_sec import build, time_generations

    cfg, robot, dyn, db, conds = build(cfg, conditions)  # the variants differ in the compiler only
    for name in names:
        if not name.startswith("shipped"):
            continue
        cfg_v = dataclasses.replace(cfg, compiler=variant_settings(cfg, name))
        run = time_generations(cfg_v, robot, dyn, db, conds, generations)
        report["variants"][name]["evolution"] = {
            k: run[k] for k in ("generations_per_s", "seconds_per_generation", "db_cost_mean")
        }
        print(
            f"{name}: {generations} generations, {run['seconds_per_generation']:.3f} s each, "
            f"database cost {run['db_cost_mean'][0]:.4f} -> {run['db_cost_mean'][-1]:.4f}",
            flush=True,
        )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--conditions", type=int, default=100)
    p.add_argument("--samples", type=int, default=100, help="T")
    p.add_argument("--demos", type=int, default=311)
    p.add_argument("--robot", default="mahru_arm")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--synthetic", action="store_true", help="fallback demonstrations")
    p.add_argument(
        "--fd-subset",
        type=int,
        default=5,
        help="also solve this many conditions with mujoco mj_inverse + FD gradients",
    )
    p.add_argument("--out", default=None, help="JSON path (default results/optimality_<plat>.json)")
    p.add_argument(
        "--config", default="configs/catch_ball.yaml", help="relative: to the repository"
    )
    p.add_argument("--repeats", type=int, default=1, help="timed calls per variant (best kept)")
    p.add_argument(
        "--evolution",
        type=int,
        default=0,
        help="also run this many generations of the config's evolution with each shipped* "
        "variant's compiler (--conditions conditions): seconds per generation, database cost",
    )
    args = p.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        p.error(f"--variants: unknown {unknown}; expected some of {sorted(VARIANTS)}")

    from evojax_motion.settings import load_config

    cfg = load_config(ROOT / args.config, [])
    plat = jax.devices()[0].platform
    t0 = time.perf_counter()
    robot, dyn, grid, basis, boundary = build_problem(args, cfg)
    setup_s = time.perf_counter() - t0
    print(
        f"problem: {args.conditions} conditions, T={args.samples}, setup {setup_s:.1f} s",
        flush=True,
    )

    t0 = time.perf_counter()
    ref = solve_reference(robot, grid, basis, boundary, cfg.compiler, gradient="jax")
    ref_s = time.perf_counter() - t0
    interp = jax.jit(lambda b, bc: compile_interpolation(b, bc, grid))(basis, boundary)
    interp_cost = torque_costs_f64(robot, grid, interp.q, boundary.duration)
    report = {
        "config": args.config,
        "platform": plat,
        "device": str(jax.devices()[0]),
        "machine": machine_info(),
        "conditions": args.conditions,
        "samples": args.samples,
        "synthetic": args.synthetic,
        "reference": {
            "solver": "scipy SLSQP, float64, JAX RNEA gradient",
            "success": float(ref.success.mean()),
            "iterations_median": float(np.median(ref.iterations)),
            "wall_s_per_condition_median": float(np.median(ref.wall_s)),
            "total_s": ref_s,
            "max_violation": float(ref.max_violation.max()),
        },
        "variants": {},
    }
    print(
        f"SLSQP (jax grad): {ref_s:.1f} s, median {np.median(ref.iterations):.0f} iterations, "
        f"{np.median(ref.wall_s) * 1e3:.0f} ms per condition",
        flush=True,
    )
    if args.fd_subset > 0:
        sub = slice(0, args.fd_subset)
        take = jax.tree_util.tree_map(lambda a: a[sub], (basis, boundary))
        fd = solve_reference(robot, grid, *take, cfg.compiler, gradient="mujoco-fd")
        agree = (fd.cost - ref.cost[sub]) / ref.cost[sub]
        report["reference"]["mujoco_fd"] = {
            "conditions": args.fd_subset,
            "wall_s_per_condition_median": float(np.median(fd.wall_s)),
            "iterations_median": float(np.median(fd.iterations)),
            "rel_cost_diff_vs_jax_grad_max": float(np.max(np.abs(agree))),
        }
        print(
            f"SLSQP (mj_inverse, FD grad) on {args.fd_subset}: "
            f"{np.median(fd.wall_s) * 1e3:.0f} ms per condition, "
            f"max |cost diff| {np.max(np.abs(agree)):.2e}",
            flush=True,
        )

    out = Path(args.out) if args.out else RESULTS / f"optimality_{plat}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in names:
        settings = variant_settings(cfg, name)
        res = run_variant(
            settings, robot, dyn, grid, basis, boundary, ref.cost, interp_cost, args.repeats
        )
        report["variants"][name] = res
        if name == "shipped":
            report["shipped"] = {
                "gap": {"median": res["gap"]["median"], "p95": res["gap"]["p95"]},
                **{k: res[k] for k in ("outside_limits", "frac_better_than_reference")},
                "frac_above_1pct": res["gap"]["frac_above_1pct"],
                "frac_within_0.1pct": res["gap"]["frac_within_0.1pct"],
                "above_interpolation": res["above_interpolation"],
                "run_s": res["run_s"],
            }
        g = res["gap"]
        print(
            f"{name}: median {g['median']:.3%} p95 {g['p95']:.3%} max {g['max']:.2%}, "
            f"run {res['run_s']:.2f} s, compile {res['compile_s']:.1f} s",
            flush=True,
        )
        out.write_text(json.dumps(report, indent=1))  # after every variant: partial runs count
    if args.evolution and not args.synthetic:
        evolution_runs(report, cfg, names, args.conditions, args.evolution)
        out.write_text(json.dumps(report, indent=1))
    print()
    print(
        "| variant | median gap | p95 gap | max gap | > 1 % | <= 0.1 % | iterations (median) | "
        "within limits | run [s] | compile [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, res in report["variants"].items():
        g = res["gap"]
        print(
            f"| {name} | {g['median']:.4%} | {g['p95']:.3%} | {g['max']:.2%} | "
            f"{g['frac_above_1pct']:.1%} | {g['frac_within_0.1pct']:.1%} | "
            f"{res['iterations']['median']:.0f} | "
            f"{res['within_limits']:.0%} | {res['run_s']:.2f} | {res['compile_s']:.1f} |"
        )
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
