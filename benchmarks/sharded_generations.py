"""Generations per second of the sharded generation step on one device and on all visible devices.

One invocation, for each condition count of ``--sweep-conditions`` (default 10000,100000):

- builds generation 0 once (demonstrations, condition set, empty evolved slots:
  ``run.training.initial_state`` of ``--config`` with ``evolution.conditions`` set to the count);
- for each device count of ``--devices`` (default: 1 and all visible), in a fresh process (clean
  peak-memory counters; an out-of-memory point is recorded as such and the sweep goes on):
  compiles ``evolution.sharding.make_sharded_generation_step`` (with the robot's torque and
  velocity limits, as `train` builds it) ahead of time (``compile_s``), puts database and
  conditions on the devices once and feeds each generation's database to the next, as `train`
  does (`run.compilation.generation_inputs`), runs ``--generations`` generations and reports
  the median seconds of generations 2.. (generation 1 fills empty slots: different work) ->
  generations/s, the speed-up over one device and the parallel efficiency (speed-up /
  devices), and each device's peak memory;
- with ``--unsharded``, first the same for the unsharded step as `train` runs it on one device
  (`run.compilation.compile_generation_step`: two programs), the reference of every point's
  ``vs_unsharded`` (time ratio, databases compared);
- compares the databases that one and n devices give after generation 1 (the same input: a
  per-step comparison) and after the last generation (chained: rounding-level differences
  compound through survivor selection, docs/scaling.md): slots whose trajectory is bit-identical,
  the largest |dq| and relative cost difference where both kept the same survivor, and slots
  whose selection differs.

Usage (GPU host, all GPUs visible):
    python benchmarks/sharded_generations.py --tag h200x2
CPU check of the script (forced host devices share the cores: correctness, not speed):
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/sharded_generations.py \
        --config configs/tiny.yaml --sweep-conditions 12 --generations 2 --tag cpu2
The unsharded step on one GPU against the sharded step on 1, 2 and 4 (a 4-GPU host):
    python benchmarks/sharded_generations.py --sweep-conditions 100000 --devices 1,2,4 \
        --unsharded --generations 3 --tag h200x4
Writes ``benchmarks/results/sharded_generations_<tag>.json`` (+ ``.md``) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from result_files import shown_path  # noqa: E402

GIB = 2**30


# ----------------------------------------------------------------------- state files


def save_state(path: Path, db, conditions, n_human: int) -> None:
    from evojax_motion.evolution.conditions import conditions_to_tree

    tree = conditions_to_tree(conditions)
    arrays = {f"db.{k}": np.asarray(v) for k, v in db._asdict().items()}
    arrays.update({f"cond.{k}": v for k, v in tree.items() if k != "boundary"})
    arrays.update({f"cond.boundary.{k}": v for k, v in tree["boundary"].items()})
    np.savez(path, n_human=np.int64(n_human), **arrays)


def load_state(path: Path):
    from evojax_motion.evolution.conditions import conditions_from_tree
    from evojax_motion.motion.database import Database

    with np.load(path) as z:
        db = Database(**{k[3:]: z[k] for k in z.files if k.startswith("db.")})
        tree: dict = {"boundary": {}}
        for k in z.files:
            if k.startswith("cond.boundary."):
                tree["boundary"][k[len("cond.boundary.") :]] = z[k]
            elif k.startswith("cond."):
                tree[k[5:]] = z[k]
        return db, conditions_from_tree(tree), int(z["n_human"])


# ------------------------------------------------------------------- one point (child)


def compile_point(args, cfg, robot, dyn, db, cond, n_human: int):
    """The step a point times, compiled ahead of time for ``db`` and ``cond``: the sharded step
    on ``args.devices`` devices, or (``args.unsharded``) the unsharded step as `train` compiles
    it on one device."""
    from evojax_motion.evolution.sharding import make_sharded_generation_step
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run.compilation import compile_generation_step
    from evojax_motion.settings import config_from_dict, config_to_dict

    if args.unsharded:
        one = config_from_dict(config_to_dict(cfg), ["parallel.devices=1"])
        return compile_generation_step(one, robot, dyn, db, cond)
    step = make_sharded_generation_step(
        dyn, make_time_grid(db.q.shape[1]), robot.lower, robot.upper, n_human,
        cfg.basis, cfg.compiler, cfg.evolution, devices=args.devices,
        torque_limit=robot.torque_limit, velocity_limit=robot.velocity_limit,
    )  # fmt: skip
    return step.lower(db, cond, np.asarray(1, np.int32)).compile()


def save_db(path: Path, db) -> None:
    np.savez(path, **{k: np.asarray(v) for k, v in db._asdict().items()})


def run_point(args) -> None:
    """Child process: time the sharded step on ``args.devices`` devices (or the unsharded step);
    print one JSON line."""
    import jax

    from evojax_motion.evolution.sharding import padded_count, replicate
    from evojax_motion.evolution.step import with_search_candidates
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import load_config

    cfg = load_config(args.config, args.set)
    robot, dyn = make_robot_dynamics(cfg)
    db, cond, n_human = load_state(Path(args.child))
    cond = with_search_candidates(db, cond, cfg.basis)  # not saved: derived, as on a resume
    m = int(cond.target.shape[0])
    out: dict = {"conditions": m, "devices": args.devices, "samples": int(db.q.shape[1])}
    out["step"] = "unsharded" if args.unsharded else "sharded"
    out["m_pad"] = m if args.unsharded else padded_count(m, args.devices)
    try:
        t0 = time.perf_counter()
        compiled = compile_point(args, cfg, robot, dyn, db, cond, n_human)
        out["compile_s"] = time.perf_counter() - t0
        db, cond = replicate((db, cond), args.devices)  # once, as `train` does
        seconds, costs, all_stats = [], [], []
        for g in range(1, args.generations + 1):
            t0 = time.perf_counter()
            db, stats = compiled(db, cond, np.asarray(g, np.int32))
            db = jax.block_until_ready(db)
            seconds.append(time.perf_counter() - t0)
            costs.append(float(stats.db_cost_mean))
            all_stats.append({k: float(v) for k, v in stats._asdict().items()})
            if g == 1:  # the same input on every device count: a per-step comparison
                save_db(gen1_path(args.result), db)
        later = seconds[1:] or seconds
        out.update(
            seconds=seconds,
            first_generation_s=seconds[0],
            seconds_per_generation=float(np.median(later)),
            generations_per_s=1.0 / float(np.median(later)),
            db_cost_mean=costs,
            stats=all_stats,
        )
        save_db(Path(args.result), db)
    except Exception as e:  # out of memory at 100k conditions on one device, say
        out["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:300]}"
    out["peak_memory_bytes"] = [
        int((d.memory_stats() or {}).get("peak_bytes_in_use", -1))
        for d in jax.local_devices()[: args.devices]
    ]
    print(json.dumps(out))


# ---------------------------------------------------------------------------- parent


def gen1_path(result: str | Path) -> Path:
    return Path(str(result).removesuffix(".npz") + "_gen1.npz")


def compare(path_a: Path, path_b: Path, n_human: int) -> dict:
    """How the databases that two device counts reached differ (evolved slots only)."""
    with np.load(path_a) as a, np.load(path_b) as b:
        same = (a["valid"] == b["valid"]) & (a["generation"] == b["generation"])
        same, valid = same[n_human:], a["valid"][n_human:] & b["valid"][n_human:]
        both = same & valid
        qa, qb = a["q"][n_human:][both], b["q"][n_human:][both]
        ca, cb = a["cost"][n_human:][both], b["cost"][n_human:][both]
        bitwise = np.all(qa == qb, axis=(1, 2))
        return {
            "humans_bitwise": bool(
                all(a[k][:n_human].tobytes() == b[k][:n_human].tobytes() for k in a.files)
            ),
            "slots_compared": int(both.sum()),
            "q_bitwise_fraction": float(bitwise.mean()) if both.any() else None,
            "q_max_abs_diff": float(np.abs(qa - qb).max(initial=0.0)),
            "cost_max_rel_diff": float(np.abs(ca / cb - 1.0).max(initial=0.0)),
            "selection_differs": int((~same).sum()),
        }


# The parent builds generation 0 with JAX too. With JAX's defaults it would keep 75 % of every
# GPU preallocated while the children run (a first run on 2 x H200 ran out of memory at 100,000
# conditions on one device and failed autotuning at 10,000 on two): the parent allocates on
# demand and returns freed memory; the children get JAX's defaults back (`child_env`).
PARENT_ALLOCATION = {
    "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
    "XLA_PYTHON_CLIENT_ALLOCATOR": "platform",
}


def child_env(user: dict) -> dict:
    """The children's environment: ``user`` = the parent's allocation variables as it found them."""
    env = dict(os.environ)
    for key, value in user.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    # JAX preallocates 75 % of each GPU; give the step what the card has (one process per run)
    env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.95")
    if "xla_force_host_platform_device_count" in env.get("XLA_FLAGS", ""):
        # forced CPU devices share one thread pool in which waiting collectives block threads:
        # with too few threads a generation can deadlock (docs/scaling.md)
        env.setdefault("PJRT_NPROC", "32")
    return env


def run_child(args, state: Path, m: int, n: int, unsharded: bool, tmp: str) -> tuple[dict, Path]:
    """One point in a process of its own: the sharded step on ``n`` devices, or the unsharded
    step. ``(point, file)``: the point's JSON and the file of its final database."""
    res_path = Path(tmp) / f"db_{m}_{'unsharded' if unsharded else n}.npz"
    cmd = [sys.executable, __file__, "--config", args.config, "--child", str(state),
           "--devices", str(n), "--generations", str(args.generations),
           "--result", str(res_path)]  # fmt: skip
    cmd += ["--unsharded"] if unsharded else []
    for s in args.set:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=child_env(args.user_env))
    lines = proc.stdout.strip().splitlines()
    if proc.returncode == 0 and lines:
        return json.loads(lines[-1]), res_path
    err = f"exit {proc.returncode}: {proc.stderr.strip()[-300:]}"
    step = "unsharded" if unsharded else "sharded"
    point = {"conditions": m, "devices": n, "step": step, "peak_memory_bytes": [], "error": err}
    return point, res_path


