"""Catch success in MuJoCo physics of online-planned catches (paper sec. 4, docs/simulation.md).

Thrower model (explicit PRNG key ``--seed``): a person stands 2-4 m from the robot's base (the
world origin), at an azimuth within +-30 deg of the aim point's, releases the ball 1-2 m above
the floor, and the ball flies 0.5-1.2 s in vacuum to an aim point: a valid human demonstration's
condition (the region the databases were built on) moved by up to ``AIM_JITTER`` per axis. The
release velocity follows from the ballistic closed form (gravity of the robot model). The same
throws go to every database.

Each throw is planned online (`online.catching.make_catcher`, one throw per call so that the
planning time per throw is the latency; wall time after the compile) and executed by the
tracking controller of `simulate` with the ball in flight. Planning is timed twice: every throw
back to back (``planning_s``: a planner fed one ball estimate after the other), and each again
right after the previous throw's simulation (``planning_after_idle_s``: the program's threads
idle for the ~0.1-1 s of physics; on 2 CPU cores this added ~1 ms a call,
``catch_success_cpu.json``). The second plan
must give the same motion (checked). Per database (human rows only,
`motion.database.humans_only`; the learned one of ``--train-dir``):

- reachable throws: the ball's path crosses the reachable set (`CatchPlan.passes_region`);
  unreachable ones are counted apart; infeasible plans: reachable, but no catch in time or no
  usable motion (`CatchPlan.feasible`, `OnlineResult.ok`); of them too fast: no catch point
  leaves the arm the time its velocity and torque limits need (`OnlineResult.within_time`);
- success rate: caught (the physical criterion of `simulate`) / reachable throws;
- eq. 5 cost of the planned motion (the paper's Fig. 5 quantity, 0.5 int |tau|^2 dt), mean and
  median over the planned throws; tracking error (RMS/max, rad and mm at the hand); fraction of
  simulated steps with some joint at its torque limit; planning time p50/p99 (both ways);
- on the first ``--optimise-subset`` planned throws, the optimisation compiler (eq. 3-5) on the
  same basis and boundary conditions as the online motion, the run's compiler settings: its cost
  and the ratio online / optimised.

    python benchmarks/catch_success.py --train-dir runs/paper --throws 500 --tag cpu
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT))

from dynamics_throughput import machine_info  # noqa: E402
from result_files import latency_ms, machine_line, write_result  # noqa: E402

from evojax_motion.linalg.precision import exact_matmuls  # noqa: E402
from evojax_motion.motion.database import Database, humans_only  # noqa: E402
from evojax_motion.online.catching import make_catcher  # noqa: E402
from evojax_motion.online.generation import build_problem, online_database  # noqa: E402
from evojax_motion.online.limits import joint_limits_f32  # noqa: E402
from evojax_motion.online.simulate import (  # noqa: E402
    Ball,
    Plan,
    Summary,
    simulate,
    summarise,
)
from evojax_motion.report.run_folder import CATCH_FILE  # noqa: E402
from evojax_motion.run.atomic import atomic_write_text  # noqa: E402
from evojax_motion.settings.online import CatchSettings, SimSettings  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
THROWER = {
    "distance_m": (2.0, 4.0),
    "azimuth_deg": (-30.0, 30.0),
    "release_height_m": (1.0, 2.0),
    "flight_s": (0.5, 1.2),
}
AIM_JITTER = 0.05  # [m] per axis around a demonstration's condition


def sample_throws(conditions: np.ndarray, gravity, n: int, key) -> tuple[np.ndarray, ...]:
    """``n`` throws at ``conditions (M, 3)`` (module docstring).

    Returns ``p0, v0, aim (n, 3)`` [m, m/s, m] and ``flight (n,)`` [s]."""
    k = jax.random.split(key, 6)
    u = [np.asarray(jax.random.uniform(ki, (n,)), np.float64) for ki in k[:4]]
    pick = np.asarray(jax.random.randint(k[4], (n,), 0, conditions.shape[0]))
    jitter = np.asarray(jax.random.uniform(k[5], (n, 3), minval=-1.0, maxval=1.0), np.float64)
    aim = np.asarray(conditions, np.float64)[pick] + AIM_JITTER * jitter

    def lerp(r, x):
        return r[0] + (r[1] - r[0]) * x

    dist = lerp(THROWER["distance_m"], u[0])
    az = np.arctan2(aim[:, 1], aim[:, 0]) + np.radians(lerp(THROWER["azimuth_deg"], u[1]))
    height = lerp(THROWER["release_height_m"], u[2])
    p0 = np.stack([dist * np.cos(az), dist * np.sin(az), height], 1)
    flight = lerp(THROWER["flight_s"], u[3])
    g = np.asarray(gravity, np.float64)
    v0 = (aim - p0 - 0.5 * g * flight[:, None] ** 2) / flight[:, None]
    return p0.astype(np.float32), v0.astype(np.float32), aim, flight


def _pct(x, ps=(50, 99)) -> dict:
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return {f"p{p}": None for p in ps}
    return {f"p{p}": float(np.percentile(x, p)) for p in ps}


class Programs(NamedTuple):
    """The jitted functions of every database's evaluation, made once (`make_programs`): the
    databases have the same shapes, so the first one's compilations serve the others."""

    catcher: Any  # `online.catching.make_catcher`'s
    problem: Any  # `online.generation.build_problem`, jitted
    optimiser: Any  # `compiler.optimisation.make_optimisation_compiler`'s, or None


