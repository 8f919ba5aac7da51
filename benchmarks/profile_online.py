"""Where an online batch's time goes: each stage of the online query timed on its own.

Stages (each jitted alone at full float32 precision, timed after compilation, median of
``--repeats``), for ``--batch`` targets near the database's conditions (as
``benchmarks/online_latency.py``):
``neighbours`` (eq. 6, the learned region and the evolved-only search), ``reach`` (+ the
human-like IK of the final posture: `online.reach.reach_query`), ``build`` (+ the per-joint
PCA and the
BCs: `online.generation.build_problem`), ``interp`` (eq. 1-2,
`compiler.interpolation.compile_interpolation`),
``limits`` (`online.limits.enforce_limits`, its projection forced on by narrowing the limits by
``--narrow`` of their span), ``dynamics`` (derivatives, inverse dynamics, eq. 5 cost), ``finish``
(`online.generation.finish_motion`: interp + limits + dynamics + checks) and ``query`` (all of it,
the
generator users call). Inside one jit XLA fuses across stages, so the parts need not add up.

Usage:
    python benchmarks/profile_online.py --batch 100000
Writes ``benchmarks/results/profile_online_<platform>.json`` and prints one line per stage.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from online_latency import DEFAULT_DB, synthetic_database, targets_near_conditions  # noqa: E402
from profile_generation import timed  # noqa: E402

from evojax_motion.compiler.basis import select_neighbours  # noqa: E402
from evojax_motion.compiler.interpolation import compile_interpolation  # noqa: E402
from evojax_motion.linalg.precision import exact_matmuls  # noqa: E402
from evojax_motion.motion.database import EVOLVED  # noqa: E402
from evojax_motion.motion.objective import cost_from_torques  # noqa: E402
from evojax_motion.motion.timegrid import derivatives  # noqa: E402
from evojax_motion.online.generation import (  # noqa: E402
    build_problem,
    finish_motion,
    load_online_model,
    make_online_generator,
    online_database,
)
from evojax_motion.online.limits import enforce_limits, joint_limits_f32  # noqa: E402
from evojax_motion.online.reach import reach_query  # noqa: E402


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--db", default=None, help="database .npz (default: the synthetic one)")
    p.add_argument("--batch", type=int, default=100_000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--narrow", type=float, default=0.3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    info = machine_info()
    source = args.db
    if source is None:
        if not DEFAULT_DB.is_file():
            DEFAULT_DB.parent.mkdir(parents=True, exist_ok=True)
            synthetic_database(DEFAULT_DB, 611, 611, 100, args.seed)
        source = str(DEFAULT_DB)
    model = load_online_model(source)
    dyn, grid, bs, st = model.dyn, model.grid, model.basis_settings, model.settings
    db = online_database(model.db)
    lower, upper = joint_limits_f32(model.robot)
    span = args.narrow * (upper - lower)
    b = args.batch
    targets = jax.device_put(targets_near_conditions(model.db, b, args.seed))
    dur = jax.device_put(np.full(b, np.nan, np.float32))
    q0 = jax.device_put(np.tile(np.asarray(model.robot.rest, np.float32), (b, 1)))

    def jit(fn):
        return jax.jit(exact_matmuls(fn))

    def neighbours(db, points):
        sel = functools.partial(
            select_neighbours, k=bs.neighbours, radius=bs.radius, w_pos=bs.w_pos
        )
        region = sel(db.condition, db.valid, points)
        evolved = sel(db.condition, db.valid & (db.origin == EVOLVED), points)
        return region, evolved

    def dynamics(q, duration):
        qd, qdd = derivatives(grid, q, duration)
        tau = jax.vmap(jax.vmap(dyn.inverse))(q, qd, qdd)
        return tau, jax.vmap(functools.partial(cost_from_torques, grid))(tau, duration)

    stages: dict = {}
    stages["neighbours"], _ = timed(jit(neighbours), db, targets, repeats=args.repeats)
    stages["reach"], _ = timed(
        jit(lambda db, t: reach_query(dyn, db, t, lower, upper, bs, st)), db, targets,
        repeats=args.repeats,
    )  # fmt: skip
    stages["build"], (basis, boundary, reach) = timed(
        jit(lambda db, t, d, q: build_problem(dyn, db, t, d, q, lower, upper, bs, st)),
        db, targets, dur, q0, repeats=args.repeats,
    )  # fmt: skip
    stages["interp"], interp = timed(
        jit(lambda b_, bc: compile_interpolation(b_, bc, grid, st.n_components)),
        basis, boundary, repeats=args.repeats,
    )  # fmt: skip
    stages["limits"], (q, _, _) = timed(
        jit(lambda b_, bc, q: enforce_limits(b_, bc, grid, q, lower + span, upper - span, st)),
        basis, boundary, interp.q, repeats=args.repeats,
    )  # fmt: skip
    stages["dynamics"], _ = timed(jit(dynamics), q, boundary.duration, repeats=args.repeats)
    stages["finish"], _ = timed(
        jit(lambda *a: finish_motion(dyn, grid, lower, upper, st, *a)),
        basis, boundary, reach, targets, repeats=args.repeats,
    )  # fmt: skip
    gen = make_online_generator(model.robot, dyn, grid, bs, st)
    stages["query"], _ = timed(gen, db, targets, dur, q0, repeats=args.repeats)
    for name, s in stages.items():
        print(
            f"{name:>10}: {s['median_s'] * 1e3:9.2f} ms  "
            f"({b / s['median_s']:.3g} targets/s; compile+run {s['compile_plus_run_s']:.1f} s)"
        )
    out = (
        Path(args.out)
        if args.out
        else ROOT / "benchmarks" / "results" / (f"profile_online_{info['platform']}.json")
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {"machine": info, "database": source, "batch": b, "stages": stages}
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written: {out}")


if __name__ == "__main__":
    main()
