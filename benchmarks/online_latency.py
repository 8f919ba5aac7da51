"""Latency and throughput of the online query (paper sec. 3.2: "in real time").

Measures, on whatever JAX backend is active (CPU or GPU):

- single-query latency: one target in (numpy), the whole trajectory out (numpy: q, qd, qdd, tau,
  flags), after a warm-up; p50/p90/p99/max over ``--queries`` different targets. Also the
  device-only time (inputs already on the device, outputs not copied back);
- batched throughput: targets per second for each ``--batch`` size, device only (targets already
  on the device, results left there), the median of ``--repeats`` timed calls after a warm-up
  call (its time, mostly compilation, reported separately). A batch larger than ``--chunk`` runs
  as ``ceil(batch / chunk)`` calls of ``chunk`` targets (one compiled shape, memory bounded),
  all dispatched before waiting for the last.

The database: ``--db FILE`` / ``--run DIR`` (``db_final.npz``), or by default a synthetic one of
the paper's size (611 demonstrations, T = 100, all valid, all human: no evolved entries), built
from ``demonstrations.synthetic.generate_demonstrations`` in ~15 s and cached in
``runs/online_latency_db.npz``. The
query does the same work on any database of this shape (the limit projection runs whenever one
motion of a batch needs it); the JSON says which database was used.

Writes ``benchmarks/results/online_latency_<platform>.json`` with machine information (device,
date, command).

    python benchmarks/online_latency.py                                  # CPU
    python benchmarks/online_latency.py --batch 10000 100000 1000000     # GPU (the defaults there)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402  (one definition for all benchmarks)

from evojax_motion.linalg.precision import exact_matmuls  # noqa: E402
from evojax_motion.motion.database import (  # noqa: E402
    EVOLVED,
    DatabaseMeta,
    make_database,
    save_database,
)
from evojax_motion.online.generation import (  # noqa: E402
    load_online_model,
    make_online_generator,
    online_database,
    online_query,
    to_numpy,
)
from evojax_motion.online.limits import joint_limits_f32  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_DB = ROOT / "runs" / "online_latency_db.npz"
SYNTHETIC = "synthetic demonstrations (demos.generate_demonstrations), 611 x T=100, not evolved"


def synthetic_database(path: Path, count: int, capacity: int, samples: int, seed: int) -> Path:
    """Demonstrations of the paper's size (``count`` valid of ``capacity``, all valid here)."""
    from evojax_motion.demonstrations.synthetic import generate_demonstrations
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import load_robot
    from evojax_motion.settings.demonstrations import DemoSettings

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


def throughput(gen, dbd, db, rest, b: int, args) -> dict:
    """Targets per second of ``gen`` for ``b`` targets (``--chunk`` per call), device only."""
    size = min(b, args.chunk)
    calls = math.ceil(b / size)
    tg = targets_near_conditions(db, calls * size, args.seed + b).reshape(calls, size, 3)
    tg = [jax.device_put(x) for x in tg]
    dur = jax.device_put(np.full(size, np.nan, np.float32))
    q0 = jax.device_put(np.tile(rest, (size, 1)))
    t = time.perf_counter()
    out = jax.block_until_ready(gen(dbd, tg[0], dur, q0))
    compile_s = time.perf_counter() - t
    row = {
        "batch": calls * size,
        "calls": calls,
        "chunk": size,
        "compile_s": compile_s,
        "ok_fraction_first_call": float(np.mean(np.asarray(out.ok))),
        "fallback_fraction_first_call": float(np.mean(np.asarray(out.fallback))),
        "projected_fraction_first_call": float(np.mean(np.asarray(out.limit_excess) > 0)),
    }
    del out
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        outs = jax.block_until_ready([gen(dbd, x, dur, q0) for x in tg])
        times.append(time.perf_counter() - t)
        del outs
    row["median_s"] = float(np.median(times))
    row["min_s"] = float(np.min(times))
    row["targets_per_s"] = row["batch"] / row["median_s"]
    print(f"batch {b:>7}: {row['targets_per_s']:.3e} targets/s ({row['median_s'] * 1e3:.2f} ms)")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--db", default=None, help="database .npz")
    ap.add_argument("--run", default=None, help="run directory (db_final.npz)")
    ap.add_argument("--queries", type=int, default=1000, help="single queries timed")
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument(
        "--batch", type=int, nargs="*", default=None, help="CPU: 16 256 4096; GPU: 1e4 1e5 1e6"
    )
    ap.add_argument("--chunk", type=int, default=100_000, help="largest batch of one call")
    ap.add_argument("--narrow", type=float, default=0.3, help="see batched_projection")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per batch size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="JSON path (default: results/...<platform>.json)")
    args = ap.parse_args(argv)

    info = machine_info()
    if args.batch is None:
        args.batch = [16, 256, 4096] if info["platform"] == "cpu" else [10**4, 10**5, 10**6]
    source, kind = args.run or args.db, "given"
    if source is None:
        kind = SYNTHETIC
        if not DEFAULT_DB.is_file():
            print("building a synthetic database (611 x 100 x 7)...", flush=True)
            DEFAULT_DB.parent.mkdir(parents=True, exist_ok=True)
            synthetic_database(DEFAULT_DB, 611, 611, 100, args.seed)
        source = str(DEFAULT_DB.relative_to(ROOT))
    model = load_online_model(source)
    db = model.db
    print(f"database {source}: {db.q.shape}, {int(db.valid.sum())} valid; {info['device_kind']}")
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
        to_numpy(gen(dbd, targets[i : i + 1], nan1, rest[None]))
    e2e, ok = [], 0
    for i in range(args.warmup, args.warmup + args.queries):
        t = time.perf_counter()
        out = to_numpy(gen(dbd, targets[i : i + 1], nan1, rest[None]))
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

    # ---- batched throughput, device only
    lower, upper = joint_limits_f32(model.robot)
    span = args.narrow * (upper - lower)
    narrowed = jax.jit(
        exact_matmuls(
            lambda *a: online_query(
                model.dyn,
                model.grid,
                lower + span,
                upper - span,
                model.basis_settings,
                model.settings,
                *a,
            )
        )
    )
    batched = [throughput(gen, dbd, db, rest, b, args) for b in args.batch]
    projection = [throughput(narrowed, dbd, db, rest, b, args) for b in args.batch]

    result = {
        "benchmark": "online_latency",
        "machine": info,
        "database": {
            "source": source,
            "kind": kind,
            "shape": list(db.q.shape),
            "valid": int(db.valid.sum()),
            "evolved": int(((np.asarray(db.origin) == EVOLVED) & np.asarray(db.valid)).sum()),
        },
        "settings": {
            "basis": dataclasses.asdict(model.basis_settings),
            "online": dataclasses.asdict(model.settings),
        },
        "single_query": single,
        "batched": batched,
        "batched_projection": projection,
        "targets": {"p50_single_ms_limit": 1.0, "throughput_limit_per_s": 1e6},
    }
    out = Path(args.out) if args.out else RESULTS / f"online_latency_{info['platform']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