def make_programs(model, catch: CatchSettings, compiler) -> Programs:
    """`Programs` of a loaded run (``model``: `online.generation.OnlineModel`); ``compiler``:
    `config.CompilerSettings` of the optimisation reference (None: none)."""
    from evojax_motion.compiler.optimisation import make_optimisation_compiler

    robot = model.robot
    catcher = make_catcher(
        robot, model.dyn, model.grid, model.basis_settings, model.settings, catch
    )
    problem = jax.jit(exact_matmuls(build_problem), static_argnums=(0, 7, 8))
    optimiser = None
    if compiler is not None:
        optimiser = make_optimisation_compiler(
            model.dyn, model.grid, robot.lower, robot.upper, compiler
        )
    return Programs(catcher, problem, optimiser)


def evaluate_database(
    model, db: Database, p0, v0, programs: Programs, sim: SimSettings, n_optimise: int
) -> dict:
    """Plan, simulate and summarise the throws ``p0, v0 (N, 3)`` against ``db`` (numpy rows).

    ``model``: an `online.generation.OnlineModel` (robot, dyn, grid, basis_settings, settings);
    ``programs``: `make_programs`' (the optimisation reference skipped where it has none).
    ``compile_s``: the first plan's wall time (the catcher's compile where no database before
    this one compiled it).
    """
    robot = model.robot
    dev_db = online_database(db)
    catcher = programs.catcher
    q0 = np.asarray(robot.rest, np.float32)[None]
    t0 = time.perf_counter()
    jax.block_until_ready(catcher(dev_db, p0[:1], v0[:1], q0))
    compile_s = time.perf_counter() - t0
    n = p0.shape[0]

    def planned(i: int) -> tuple[Any, float]:  # throw i's catch and its wall time [s]
        t0 = time.perf_counter()
        out = jax.block_until_ready(catcher(dev_db, p0[i : i + 1], v0[i : i + 1], q0))
        return out, time.perf_counter() - t0

    # Latency two ways: back to back (a planner fed one ball estimate after the other), and
    # again right after the previous throw's physics (the planner idle meanwhile).
    plans = [planned(i) for i in range(n)]
    plan_s = np.array([t for _, t in plans])
    idle_s = np.zeros(n)
    rows: list[dict[str, Any]] = []
    for i in range(n):
        again, idle_s[i] = planned(i)
        plan, motion = jax.device_get(plans[i][0])
        np.testing.assert_array_equal(jax.device_get(again).motion.q, motion.q)
        row = {
            "reachable": bool(plan.passes_region[0]),
            "planned": bool(plan.feasible[0] and motion.ok[0]),
            "cost": float(motion.cost[0]),
            "catch_point": np.asarray(plan.catch_point[0]),
            "duration": float(motion.duration[0]),
            "in_time": bool(plan.feasible[0] and motion.within_time[0]),
            "palm_facing": float(plan.palm_facing[0]),
        }
        if row["planned"]:
            ball = Ball(p0[i].astype(np.float64), v0[i].astype(np.float64))
            t_end = max(float(motion.t[0, -1]), float(plan.catch_time[0])) + sim.hold
            rollout = simulate(robot, Plan(motion.t[0], motion.q[0], motion.qd[0], motion.qdd[0]),
                               sim, ball, t_end)  # fmt: skip
            row["sim"] = summarise(rollout, True)
        rows.append(row)
    reachable = np.array([r["reachable"] for r in rows])
    planned = np.array([r["planned"] for r in rows])
    in_time = np.array([r["in_time"] for r in rows])
    sims: list[Summary] = [r["sim"] for r in rows if r["planned"]]
    caught = sum(bool(s.caught) for s in sims)
    cost = np.array([r["cost"] for r in rows if r["planned"]])
    out = {
        "entries": int(np.asarray(db.valid).sum()),
        "throws": n,
        "reachable": int(reachable.sum()),
        "unreachable": int((~reachable).sum()),
        "infeasible_plans": int((reachable & ~planned).sum()),
        "infeasible_too_fast": int((reachable & ~planned & ~in_time).sum()),
        "planned": int(planned.sum()),
        "caught": int(caught),
        "success_rate": caught / max(int(reachable.sum()), 1),
        "success_rate_of_planned": caught / max(int(planned.sum()), 1),
        "cost": {"mean": float(cost.mean()) if cost.size else None,
                 "median": float(np.median(cost)) if cost.size else None},
        "tracking_rms_rad": _pct([s.tracking_rms for s in sims], (50, 95)),
        "tracking_max_rad": max((s.tracking_max for s in sims), default=None),
        "hand_rms_mm": _pct([s.hand_rms_mm for s in sims], (50, 95)),
        "hand_max_mm": max((s.hand_max_mm for s in sims), default=None),
        "at_torque_limit": float(np.mean([s.at_torque_limit for s in sims])) if sims else None,
        "closest_mm_missed": _pct([1e3 * s.closest_distance for s in sims if not s.caught],
                                  (50,)),
        "closest_mm_caught": _pct([1e3 * s.closest_distance for s in sims if s.caught],
                                  (50, 99)),
        "palm_facing": _pct([r["palm_facing"] for r in rows if r["planned"]], (1, 50)),
        "planning_s": _pct(plan_s),
        "planning_after_idle_s": _pct(idle_s),
        "compile_s": compile_s,
    }  # fmt: skip
    if programs.optimiser is not None and n_optimise > 0 and planned.any():
        out["optimised"] = optimise_subset(model, dev_db, rows, programs, n_optimise)
    return out


