"""What a user waits for from launch: the command line in fresh processes, cold and warm.

Runs ``evojax-motion`` as a user does, each command in a new process, first with an empty cache
directory of its own (``$EVOJAX_MOTION_JAX_CACHE``: compiled and traced programs, synthesised
demonstrations; `run.cache`) and then again with the cache that its first run filled:

- ``import``: ``python -c "import evojax_motion.run.training"`` (the interpreter and the
  package's modules; JAX and MuJoCo load later, inside each command);
- ``train``: ``train CONFIG`` into a fresh run folder; its summary's phases (``demos_seconds``,
  ``conditions_seconds``, ``compile_seconds``, ``seconds_per_generation`` x generations) beside the
  wall time measured here;
- ``generate`` and ``catch``: one query each on the database that the cold ``train`` wrote
  (``--target`` / ``--ball`` as in the README; on the host's CPU, their default ``--device``).

Wall times are the parent's clock around each process (launch to exit). Targets:
``train configs/catch_ball.yaml`` <= 10 s cold on 2 CPU cores, <= 15 s on one H100, <= 3 s
warm; ``generate`` and ``catch`` <= 3 s cold.

Usage:
    python benchmarks/cold_start.py --config configs/catch_ball.yaml --tag cpu
Writes ``benchmarks/results/cold_start_<tag>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from dynamics_throughput import machine_info  # noqa: E402
from result_files import machine_line, phases_text, write_result  # noqa: E402

from evojax_motion.run.cache import CACHE_ENV  # noqa: E402

# train's summary lines that are phases (seconds)
TRAIN_PHASES = ("demos_seconds", "conditions_seconds", "compile_seconds", "total_seconds")
TARGET = ("0.39", "-0.30", "1.39")  # README's `generate` example [m]
BALL = ("2.4", "-0.5", "1.3", "-2.0", "0.2", "5.0")  # README's `catch` example [m, m/s]


def summary_values(text: str) -> dict[str, float]:
    """The numeric ``key value`` lines of a command's summary (``train``'s table)."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 2:
            try:
                out[parts[0]] = float(parts[1])
            except ValueError:
                continue
    return out


def timed(cmd: list[str], env: dict) -> dict:
    """Run ``cmd`` in a new process: ``{"wall_s", "exit"}`` and its summary values; the output's
    tail is printed when it fails."""
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        print(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-2000:]}", file=sys.stderr)
    return {"wall_s": wall, "exit": done.returncode, "summary": summary_values(done.stdout)}


def run_all(config: str, overrides: list[str], work: Path) -> list[dict]:
    """Cold then warm rows of every command (see the module docstring) in ``work``."""
    cli = [sys.executable, "-m", "evojax_motion.cli.entry"]
    sets = [a for o in overrides for a in ("--set", o)]
    db = work / "train_cold"
    commands = {
        "import": lambda _: [sys.executable, "-c", "import evojax_motion.run.training"],
        "train": lambda phase: [*cli, "train", config, *sets,
                                "--out", str(work / f"train_{phase}")],
        "generate": lambda phase: [*cli, "generate", "--db", str(db), "--target", *TARGET,
                                   "--out", str(work / f"generate_{phase}.csv")],
        "catch": lambda phase: [*cli, "catch", "--db", str(db), "--ball", *BALL,
                                "--out", str(work / f"catch_{phase}.csv")],
    }  # fmt: skip
    rows = []
    for phase in ("cold", "warm"):
        for name in ("import", "train", "generate", "catch"):
            # each command its own cache: cold is empty, warm is what that cold run left
            r = timed(commands[name](phase), {**os.environ, CACHE_ENV: str(work / f"cache_{name}")})
            row = {"command": name, "cache": phase, "wall_s": r["wall_s"], "exit": r["exit"]}
            if name == "train":
                row["phases"] = {k: r["summary"][k] for k in TRAIN_PHASES if k in r["summary"]}
                gens, per = (
                    r["summary"].get("generations"),
                    r["summary"].get("seconds_per_generation"),
                )
                if gens is not None and per is not None:
                    row["phases"]["generations_seconds"] = gens * per
            rows.append(row)
            print(row, flush=True)
    return rows


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/catch_ball.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cold_start-") as tmp:
        rows = run_all(args.config, args.set, Path(tmp))
    m = machine_info()
    result = {"machine": m, "config": args.config, "overrides": args.set, "rows": rows}
    md = [
        machine_line(m),
        "",
        "| command | cache | wall s | exit | train phases (s) |",
        "|---|---|---:|---:|---|",
    ]
    for r in rows:
        phases = phases_text(r.get("phases", {}))
        md.append(f"| {r['command']} | {r['cache']} | {r['wall_s']:.1f} | {r['exit']} | {phases} |")
    write_result(
        Path(args.out_dir) / f"cold_start_{args.tag or m['platform']}", result, "\n".join(md)
    )
    return result


if __name__ == "__main__":
    main()
