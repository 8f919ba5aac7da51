"""What a training run's generation costs beyond the generation step: its files.

`evojax-motion train` writes after every generation its metrics and, every
``train.checkpoint_every`` generations, an orbax checkpoint (`train.run_training`). This runs
the same config once per ``--every`` value (fresh run folders, the progress bar off, plots off)
and reads each run's ``metrics.jsonl``: the step's own time (``seconds``, dispatch to result)
and the wall time from one generation's end to the next (``finished_at``), whose difference is
the loop's own cost (copying the database to the host, the checkpoint, the metrics file).
Means over generations 2 .. N (generation 1 fills the empty slots).

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

from evojax_motion.compile_cache import enable_compile_cache  # noqa: E402
from evojax_motion.config import load_config  # noqa: E402
from evojax_motion.train import METRICS_FILE, run_training  # noqa: E402


def loop_times(rows: list[dict]) -> dict:
    """Means over ``rows[1:]`` (metrics.jsonl rows of consecutive generations) of the step's
    ``seconds`` and of the wall time between generation ends (means, not medians: a checkpoint
    every n-th generation is part of the average cost); their difference, the loop's."""
    step = [r["seconds"] for r in rows[1:]]
    wall = [b["finished_at"] - a["finished_at"] for a, b in itertools.pairwise(rows)]
    if not step:
        raise ValueError("loop_times: expected two or more generations")
    s, w = float(np.mean(step)), float(np.mean(wall))
    return {"step_s": s, "wall_s": w, "loop_s": w - s, "generations_per_s": 1.0 / w}


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
        "| checkpoint_every | step s | generation to generation s | loop's own s "
        "| generations / s |",
        "|---:|---:|---:|---:|---:|",
        *(
            f"| {r['checkpoint_every']} | {r['step_s']:.4f} | {r['wall_s']:.4f} "
            f"| {r['loop_s']:.4f} | {r['generations_per_s']:.3g} |"
            for r in rows
        ),
    ]
    write_result(
        Path(args.out_dir) / f"train_loop_{args.tag or m['platform']}", result, "\n".join(md)
    )
    return result


if __name__ == "__main__":
    main()
