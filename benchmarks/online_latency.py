"""Latency and throughput of the online query (paper sec. 3.2: "in real time").

Measures, on whatever JAX backend is active (CPU or GPU):

- single-query latency: one target in (numpy), the whole trajectory out (numpy: q, qd, qdd, tau,
  flags), after a warm-up; p50/p90/p99/max over ``--queries`` different targets. Also the
  device-only time (inputs already on the device, outputs not copied back);
- batched throughput: targets per second for each ``--batch`` size (compile time separate).

The database: ``--db FILE`` / ``--run DIR`` (``db_final.npz``), or by default a synthetic one of
the paper's size (311 demonstrations + 300 slots, T = 100), all entries valid, built from
``demos.generate_demonstrations`` (latency does not depend on the entries' content).

Writes ``benchmarks/results/online_latency_<platform>.json`` with machine information.

    python benchmarks/online_latency.py                       # CPU
    JAX_PLATFORMS=cuda python benchmarks/online_latency.py --batch 1024 16384 65536 262144
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evojax_motion.database import DatabaseMeta, make_database, save_database  # noqa: E402
from evojax_motion.online import (  # noqa: E402
    load_online_model,
    make_online_generator,
    online_database,
)

RESULTS = ROOT / "benchmarks" / "results"


def machine_info() -> dict:
    dev = jax.devices()[0]
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "platform": dev.platform,
        "device": getattr(dev, "device_kind", str(dev)),
        "device_count": jax.device_count(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
    }


def synthetic_database(path: Path, count: int, capacity: int, samples: int, seed: int) -> Path:
    """Demonstrations of the paper's size (``count`` valid of ``capacity``, all valid here)."""
    from evojax_motion.demos import DemoSettings, generate_demonstrations
    from evojax_motion.dynamics import make_dynamics
    from evojax_motion.robot import load_robot

    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot)
    db, _ = generate_demonstrations(
        robot, dyn, DemoSettings(count=capacity, samples=samples), jax.random.key(seed)
    )
    db = make_database(db.q, db.duration, db.condition, db.cost, capacity=capacity)
    meta = DatabaseMeta(robot.name, robot.mjcf, robot.joint_names, robot.site_name, True, "bench")
    save_database(path, db, meta)
    return path


def targets_near_conditions(db, n: int, seed: int, spread: float = 0.03) -> np.ndarray:
    """``n`` targets: valid conditions plus Gaussian noise (inside the learned region)."""
    rng = np.random.default_rng(seed)
    cond = np.asarray(db.condition)[np.asarray(db.valid)]
    pick = cond[rng.integers(0, cond.shape[0], n)]
    return (pick + rng.normal(0.0, spread, pick.shape)).astype(np.float32)


def percentiles(ms: np.ndarray) -> dict:
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p90_ms": float(np.percentile(ms, 90)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "mean_ms": float(ms.mean()),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--db", default=None, help="database .npz")
    ap.add_argument("--run", default=None, help="run directory (db_final.npz)")
    ap.add_argument("--queries", type=int, default=1000, help="single queries timed")
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--batch", type=int, nargs="*", default=[16, 256, 4096])
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per batch size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="JSON path (default: results/...<platform>.json)")
    args = ap.parse_args(argv)

    info = machine_info()
    source = args.run or args.db
    if source is None:
        path = RESULTS / "online_latency_db.npz"
        if not path.is_file():
            print("building a synthetic database (611 x 100 x 7)...", flush=True)
            synthetic_database(path, 311, 611, 100, args.seed)
        source = str(path)
    model = load_online_model(source)
    db = model.db
    print(f"database {source}: {db.q.shape}, {int(db.valid.sum())} valid; {info['device']}")
    gen = make_online_generator(
        model.robot, model.dyn, model.grid, model.basis_settings, model.settings
    )
    dbd = online_database(db)
    rest = np.asarray(model.robot.rest, np.float32)
    nan1 = np.full(1, np.nan, np.float32)

    # ---- single query: numpy in, numpy out
    targets = targets_near_conditions(db, args.queries + args.warmup, args.seed)
    t0 = time.perf_counter()
    jax.block_until_ready(gen(dbd, targets[:1], nan1, rest[None]))
    compile_single = time.perf_counter() - t0
    for i in range(args.warmup):
        jax.device_get(gen(dbd, targets[i : i + 1], nan1, rest[None]))
    e2e, ok = [], 0
    for i in range(args.warmup, args.warmup + args.queries):
        t = time.perf_counter()
        out = jax.device_get(gen(dbd, targets[i : i + 1], nan1, rest[None]))
        e2e.append(time.perf_counter() - t)
        ok += int(out.ok[0])
    # device only: inputs already on the device, wait for the result without copying it
    dev_targets = [jax.device_put(targets[i : i + 1]) for i in range(args.queries)]
    nan_d, rest_d = jax.device_put(nan1), jax.device_put(rest[None])
    dev = []
    for x in dev_targets:
        t = time.perf_counter()
        jax.block_until_ready(gen(dbd, x, nan_d, rest_d))
        dev.append(time.perf_counter() - t)
    single = {
        "compile_s": compile_single,
        "end_to_end": percentiles(np.asarray(e2e) * 1e3),
        "device_only": percentiles(np.asarray(dev) * 1e3),
        "ok_fraction": ok / args.queries,
        "queries": args.queries,
    }
    print(
        f"single query: p50 {single['end_to_end']['p50_ms']:.3f} ms, p99 "
        f"{single['end_to_end']['p99_ms']:.3f} ms (device only p50 "
        f"{single['device_only']['p50_ms']:.3f} ms); compile {compile_single:.1f} s",
        flush=True,
    )

    # ---- batched throughput
    batched = []
    for b in args.batch:
        tg = jax.device_put(targets_near_conditions(db, b, args.seed + b))
        dur = jax.device_put(np.full(b, np.nan, np.float32))
        q0 = jax.device_put(np.tile(rest, (b, 1)))
        t = time.perf_counter()
        out = jax.block_until_ready(gen(dbd, tg, dur, q0))
        compile_s = time.perf_counter() - t
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            out = jax.block_until_ready(gen(dbd, tg, dur, q0))
            times.append(time.perf_counter() - t)
        best = float(np.median(times))
        row = {
            "batch": b,
            "compile_s": compile_s,
            "median_s": best,
            "targets_per_s": b / best,
            "ok_fraction": float(np.mean(np.asarray(out.ok))),
        }
        batched.append(row)
        print(f"batch {b:>7}: {row['targets_per_s']:.3e} targets/s ({best * 1e3:.2f} ms)")

    result = {
        "benchmark": "online_latency",
        "machine": info,
        "database": {"source": source, "shape": list(db.q.shape), "valid": int(db.valid.sum())},
        "settings": {
            "basis": dataclasses.asdict(model.basis_settings),
            "online": dataclasses.asdict(model.settings),
        },
        "single_query": single,
        "batched": batched,
        "targets": {"p50_single_ms_limit": 1.0, "throughput_limit_per_s": 1e6},
    }
    out = Path(args.out) if args.out else RESULTS / f"online_latency_{info['platform']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
