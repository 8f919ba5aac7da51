"""Where a generation's time goes: each stage of the generation step timed on its own.

Stages (each jitted alone, timed after compilation, median of ``--repeats``):
``neighbours`` (eq. 6 top-k), ``pca`` (per-joint PCA of the neighbours), ``bc_solve``
(`compiler.interpolation.solve_boundary` with the optimisation compiler's rule), ``reduced``
(`compiler.problems.reduced_problems`: BC solve + orthonormal null directions + node arrays),
``value`` and ``value_grad`` of the batched search objective at z = 0 as the optimiser
compiles them (`compiler.optimisation.cpu_fast_path`, `compiler.search_objective.make_search_value`:
on CPU with BFGS the scalar RNEA layout and one reduction over the nodes), ``value_grad_autodiff``
(autodiff of `compiler.search_objective.make_objective` with the config's dynamics, for
comparison) and ``hessian`` (of the latter), ``eigh`` of the batch's trust-region model (B, n, n)
(``jnp.linalg.eigh``, and ``small_eigh``: Jacobi on accelerators), ``tr_step`` (the trust-region
step of that model: eigh + secular iterations), and the whole optimiser (``optimise``, compiled
as the step compiles it) and generation step (``step``). The sum of the parts is not the step:
inside one jit XLA fuses across them.

Usage:
    python benchmarks/profile_generation.py --conditions 300 [--set compiler.method=bfgs]
Writes ``benchmarks/results/profile_generation_<tag>.json`` and prints one line per stage.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_default_matmul_precision", "highest")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from generations_per_sec import build  # noqa: E402

from evojax_motion.compiler.basis import pca_basis, select_neighbours, small_eigh  # noqa: E402
from evojax_motion.compiler.interpolation import solve_boundary  # noqa: E402
from evojax_motion.compiler.optimisation import compile_optimisation, cpu_fast_path  # noqa: E402
from evojax_motion.compiler.problems import reduced_problems  # noqa: E402
from evojax_motion.compiler.search_objective import make_objective, make_search_value  # noqa: E402
from evojax_motion.evolution.step import make_generation_step  # noqa: E402
from evojax_motion.motion.database import count_human  # noqa: E402
from evojax_motion.motion.timegrid import make_time_grid  # noqa: E402
from evojax_motion.settings import load_config  # noqa: E402
from evojax_motion.solvers.steps import trust_region_step  # noqa: E402


def timed(fn, *args, repeats: int) -> dict:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t0)
    return {"compile_plus_run_s": first, "median_s": float(np.median(runs))}, out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--conditions", type=int, default=300)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip", default="", help="comma-separated stages not to run")
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    skip = set(args.skip.split(","))

    cfg, robot, dyn, db, conds = build(load_config(args.config, args.set), args.conditions)
    grid = make_time_grid(db.q.shape[1])
    b, st = cfg.basis, cfg.compiler
    k = st.n_components
    lo = jnp.asarray(robot.lower) + st.limit_margin
    hi = jnp.asarray(robot.upper) - st.limit_margin
    stages: dict = {}

    def run(name, fn, *a, options=None):
        if name in skip:
            return None
        stages[name], out = timed(jax.jit(fn, compiler_options=options), *a, repeats=args.repeats)
        print(json.dumps({name: stages[name]}), flush=True)
        return out

    nb = run("neighbours", lambda d, c: select_neighbours(
        d.condition, d.valid, c.target, b.neighbours, b.radius, b.w_pos), db, conds)  # fmt: skip
    basis = run("pca", lambda d, n: pca_basis(d.q, d.duration, n, k), db, nb)
    bd = conds.boundary
    run("bc_solve", lambda ba, bc: solve_boundary(ba, bc, grid, k, leak=st.bc_leak), basis, bd)
    red = run("reduced", lambda ba, bc: reduced_problems(
        ba, bc, grid, k, st.bc_leak, st.max_free_per_joint, st.search_stride),
        basis, bd)  # fmt: skip
    prob = red[0]
    objective = make_objective(dyn, lo, hi, st.limit_penalty)
    fast_dyn, options = cpu_fast_path(dyn, st)  # as the optimiser's program is compiled
    search = make_search_value(fast_dyn, lo, hi, st.limit_penalty, st.method)
    j, f = prob.mask.shape[1:]
    z0 = jnp.zeros((args.conditions, j * f))

    def fun(z, pr):
        return search(z.reshape(j, f), pr)

    def autodiff(z, pr):
        return objective(z.reshape(j, f), pr)[0]

    run("value", jax.vmap(fun), z0, prob, options=options)
    run("value_grad", jax.vmap(jax.value_and_grad(fun)), z0, prob, options=options)
    run("value_grad_autodiff", jax.vmap(jax.value_and_grad(autodiff)), z0, prob)
    hess = run("hessian", jax.vmap(jax.hessian(autodiff)), z0, prob)
    if hess is not None:
        sym = 0.5 * (hess + jnp.swapaxes(hess, 1, 2)) + 1e-3 * jnp.eye(j * f)
        run("eigh", jnp.linalg.eigh, sym)
        run("small_eigh", small_eigh, sym)
        g0 = jnp.ones((args.conditions, j * f))
        radius = jnp.full((args.conditions,), 0.3)
        run("tr_step", trust_region_step, sym, g0, radius)
    out = run("optimise", lambda ba, bc: compile_optimisation(
        ba, bc, fast_dyn, grid, robot.lower, robot.upper, st),
        basis, bd, options=options)  # fmt: skip
    n_human = count_human(db)
    step = make_generation_step(dyn, grid, robot.lower, robot.upper, n_human, b, st, cfg.evolution)
    if "step" not in skip:
        stages["step"], _ = timed(step, db, conds, np.asarray(1, np.int32), repeats=args.repeats)
        print(json.dumps({"step": stages["step"]}), flush=True)
    result = {
        "machine": machine_info(),
        "config": args.config,
        "overrides": args.set,
        "conditions": args.conditions,
        "samples": int(db.q.shape[1]),
        "stages": stages,
    }
    if out is not None:
        result["iterations_median"] = float(np.median(np.asarray(out.iterations)))
        result["iterations_max"] = int(np.max(np.asarray(out.iterations)))
    tag = args.tag or result["machine"]["platform"]
    path = Path(args.out_dir) / f"profile_generation_{tag}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written: {path}")


if __name__ == "__main__":
    main()
