"""Where a fresh process's compile time goes before the first generation: every program JAX
traces and compiles while `run.training.initial_state` builds generation 0 (demonstrations, then the
condition set and costs), and the generation step, grouped by phase and program name, with the
dynamics and step options `train` compiles them with (`model.dynamics.training_dynamics`). Also
each phase's wall time, one after the other here (`train` overlaps the step's compile with the
setup).

Reads JAX's own log lines (``jax_log_compiles``: "Finished tracing ... / XLA compilation of
NAME in S sec"). Run it in a fresh process with no compilation cache to see cold compiles.

Usage:
    python benchmarks/profile_compiles.py [--config configs/catch_ball.yaml] [--tag cpu]
Writes ``benchmarks/results/profile_compiles_<tag>.json`` and prints the largest entries.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import re
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_default_matmul_precision", "highest")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from result_files import shown_path  # noqa: E402

_LINE = re.compile(r"Finished (.*?) (?:of|for) (\S+) in ([0-9.e-]+) sec")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--tag", default="", help="suffix of the JSON name (default: platform)")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)

    phase = ["setup"]
    seconds: dict = collections.defaultdict(float)
    counts: collections.Counter = collections.Counter()

    class Listener(logging.Handler):
        def emit(self, record):
            m = _LINE.search(record.getMessage())
            if m:
                what = "compile" if "XLA compilation" in m.group(1) else "trace/lower"
                seconds[(phase[0], m.group(2), what)] += float(m.group(3))
                if what == "compile":
                    counts[phase[0]] += 1

    logging.getLogger("jax").addHandler(Listener())
    logging.getLogger("jax").setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)

    import evojax_motion.run.workflow as workflow
    from evojax_motion.model.dynamics import training_dynamics
    from evojax_motion.run import compilation
    from evojax_motion.run import training as train
    from evojax_motion.settings import load_config

    cfg = load_config(args.config)
    robot, dyn = workflow.make_robot_dynamics(cfg)
    evo = cfg.evolution
    dyn, short = training_dynamics(dyn, evo.generations, evo.conditions)  # as `train`
    demos = workflow.demonstrations  # what `run.training.initial_state` calls

    def timed_demos(*a, **k):  # the phases: demonstrations, then everything else of the setup
        phase[0] = "demonstrations"
        out = demos(*a, **k)
        phase[0] = "conditions and costs"
        return out

    workflow.demonstrations = timed_demos
    db, conditions, *_, walls = train.initial_state(cfg, robot, dyn)
    phase[0] = "generation step"
    t0 = time.perf_counter()
    compilation.compile_generation_step(cfg, robot, dyn, db, conditions, short_run=short)
    walls = {**walls, "step_seconds": time.perf_counter() - t0}
    rows = [
        {"phase": k[0], "program": k[1], "stage": k[2], "seconds": round(v, 3)}
        for k, v in sorted(seconds.items(), key=lambda kv: -kv[1])
    ]
    result = {
        "machine": machine_info(),
        "config": shown_path(args.config),
        "compiled_programs": dict(counts),
        "compile_seconds": {
            ph: round(
                sum(r["seconds"] for r in rows if r["phase"] == ph and r["stage"] == "compile"), 2
            )
            for ph in counts
        },
        "wall_seconds": {k: round(v, 2) for k, v in walls.items()},
        "entries": rows,
    }
    tag = args.tag or result["machine"]["platform"]
    out = Path(args.out_dir) / f"profile_compiles_{tag}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    shown = ("compiled_programs", "compile_seconds", "wall_seconds")
    print(json.dumps({k: result[k] for k in shown}))
    for r in rows[:12]:
        print(r)
    print(f"written: {out}")


if __name__ == "__main__":
    main()
