"""Throughput of the inverse dynamics behind the torque cost (paper eq. 5), per backend.

For each backend (``rnea``, ``mjx``; float32) and one robot, over ``--n`` random states inside
the joint limits, vmapped and jitted as the optimiser uses them:

- ``inverse``: ``tau = M(q) qdd + C(q, qd) qd + g(q)`` -> evaluations/s;
- ``value_and_grad``: ``sum tau^2`` and its gradient w.r.t. (q, qd, qdd) -> evaluations/s;
  ``rnea`` is the platform's default layout; ``rnea-vector`` / ``rnea-scalar`` pick one;
- compile time (ahead of time, separately), and FLOPs and bytes accessed per evaluation from
  XLA's ``cost_analysis`` of the compiled function;
- ``max_abs_err``: float32 torques against C MuJoCo (float64) on the first states;
- ``mujoco_c``: C MuJoCo's ``mj_inverse`` in a Python loop, one core (the plain-user baseline).

Timings are the median of ``--repeats`` calls after compilation. The machine's load average is
recorded before and after: on a shared machine, compare only runs with a similar load.

    python benchmarks/dynamics_throughput.py [--n 20000] [--repeats 5] [--backends rnea,mjx]
        [--robot mahru_arm] [--tag TAG]

Writes ``benchmarks/results/dynamics_throughput_<platform>[_<tag>].json`` and prints a table.
``XLA_FLAGS`` (e.g. ``--xla_cpu_use_fusion_emitters=false``) is recorded: run once with and once
without, with different tags, to compare.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evojax_motion.model.dynamics import BACKENDS, make_dynamics  # noqa: E402
from evojax_motion.model.rnea import FORMS, default_form, make_rnea  # noqa: E402
from evojax_motion.model.robot import load_robot  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
N_CHECK = 1000  # states checked against C MuJoCo


def random_states(robot, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd): (n, J) each, q uniform inside the limits."""
    rng = np.random.default_rng(seed)
    j = robot.n_joints
    q = rng.uniform(robot.lower, robot.upper, (n, j))
    return q, 2.0 * rng.standard_normal((n, j)), 10.0 * rng.standard_normal((n, j))


def mj_inverse_loop(robot, q, qd, qdd) -> tuple[np.ndarray, float]:
    """C MuJoCo reference torques (n, J) and the loop's evaluations/s."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    tau = np.zeros_like(q)
    adr_q, adr_v = robot.qpos_adr, robot.dof_adr
    start = time.perf_counter()
    for i in range(len(q)):
        d.qpos[adr_q], d.qvel[adr_v], d.qacc[adr_v] = q[i], qd[i], qdd[i]
        mujoco.mj_inverse(m, d)
        tau[i] = d.qfrc_inverse[adr_v]
    return tau, len(q) / (time.perf_counter() - start)


def cost_per_eval(compiled, n: int) -> dict:
    cost = compiled.cost_analysis()
    if isinstance(cost, list | tuple):  # older jax: one dict per program
        cost = cost[0] if cost else {}
    cost = cost or {}
    return {
        "flops_per_eval": float(cost.get("flops", float("nan"))) / n,
        "bytes_per_eval": float(cost.get("bytes accessed", float("nan"))) / n,
    }


def time_calls(fn, args, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return times


def bench_backend(robot, backend: str, states, ref_tau, repeats: int) -> dict:
    """backend: a `BACKENDS` name, or ``rnea-<form>`` for one RNEA layout (`FORMS`)."""
    if backend.startswith("rnea-"):
        dyn = make_rnea(robot, jnp.float32, form=backend.removeprefix("rnea-"))
    else:
        dyn = make_dynamics(robot, backend, jnp.float32)
    n = len(states[0])
    args = tuple(jnp.asarray(x, jnp.float32) for x in states)
    batched = jax.vmap(dyn.inverse)

    def energy(q, qd, qdd):
        return jnp.sum(batched(q, qd, qdd) ** 2)

    out = {}
    for name, fn in (
        ("inverse", batched),
        ("value_and_grad", jax.value_and_grad(energy, argnums=(0, 1, 2))),
    ):
        start = time.perf_counter()
        compiled = jax.jit(fn).lower(*args).compile()
        compile_s = time.perf_counter() - start
        result = jax.block_until_ready(compiled(*args))  # warm-up
        times = time_calls(compiled, args, repeats)
        median = statistics.median(times)
        out[name] = {
            "compile_s": compile_s,
            "median_s": median,
            "min_s": min(times),
            "evals_per_s": n / median,
            **cost_per_eval(compiled, n),
        }
        if name == "inverse":
            k = min(N_CHECK, n)
            err = np.abs(np.asarray(result[:k], np.float64) - ref_tau[:k]).max()
            out["max_abs_err_vs_mujoco_c"] = float(err)
            out["max_abs_tau"] = float(np.abs(ref_tau[:k]).max())
    return out


def _processor() -> str:
    return platform.processor() or platform.machine()


def cpu_model() -> str:
    """The CPU's model name (Linux: ``/proc/cpuinfo``), else `_processor`: timings on
    CPUs of the same core count differ by model (CHANGELOG.md)."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return _processor()


