"""The optimiser's batched Cholesky solve as XLA compiles it against a hand-written Pallas kernel.

`linalg.cholesky.cholesky_solve` (the quasi-Newton step of every optimiser pass; ``n`` = 14 on
the paper configuration) is unrolled into elementwise operations that XLA splits into ~9 kernels
per call; at 1,000 problems on a GPU their time is their dependency chains, not their work
(`benchmarks/linearity.py`). `pallas_cholesky_solve` is the same algorithm as one Pallas (Triton)
kernel, one thread per problem, the factor held in registers. Both run in a loop of
``--passes`` dependent solves (as in the optimiser) at each ``--batch``; reported per solve,
with the compile time and the largest error against a float64 NumPy solve of the same systems.

Not used by the package: on an H100 the kernel solved 2.4x faster, but Triton took 16-20 s to
compile it (CHANGELOG.md). On CPU the kernel runs in Pallas'
interpreter (a correctness check only: its timings mean nothing).

Usage:
    python benchmarks/cholesky_kernels.py --batch 1000,3072 --tag gpu
Writes ``benchmarks/results/cholesky_kernels_<tag>.json`` and ``.md``.
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from result_files import machine_line, write_result  # noqa: E402

from evojax_motion.linalg.cholesky import cholesky_solve as _cholesky_solve  # noqa: E402

BLOCKS = ((32, 1), (64, 2), (128, 4))  # problems per program, warps per program


def _kernel(n: int, block: int):
    def kernel(a_ref, b_ref, x_ref, ok_ref):
        low = [[None] * n for _ in range(n)]  # (block,) entries of the factor
        ok = jnp.ones((block,), jnp.bool_)
        for k in range(n):
            d = a_ref[k * n + k, :]
            for i in range(k):
                d = d - low[k][i] * low[k][i]
            ok = ok & (d > 0)
            low[k][k] = jnp.sqrt(jnp.where(d > 0, d, 1.0))
            for m in range(k + 1, n):
                c = a_ref[m * n + k, :]
                for i in range(k):
                    c = c - low[m][i] * low[k][i]
                low[m][k] = c / low[k][k]
        y = []
        for k in range(n):
            t = b_ref[k, :]
            for i in range(k):
                t = t - low[k][i] * y[i]
            y.append(t / low[k][k])
        x = [None] * n
        for k in reversed(range(n)):
            t = y[k]
            for i in range(k + 1, n):
                t = t - low[i][k] * x[i]
            x[k] = t / low[k][k]
        for k in range(n):
            x_ref[k, :] = x[k]
        ok_ref[0, :] = ok.astype(x_ref.dtype)

    return kernel


def pallas_cholesky_solve(a, b, block: int = 128, warps: int = 4):
    """``(a^-1 b, ok)`` like `linalg.cholesky.cholesky_solve` for ``a (B, n, n)``, ``b (B, n)``: one
    Pallas kernel, ``block`` problems per program (a power of two), problems along the lanes
    (the inputs are transposed to ``(n * n, B)`` for it). On CPU, Pallas' interpreter."""
    from jax.experimental import pallas as pl

    batch, n = b.shape
    padded = -(-batch // block) * block
    at = jnp.pad(a.reshape(batch, n * n), ((0, padded - batch), (0, 0))).T
    bt = jnp.pad(b, ((0, padded - batch), (0, 0))).T
    interpret = jax.default_backend() == "cpu"
    params = {}
    if not interpret:
        from jax.experimental.pallas import triton as plt

        params["compiler_params"] = plt.CompilerParams(num_warps=warps, num_stages=1)
    cols = lambda rows: pl.BlockSpec((rows, block), lambda i: (0, i))  # noqa: E731
    x, ok = pl.pallas_call(
        _kernel(n, block),
        grid=(padded // block,),
        in_specs=[cols(n * n), cols(n)],
        out_specs=[cols(n), cols(1)],
        out_shape=[
            jax.ShapeDtypeStruct((n, padded), a.dtype),
            jax.ShapeDtypeStruct((1, padded), a.dtype),
        ],
        interpret=interpret,
        **params,
    )(at, bt)
    return x.T[:batch], ok[0, :batch] > 0


def spd_systems(batch: int, n: int, seed: int = 0):
    """``(a (B, n, n), b (B, n))`` float32, ``a`` symmetric positive definite (condition ~1e3)."""
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(batch, n, n))
    a = m @ m.transpose(0, 2, 1) / n + 1e-2 * np.eye(n)
    return a.astype(np.float32), rng.normal(size=(batch, n)).astype(np.float32)


def time_solver(solve, a, b, passes: int, repeats: int) -> dict:
    """Microseconds per solve in a loop of ``passes`` dependent solves (the right-hand side moves
    with the last solution, as in the optimiser: no solve can be hoisted), compile seconds, and
    the largest relative error of one solve against float64 NumPy."""

    def loop(a, b):
        body = lambda _, x: solve(a, b + 1e-3 * x)[0]  # noqa: E731
        return jax.lax.fori_loop(0, passes, body, jnp.zeros_like(b))

    t0 = time.perf_counter()
    compiled = jax.jit(loop).lower(a, b).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(a, b))
    seconds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(a, b))
        seconds.append(time.perf_counter() - t0)
    x, ok = jax.jit(solve)(a, b)
    ref = np.linalg.solve(np.float64(a), np.float64(b)[..., None])[..., 0]
    err = np.max(np.abs(np.asarray(x, np.float64) - ref)) / np.max(np.abs(ref))
    return {"us_per_solve": 1e6 * float(np.median(seconds)) / passes, "compile_s": compile_s,
            "max_rel_error": float(err), "all_ok": bool(np.all(ok))}  # fmt: skip


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", default="1000,3072", help="problems per solve, comma-separated")
    p.add_argument("--n", type=int, default=14, help="unknowns per problem (paper config: 14)")
    p.add_argument("--passes", type=int, default=31, help="dependent solves per timed call")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    solvers = {"xla (compile_optim._cholesky_solve)": _cholesky_solve}
    for block, warps in BLOCKS:
        solvers[f"pallas, {block} problems x {warps} warps"] = (
            lambda a, b, block=block, warps=warps: pallas_cholesky_solve(a, b, block, warps)
        )
    rows = []
    for batch in [int(x) for x in args.batch.split(",") if x]:
        a, b = map(jnp.asarray, spd_systems(batch, args.n))
        for name, solve in solvers.items():
            r = {
                "batch": batch,
                "solver": name,
                **time_solver(solve, a, b, args.passes, args.repeats),
            }
            rows.append(r)
            print(json.dumps(r), flush=True)
    result = {"machine": machine_info(), "n": args.n, "passes": args.passes, "rows": rows}
    m = result["machine"]
    md = [
        f"{machine_line(m)}. {args.n} unknowns, {args.passes} dependent solves a call.",
        "",
        "| problems | solver | us / solve | compile s | max error vs float64 |",
        "|---:|---|---:|---:|---:|",
        *(
            f"| {r['batch']} | {r['solver']} | {r['us_per_solve']:.1f} | {r['compile_s']:.1f} "
            f"| {r['max_rel_error']:.1e} |"
            for r in rows
        ),
    ]
    stem = Path(args.out_dir) / f"cholesky_kernels_{args.tag or m['platform']}"
    write_result(stem, result, "\n".join(md))
    return result


if __name__ == "__main__":
    main()
