"""Batched eigen-decompositions of small symmetric matrices, as the per-joint PCA needs them.

The online query and the generation step decompose one ``k x k`` Gram matrix per (target, joint):
700,000 of them for 100,000 online targets (k = 10 neighbours, 7 joints). This times, for
``--batch`` such Gram matrices of random centred ``(k, T)`` trajectories (jitted, median of
``--repeats`` after a compiling call):

- ``jacobi_eigh``: `basis.jacobi_eigh` under vmap (elementwise parallel Jacobi, no solver call);
- ``linalg_eigh``: ``jnp.linalg.eigh`` on the batch (LAPACK on CPU; cuSOLVER's batched Jacobi on
  GPUs);
- ``pca_rows_gram``: the PCA's two-pass Gram decomposition (`compiler.basis._pca_rows_gram`, what
the
  accelerator path runs) and ``pca_rows_jacobi_eigh``, the same two passes with `jacobi_eigh`
  (6 and 2 sweeps: an earlier accelerator path);

and the largest singular-value difference between the two PCA variants (relative to s_0).

Usage: ``python benchmarks/small_eigh.py --batch 700000`` (GPU), ``--batch 20000`` (CPU).
Writes ``benchmarks/results/small_eigh_<platform>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from profile_generation import timed  # noqa: E402

from evojax_motion.compiler.basis import _pca_rows_gram  # noqa: E402
from evojax_motion.linalg.jacobi import jacobi_eigh  # noqa: E402
from evojax_motion.linalg.precision import exact_matmuls  # noqa: E402


def pca_rows_jacobi_eigh(centred, n_components: int):
    """`compiler.basis._pca_rows_gram` with `jacobi_eigh` (6 sweeps, then 2 on the nearly diagonal
    Gram)."""
    _, u = jacobi_eigh(centred @ centred.T)
    y = u.T @ centred
    _, w = jacobi_eigh(y @ y.T, 2)
    z = w.T @ y
    sv, order = jax.lax.top_k(jnp.sqrt(jnp.sum(z * z, axis=1)), n_components)
    return sv, z[order] / jnp.where(sv > 0, sv, 1.0)[:, None]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=700_000)
    p.add_argument("--neighbours", type=int, default=10)
    p.add_argument("--samples", type=int, default=100)
    p.add_argument("--components", type=int, default=4)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    info = machine_info()
    rng = np.random.default_rng(0)
    x = rng.normal(size=(args.batch, args.neighbours, args.samples)).astype(np.float32)
    x = jax.device_put(x - x.mean(axis=1, keepdims=True))
    gram = jax.jit(exact_matmuls(lambda a: jnp.einsum("bkt,blt->bkl", a, a)))(x)
    k = args.components

    def jit(fn):
        return jax.jit(exact_matmuls(fn))

    pca_new = jit(jax.vmap(lambda a: _pca_rows_gram(a, k)))
    pca_old = jit(jax.vmap(lambda a: pca_rows_jacobi_eigh(a, k)))
    results = {
        "jacobi_eigh": timed(jit(jax.vmap(jacobi_eigh)), gram, repeats=args.repeats)[0],
        "linalg_eigh": timed(jit(jnp.linalg.eigh), gram, repeats=args.repeats)[0],
        "pca_rows_gram": timed(pca_new, x, repeats=args.repeats)[0],
        "pca_rows_jacobi_eigh": timed(pca_old, x, repeats=args.repeats)[0],
    }
    s_new, s_old = pca_new(x)[0], pca_old(x)[0]
    diff = float(jnp.max(jnp.abs(s_new - s_old) / s_new[:, :1]))
    for name, r in results.items():
        print(
            f"{name:>22}: {r['median_s'] * 1e3:8.2f} ms "
            f"(compile+run {r['compile_plus_run_s']:.1f} s)"
        )
    print(f"singular values, largest difference / s_0: {diff:.2e}")
    out = (
        Path(args.out)
        if args.out
        else ROOT / "benchmarks" / "results" / (f"small_eigh_{info['platform']}.json")
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    shape = {"batch": args.batch, "k": args.neighbours, "T": args.samples, "components": k}
    result = {"machine": info, **shape, "stages": results, "sv_max_rel_diff": diff}
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written: {out}")


if __name__ == "__main__":
    main()