def machine_info() -> dict:
    dev = jax.devices()[0]
    return {
        "platform": dev.platform,
        "device_kind": dev.device_kind,
        "device_count": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "processor": _processor(),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20000, help="states per batched call")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per function")
    choices = (*BACKENDS, *(f"rnea-{f}" for f in FORMS))
    parser.add_argument(
        "--backends",
        default=",".join(BACKENDS),
        help=f"comma-separated, of {choices} (rnea: the platform's default form)",
    )
    parser.add_argument("--robot", default="mahru_arm", help="shipped robot or MJCF path")
    parser.add_argument("--mujoco-n", type=int, default=20000, help="states for the C loop")
    parser.add_argument("--tag", default="", help="suffix of the result file name")
    args = parser.parse_args(argv)
    backends = [b for b in args.backends.split(",") if b]
    unknown = sorted(set(backends) - set(choices))
    if unknown:
        parser.error(f"--backends: unknown {unknown}; expected some of {choices}")

    robot = load_robot(args.robot)
    states = random_states(robot, max(args.n, args.mujoco_n))
    c_states = tuple(x[: args.mujoco_n] for x in states)
    ref_tau, c_rate = mj_inverse_loop(robot, *c_states)
    info = machine_info()
    load_before = os.getloadavg() if hasattr(os, "getloadavg") else None
    results = {
        "machine": info,
        "robot": robot.name,
        "n_joints": robot.n_joints,
        "n": args.n,
        "repeats": args.repeats,
        "dtype": "float32",
        "rnea_default_form": default_form(),
        "mujoco_c": {"evals_per_s": c_rate, "n": args.mujoco_n, "threads": 1},
        "backends": {},
    }
    batch = tuple(x[: args.n] for x in states)
    for backend in backends:
        print(f"{backend}: compiling and timing ...", file=sys.stderr, flush=True)
        results["backends"][backend] = bench_backend(robot, backend, batch, ref_tau, args.repeats)
    results["load_average_before_after"] = [load_before, os.getloadavg()]

    tag = f"_{args.tag}" if args.tag else ""
    path = RESULTS / f"dynamics_throughput_{info['platform']}{tag}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2) + "\n")

    print(
        f"\n{robot.name} (J={robot.n_joints}), N={args.n}, {info['device_kind']}, "
        f"XLA_FLAGS={info['xla_flags']!r}, rnea = rnea-{default_form()}"
    )
    print("| backend | function | evals/s | compile s | kFLOP/eval | kB/eval |")
    print("|---|---|---|---|---|---|")
    print(f"| C mujoco mj_inverse (1 core loop) | inverse | {c_rate:.3g} | - | - | - |")
    for backend, res in results["backends"].items():
        for fn in ("inverse", "value_and_grad"):
            r = res[fn]
            print(
                f"| {backend} | {fn} | {r['evals_per_s']:.3g} | {r['compile_s']:.1f} | "
                f"{r['flops_per_eval'] / 1e3:.2f} | {r['bytes_per_eval'] / 1e3:.2f} |"
            )
    for backend, res in results["backends"].items():
        print(
            f"{backend}: max |tau - tau_C| = {res['max_abs_err_vs_mujoco_c']:.2e} N m "
            f"(max |tau| {res['max_abs_tau']:.1f})"
        )
    print(f"wrote {path.relative_to(ROOT)}")
    return results


if __name__ == "__main__":
    main()
