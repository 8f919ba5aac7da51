"""Where a compiled generation's time goes on the device: a `jax.profiler` trace, summarised.

Builds the configuration's generation step at ``--conditions`` as `train` runs it (compiled by
`run.compilation.compile_generation_step`, inputs kept on the device), times ``--generations`` warm
generations, then traces ``--traced`` more and summarises the trace (`summarise_trace`):

- device: kernels per generation, the time the busiest stream is busy (``busy_us``) and the
  span from its first kernel's start to its last one's end (``span_us``), per generation, and
  the gaps between its kernels (the device idle: ``idle_us``, and the largest gaps with the
  kernels around them);
- the kernels that take the most time (name, launches and mean microseconds per launch);
- host: the named events that take the most time in all (e.g. ``cuGraphLaunch``,
  ``command_buffer::update``: launching and updating XLA's CUDA graphs);
- the kernels' launches and time by the project function they come from (``by_source``: read
  from the compiled program's HLO, `trace_summary.kernel_sources`), which says where kernels
  are worth fusing (e.g. the optimiser's algebra against its dynamics).

A step of two programs (`run.compilation.StagedStep`, one device) is traced program by program, each
with
its own HLO (the two name different kernels alike), and summarised together
(`trace_summary.merge_stages`; each program's summary under ``stages``).

``busy_us / span_us`` near 1 says the device is the bound; far below, the host (launching or
preparing work) leaves the device waiting. The timing runs without the profiler (it costs the
host time). On CPU only the timing runs (its trace holds no device kernels). XLA settings
come from ``XLA_FLAGS`` as usual and are recorded with the machine.

Usage:
    python benchmarks/trace_generation.py --conditions 1000 --tag gpu_1k
Writes ``benchmarks/results/trace_generation_<tag>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_default_matmul_precision", "highest")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from generations_per_sec import build, run_generations  # noqa: E402
from trace_summary import merge_stages, read_trace, summarise_trace  # noqa: E402

from evojax_motion.run.compilation import (  # noqa: E402
    StagedStep,
    compile_generation_step,
    generation_inputs,
)
from evojax_motion.settings import load_config  # noqa: E402

WARM_UP = 3  # generations run before the timed ones


def traced(program, call, first: int, n: int) -> dict:
    """`summarise_trace` of ``call(g)`` for generations ``first .. first + n - 1`` (each run to its
    end) under `jax.profiler`; ``program``: the compiled program that runs, whose HLO names each
    kernel's source (`kernel_sources`)."""
    with tempfile.TemporaryDirectory(prefix="trace_generation-") as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for g in range(first, first + n):
                jax.block_until_ready(call(g))
        return summarise_trace(read_trace(Path(tmp)), n, program.as_text())


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--conditions", type=int, default=1000)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument(
        "--generations", type=int, default=20, help=f"timed, after {WARM_UP} warm-up ones"
    )
    p.add_argument("--traced", type=int, default=2, help="generations traced after the timing")
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)

    cfg, robot, dyn, db, conds = build(load_config(args.config, args.set), args.conditions)
    t0 = time.perf_counter()
    step = compile_generation_step(cfg, robot, dyn, db, conds)
    compile_s = time.perf_counter() - t0
    db, conds = generation_inputs(cfg, db, conds)  # as `train` runs its generations
    # generation 1 fills empty slots; later ones are alike
    db, _, _, _ = run_generations(step, db, conds, 1, WARM_UP)
    db, seconds, _, _ = run_generations(step, db, conds, 1 + WARM_UP, args.generations)
    trace = None  # a CPU trace holds no device kernels to summarise
    if args.traced > 0 and jax.default_backend() != "cpu":
        first = 1 + WARM_UP + args.generations
        if isinstance(step, StagedStep):  # each program traced on its own, with its own HLO
            staged = step.prepare(db, conds)
            runs = {
                "prepare": (step.prepare, lambda g: step.prepare(db, conds)),
                "finish": (step.finish, lambda g: step.finish(db, conds, np.int32(g), staged)),
            }
            trace = merge_stages({k: traced(*v, first, args.traced) for k, v in runs.items()})
        else:
            trace = traced(step, lambda g: step(db, conds, np.int32(g)), first, args.traced)
    median = float(np.median(seconds))
    result = {
        "machine": machine_info(),
        "config": args.config,
        "overrides": args.set,
        "conditions": args.conditions,
        "compile_s": compile_s,
        "seconds_per_generation": median,
        "us_per_condition": 1e6 * median / args.conditions,
        "seconds": seconds,
        "traced_generations": args.traced,
        "trace": trace,
    }
    line = f"{args.conditions} conditions: {1e3 * median:.2f} ms a generation "
    line += f"({result['us_per_condition']:.2f} us a condition)"
    if trace is not None:
        line += (
            f"; traced: {trace['kernels_per_generation']:.0f} kernels, device busy "
            f"{trace['busy_us_per_generation'] / 1e3:.2f} of "
            f"{trace['span_us_per_generation'] / 1e3:.2f} ms a generation"
        )
    print(line)
    for row in (trace or {}).get("by_source", [])[:10]:
        print(
            f"  {row['kernels_per_generation']:7.1f} kernels {row['us_per_generation']:9.1f} us"
            f"  {row['source']}"
        )
    tag = args.tag or result["machine"]["platform"]
    path = Path(args.out_dir) / f"trace_generation_{tag}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written: {path}")
    return result


if __name__ == "__main__":
    main()