def optimise_subset(model, dev_db, rows, programs: Programs, k: int) -> dict:
    """The optimisation compiler on the first ``k`` planned throws' basis and BCs."""
    use = [r for r in rows if r["planned"]][:k]
    robot = model.robot
    lower, upper = (jnp.asarray(a) for a in joint_limits_f32(robot))
    points = jnp.asarray(np.stack([r["catch_point"] for r in use]), jnp.float32)
    dur = jnp.asarray([r["duration"] for r in use], jnp.float32)
    q0 = jnp.tile(jnp.asarray(robot.rest, jnp.float32)[None], (len(use), 1))
    basis, bc, _ = programs.problem(
        model.dyn, dev_db, points, dur, q0, lower, upper, model.basis_settings, model.settings
    )
    t0 = time.perf_counter()
    res = jax.device_get(jax.block_until_ready(exact_matmuls(programs.optimiser)(basis, bc)))
    wall = time.perf_counter() - t0
    finite = np.asarray(res.finite)
    c_opt = np.asarray(res.cost, np.float64)[finite]
    c_on = np.array([r["cost"] for r in use])[finite]
    ratio = c_on / c_opt
    return {
        "throws": len(use),
        "finite": int(finite.sum()),
        "cost": {"mean": float(c_opt.mean()), "median": float(np.median(c_opt))},
        "ratio_online_over_optimised": {**_pct(ratio, (5, 50, 95)), "mean": float(ratio.mean())},
        "wall_s_incl_compile": wall,
    }


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        machine_line(m),
        "",
        f"{result['throws']} throws, seed {result['seed']}; load average "
        f"{result['load_average']}; run `{result['run']}`.",
        "",
        "| database | entries | reachable | unreachable | infeasible (too fast) | caught | success "
        "| cost mean / median | hand RMS p50 / max mm | at torque limit | plan p50 / p99 ms "
        "| after idle p50 / p99 ms | optimised median (online / opt p50) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, d in result["databases"].items():
        opt = d.get("optimised")
        opt_txt = (
            f"{opt['cost']['median']:.4g} ({opt['ratio_online_over_optimised']['p50']:.3f}, "
            f"n={opt['finite']})"
            if opt
            else "-"
        )

        def f(x, fmt):
            return "-" if x is None else format(x, fmt)

        lines.append(
            f"| {name} | {d['entries']} | {d['reachable']} | {d['unreachable']} | "
            f"{d['infeasible_plans']} ({d['infeasible_too_fast']}) | {d['caught']} | "
            f"{d['success_rate']:.1%} | "
            f"{f(d['cost']['mean'], '.4g')} / {f(d['cost']['median'], '.4g')} | "
            f"{f(d['hand_rms_mm']['p50'], '.2f')} / {f(d['hand_max_mm'], '.1f')} | "
            f"{f(d['at_torque_limit'], '.2%')} | {latency_ms(d['planning_s'])} | "
            f"{latency_ms(d.get('planning_after_idle_s'))} | {opt_txt} |"
        )
    return "\n".join(lines)


