"""What a training run's generation costs beyond the generation step: its files.

`evojax-motion train` writes after every generation its metrics and, every
``train.checkpoint_every`` generations, an orbax checkpoint (`run.training.run_training`); it queues
the next generation before writing a generation's files, so the two overlap. This runs the
same config once per ``--every`` value (fresh run folders, progress bar and plots off) and
reads each run's ``metrics.jsonl``: the wall time from one generation's result to the next, as
a mean over generations 2 .. N (generation 1 fills the empty slots; a mean, so that a
checkpoint every n-th generation counts), and generations per second. Compare with
`generations_per_sec.py`'s time of the step alone.

Usage:
    python benchmarks/train_loop.py --config configs/catch_ball.yaml --generations 20 \\
        --every 1,10 --tag cpu
Writes ``benchmarks/results/train_loop_<tag>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from result_files import machine_line, write_result  # noqa: E402

from evojax_motion.run.cache import enable_compile_cache  # noqa: E402
from evojax_motion.run.training import METRICS_FILE, run_training  # noqa: E402
from evojax_motion.settings import load_config  # noqa: E402


def loop_times(rows: list[dict]) -> dict:
    """Mean wall time per generation over ``rows[1:]`` (metrics.jsonl rows of consecutive
    generations; from one generation's ``finished_at`` to the next) and its inverse."""
    wall = [b["finished_at"] - a["finished_at"] for a, b in itertools.pairwise(rows)]
    if not wall:
        raise ValueError("loop_times: expected two or more generations")
    w = float(np.mean(wall))
    return {"wall_s": w, "generations_per_s": 1.0 / w}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "catch_ball.yaml"))
    p.add_argument("--generations", type=int, default=20)
    p.add_argument("--every", default="1,10", help="train.checkpoint_every values")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    enable_compile_cache()  # as the command line does: later runs reuse the first's compiles
    rows = []
    for every in [int(x) for x in args.every.split(",") if x]:
        fixed = [f"evolution.generations={args.generations}", "train.plots=false"]
        cfg = load_config(args.config, [*args.set, *fixed, f"train.checkpoint_every={every}"])
        with tempfile.TemporaryDirectory(prefix="train_loop-") as tmp:
            run_training(cfg, Path(tmp) / "run", progress=False)
            lines = (Path(tmp) / "run" / METRICS_FILE).read_text().splitlines()
        r = {"checkpoint_every": every, **loop_times([json.loads(x) for x in lines])}
        rows.append(r)
        print(json.dumps(r), flush=True)
    m = machine_info()
    result = {"machine": m, "config": args.config, "overrides": args.set,
              "generations": args.generations, "rows": rows}  # fmt: skip
    md = [
        machine_line(m),
        "",
        "| checkpoint_every | s / generation | generations / s |",
        "|---:|---:|---:|",
        *(
            f"| {r['checkpoint_every']} | {r['wall_s']:.4f} | {r['generations_per_s']:.3g} |"
            for r in rows
        ),
    ]
    write_result(
        Path(args.out_dir) / f"train_loop_{args.tag or m['platform']}", result, "\n".join(md)
    )
    return result


if __name__ == "__main__":
    main()