def versus(ref: tuple[dict, Path], point: dict, res_path: Path, n_human: int) -> dict:
    """``point`` (final database in ``res_path``) against ``ref``, a ``(point, file)``: its
    time per generation over the reference's, and the databases compared after generation 1
    and after the last."""
    return {
        "time_ratio": point["seconds_per_generation"] / ref[0]["seconds_per_generation"],
        "generation_1": compare(gen1_path(ref[1]), gen1_path(res_path), n_human),
        "final": compare(ref[1], res_path, n_human),
    }


def record(result: dict, out: Path, point: dict) -> None:
    """Add ``point`` to ``result``, print it and write the result so far (partial results
    survive a failed point)."""
    result["points"].append(point)
    print(json.dumps({k: v for k, v in point.items() if k != "seconds"}), flush=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


def _cell(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


# The databases a point is compared with in the table, the first it has: (key, shown as).
REFERENCES = (("vs_one_device", "sharded, 1 device"), ("vs_unsharded", "unsharded"))


def markdown(result: dict) -> str:
    from make_report import machine_label

    m = result["machine"]
    cpus = "" if m["platform"] == "cpu" else f", {m['cpu_count']} CPUs"  # the label has a CPU's
    lines = [
        f"Machine: {machine_label(m)} ({m['platform']}{cpus}), "
        f"jax {m['jax']}, {m['date']}. Config: `{result['config']}`"
        + (f" with {', '.join(result['overrides'])}" if result["overrides"] else "")
        + f". Command: `{m['command']}`",
        "",
        "| conditions | step | devices | compile s | s / generation | generations / s | speed-up | "
        "efficiency | s / generation over unsharded | peak GiB / device | "
        "last gen: db cost mean | compared with | gen 1: q bit-identical | "
        "gen 1: max abs dq [rad] | last gen: max abs dq [rad] |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in result["points"]:
        peak_bytes = max(r.get("peak_memory_bytes") or [-1])
        peak = f"{peak_bytes / GIB:.1f}" if peak_bytes >= 0 else "-"  # CPU: no allocator stats
        head = f"| {r['conditions']} | {r.get('step', 'sharded')} | {r['devices']} |"
        if "error" in r:
            lines.append(
                f"{head} - | - | - | - | - | - | {peak} | - | - | {r['error'][:60]} | - | - |"
            )
            continue
        # against the sharded step on one device, or (that point itself) the unsharded step
        against, ref = next(((name, r[key]) for key, name in REFERENCES if key in r), ("-", {}))
        cmp, last = ref.get("generation_1", {}), ref.get("final", {})
        bit = cmp.get("q_bitwise_fraction")
        cells = [
            _cell(r.get("compile_s"), ".1f"),
            _cell(r.get("seconds_per_generation"), ".4g"),
            _cell(r.get("generations_per_s"), ".3g"),
            _cell(r.get("speedup"), ".2f"),
            _cell(r.get("efficiency"), ".2f"),
            _cell((r.get("vs_unsharded") or {}).get("time_ratio"), ".3f"),
            peak,
            _cell(r["db_cost_mean"][-1], ".4f"),
            against,
            "-" if bit is None else f"{100 * bit:.1f} %",
            _cell(cmp.get("q_max_abs_diff"), ".2g"),
            _cell(last.get("q_max_abs_diff"), ".2g"),
        ]
        lines.append(f"{head} {' | '.join(cells)} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--set", action="append", default=[], help="KEY=VALUE config override")
    p.add_argument("--sweep-conditions", default="10000,100000")
    p.add_argument("--devices", default="", help="e.g. 1,2,4 (default: 1 and all visible)")
    p.add_argument("--generations", type=int, default=3, help="timed generations per point")
    p.add_argument(
        "--unsharded",
        action="store_true",
        help="also time the unsharded step on one device, the reference of every point",
    )
    p.add_argument("--tag", default="", help="suffix of the JSON name (default: platform)")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    p.add_argument("--child", default="", help=argparse.SUPPRESS)
    p.add_argument("--result", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        args.devices = int(args.devices)
        run_point(args)
        return
    args.user_env = {key: os.environ.get(key) for key in PARENT_ALLOCATION}
    os.environ.update(PARENT_ALLOCATION)

    import gc

    import jax
    from generations_per_sec import build, machine_info

    from evojax_motion.motion.database import count_human
    from evojax_motion.settings import load_config

    cfg = load_config(args.config, args.set)
    n_all = jax.device_count()
    counts = sorted({1, n_all}) if not args.devices else [int(x) for x in args.devices.split(",")]
    result = {
        "machine": machine_info(),
        "config": shown_path(args.config),
        "overrides": args.set,
        "generations": args.generations,
        "points": [],
    }
    tag = args.tag or result["machine"]["platform"]
    out = Path(args.out_dir) / f"sharded_generations_{tag}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for m in [int(x) for x in args.sweep_conditions.split(",") if x]:
            t0 = time.perf_counter()
            _, _, _, db, cond = build(cfg, m)
            n_human = count_human(db)
            state = Path(tmp) / f"state_{m}.npz"
            save_state(state, db, cond, n_human)
            del db, cond  # free the parent's device memory before the children run
            gc.collect()
            print(f"conditions {m}: generation 0 built in {time.perf_counter() - t0:.1f} s")
            plain = None  # (point, final database file) of the unsharded step
            if args.unsharded:
                plain = run_child(args, state, m, 1, True, tmp)
                record(result, out, plain[0])
                plain = None if "error" in plain[0] else plain
            base = None  # ditto, the sharded step on one device
            for n in counts:
                point, res_path = run_child(args, state, m, n, False, tmp)
                if "error" not in point:
                    if n == 1:
                        base = (point, res_path)
                        point["speedup"] = point["efficiency"] = 1.0
                    elif base is not None:
                        point["speedup"] = (
                            base[0]["seconds_per_generation"] / point["seconds_per_generation"]
                        )
                        point["efficiency"] = point["speedup"] / n
                        point["vs_one_device"] = versus(base, point, res_path, n_human)
                    if plain is not None:
                        point["vs_unsharded"] = versus(plain, point, res_path, n_human)
                record(result, out, point)
    table = markdown(result)
    out.with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"\nwritten: {out}")


if __name__ == "__main__":
    main()