def run(model, cfg, run_dir: str, throws: int, seed: int, n_optimise: int) -> dict:
    """The benchmark's result document for a loaded run (``model``, ``cfg``)."""
    catch, sim = CatchSettings(), SimSettings()
    humans = humans_only(model.db)
    conditions = np.asarray(humans.condition)[np.asarray(humans.valid)]
    gravity = np.asarray(model.robot.mj_model.opt.gravity)
    p0, v0, _, _ = sample_throws(conditions, gravity, throws, jax.random.key(seed))
    dbs = {"human-only": humans, "learned": model.db}
    result: dict[str, Any] = {
        "benchmark": "catch_success",
        "run": run_dir,
        "throws": throws,
        "seed": seed,
        "thrower": {**THROWER, "aim_jitter_m": AIM_JITTER},
        "catch_settings": dataclasses.asdict(catch),
        "sim_settings": dataclasses.asdict(sim),
        "load_average": [round(x, 2) for x in _loadavg()],
        "databases": {},
    }
    t0 = time.perf_counter()
    programs = make_programs(model, catch, cfg.compiler)
    for name, db in dbs.items():
        result["databases"][name] = evaluate_database(model, db, p0, v0, programs, sim, n_optimise)
        print(name, result["databases"][name]["success_rate"], flush=True)
    result["wall_s"] = time.perf_counter() - t0
    result["load_average_end"] = [round(x, 2) for x in _loadavg()]
    return result


def _loadavg() -> tuple[float, ...]:
    try:
        import os

        return os.getloadavg()
    except OSError:
        return (math.nan,) * 3


def main(argv=None) -> dict:
    from evojax_motion.online.generation import load_online_model
    from evojax_motion.run.cache import enable_compile_cache
    from evojax_motion.settings import load_config

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train-dir", required=True, help="finished training run (the learned db)")
    ap.add_argument("--throws", type=int, default=500, help="random throws (N)")
    ap.add_argument("--optimise-subset", type=int, default=20, help="throws for the optimiser")
    ap.add_argument("--seed", type=int, default=0, help="PRNG seed of the throws")
    ap.add_argument("--out-dir", default=str(RESULTS))
    ap.add_argument("--tag", default=None, help="machine kind tag of the file name")
    args = ap.parse_args(argv)
    if args.throws < 1 or args.optimise_subset < 0:
        ap.error("--throws: expected >= 1; --optimise-subset: expected >= 0")
    enable_compile_cache()
    run_dir = Path(args.train_dir)
    model = load_online_model(run_dir)
    cfg = load_config(run_dir / "config.yaml")
    result = run(model, cfg, str(run_dir), args.throws, args.seed, args.optimise_subset)
    result["machine"] = m = machine_info()
    write_result(
        Path(args.out_dir) / f"catch_success_{args.tag or m['platform']}", result, markdown(result)
    )
    # beside the run too, for its report (`evojax-motion report RUN`: catches per database)
    atomic_write_text(run_dir / CATCH_FILE, json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
