"""Render BENCHMARKS.md: the current figures, one table per benchmark, from benchmarks/results/.

Usage: ``python benchmarks/make_report.py`` rewrites BENCHMARKS.md; ``--check`` only says whether
it is up to date (exit status 1 if not). No figure is typed by hand: every row is read from one
result file, named in the row, and each table lists the machine, date and command of its files.

``benchmarks/results/`` holds one current file per benchmark and machine kind: a new measurement
replaces the file it supersedes (git keeps the old one), and what was tried and why it won or
lost goes to CHANGELOG.md. Every file there must be rendered by a section below
(`render` raises otherwise), so that the page and the folder cannot drift apart.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from result_files import latency_ms, phases_text  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "BENCHMARKS.md"
MAX_LINES = 330  # the page stays a summary of the current figures
BY_SOURCE_ROWS = 3  # functions listed per trace
NOT_RECORDED = "not recorded"
# What a file does not record about itself but a reader needs (shown under its table). Every
# key must name a file in results/ (tests/benchmark_scripts/test_make_report.py).
NOTES = {
    "sharded_generations_h200x4_1m.json": "the unsharded point only: the call's time limit "
    "ended it before the 4-device point",
    "optimality_cpu_fast.json": "Newton with the paper config's `search_stride` and "
    "`max_free_per_joint`",
    "online_quality.json": "`python benchmarks/online_quality.py --run runs/paper`, the run of "
    "`evojax-motion train configs/catch_ball.yaml --out runs/paper` on 2 CPU cores",
}


class Sources:
    """The result files a rendering read, by name (to check that every file is rendered)."""

    def __init__(self, results: Path) -> None:
        self.results = results
        self.used: set[str] = set()

    def load(self, pattern: str) -> list[tuple[str, dict]]:
        """``(file name, parsed JSON)`` of every ``results/<pattern>``, sorted by name."""
        found = []
        for path in sorted(self.results.glob(pattern)):
            self.used.add(path.name)
            if path.suffix == ".json":
                found.append((path.name, json.loads(path.read_text())))
        return found

    def mark(self, pattern: str) -> list[str]:
        """Names of the files matching ``pattern`` (read by another section's JSON or shown)."""
        names = [p.name for p in sorted(self.results.glob(pattern))]
        self.used.update(names)
        return names


def machine_label(m: dict | str | None) -> str:
    """A short name of the machine of a result's ``machine`` record: ``"2 CPUs, AMD EPYC"``,
    ``"H100"``, ``"2 x H200"``; records from before the scripts wrote one give what they have."""
    if not isinstance(m, dict):
        return f"CPU ({m})" if m else f"machine {NOT_RECORDED}"
    kind = m.get("device_kind") or ", ".join(m.get("devices", [])) or m.get("platform", "?")
    if kind.startswith("cpu"):
        model = m.get("cpu_model")
        count = m.get("cpu_count")
        label = f"{count} CPUs" if count else "CPU"
        return label + (f", {model}" if model else "")
    kind = kind.removeprefix("NVIDIA ").split(" ")[0]
    n = m.get("device_count", 1)
    return f"{n} x {kind}" if n > 1 else kind


def date_of(m: dict | str | None) -> str:
    """``YYYY-MM-DD`` of a ``machine`` record (UTC)."""
    return str(m["date"])[:10] if isinstance(m, dict) and m.get("date") else NOT_RECORDED


def table(header: str, rows: Iterable[Sequence[object]], align: str) -> list[str]:
    """A markdown table: ``header`` the column names separated by ``" | "``, ``align`` one
    letter per column, ``l`` or ``r``."""
    rule = "|" + "|".join("---" if a == "l" else "---:" for a in align) + "|"
    lines = [f"| {header} |", rule]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def provenance(found: list[tuple[str, dict]]) -> list[str]:
    """One line per file: its machine, JAX version, date, command and XLA flags where set, and
    its entry of `NOTES`."""
    out = []
    for name, d in found:
        m = d.get("machine")
        rec = m if isinstance(m, dict) else {}
        line = f"- `{name}`: {machine_label(m)}"
        line += f", jax {rec['jax']}" if rec.get("jax") else ""
        if rec.get("date") or rec.get("command"):
            line += f", {date_of(m)}; "
            line += f"`{rec['command']}`" if rec.get("command") else f"command {NOT_RECORDED}"
        else:
            line += f"; date and command {NOT_RECORDED}"
        line += f"; `XLA_FLAGS={rec['xla_flags']}`" if rec.get("xla_flags") else ""
        line += f"; {NOTES[name]}" if name in NOTES else ""
        out.append(line)
    return out


def section(title: str, intro: str, body: list[str], found: list[tuple[str, dict]]) -> list[str]:
    if not body:
        return []
    lines = [f"## {title}", ""]
    lines += [intro, ""] if intro else []
    return [*lines, *body, "", *provenance(found), ""]


def _pct(x: float) -> str:
    return f"{100 * x:.4f} %" if abs(x) < 0.01 else f"{100 * x:.2f} %"


def _g(x: float | None, digits: int = 3) -> str:
    if x is None:
        return "-"
    return f"{x:.{digits}g}" if abs(x) < 10 ** max(digits, 4) else f"{x:.2e}"


# --- generations_per_sec.py -----------------------------------------------------------------

FIRST_GENERATION_KEYS = ("to_first_generation_s", "demos_s", "conditions_s", "compile_wait_s")


def paper_scale(src: Sources) -> list[str]:
    src.mark("generations_per_sec_*.md")  # the script's own rendering of the same JSON
    found = [(n, d) for n, d in src.load("generations_per_sec_*.json") if "_sweep" not in n]
    rows, base, first, timed, gapped = [], [], [], set(), set()
    for name, d in found:
        s = d["sweep"][0]
        gap = d.get("gap") or {}
        gapped |= {gap["conditions"]} if gap else set()
        rows.append(
            [
                f"`{name}`",
                machine_label(d["machine"]),
                s["conditions"],
                f"{s['compile_s']:.1f}",
                f"{1e3 * s['seconds_per_generation']:.1f}",
                _g(s["generations_per_s"]),
                _pct(gap["median_gap"]) if gap else "-",
                _pct(gap["p95_gap"]) if gap else "-",
            ]
        )
        timed |= {b["conditions_timed"] for b in (d.get("baseline") or {}).values()}
        for b, r in (d.get("baseline_ratios") or {}).items():
            base.append(
                [f"`{name}`", b, f"{r['seconds_per_generation']:.2f}", f"{r['speedup']:.1f}x"]
            )
        fg = d.get("first_generation") or {}
        for run, r in fg.items():
            if isinstance(r, dict):
                first.append(
                    [f"`{name}`", run.replace("_", " ")]
                    + [f"{r[k]:.1f}" for k in FIRST_GENERATION_KEYS]
                    + [f"{r['first_generation_s']:.2f}"]
                )
    body = table(
        (
            "file | machine | conditions | compile s | ms / generation | "
            "generations / s | median gap | p95 gap"
        ),
        rows,
        "llrrrrrr",
    )
    if base:
        body += [
            "",
            "The baseline a user would write: SciPy SLSQP per condition (float64; gradients by "
            "MuJoCo finite differences or JAX), one process or a pool over all cores, timed on "
            f"{' / '.join(map(str, sorted(timed)))} conditions and scaled to a generation:",
            "",
            *table("file | SLSQP baseline | s / generation | ours faster by", base, "llrr"),
        ]
    if first:
        body += [
            "",
            "Time to the end of generation 1 of `evojax-motion train configs/catch_ball.yaml`, "
            "a fresh process each (cold: empty compilation cache):",
            "",
            *table(
                (
                    "file | run | to first generation s | demonstrations s | "
                    "conditions s | compile wait s | generation s"
                ),
                first,
                "llrrrrr",
            ),
        ]
    return section(
        "Generations per second at paper scale (`benchmarks/generations_per_sec.py`)",
        "`configs/catch_ball.yaml` (300 conditions, T = 100, BFGS); the median generation after "
        "the first. Gap: (ours - SLSQP) / SLSQP of the float64 eq. 5 cost on the first "
        f"generation's problems of {' / '.join(map(str, sorted(gapped)))} conditions "
        "(negative: ours is lower).",
        body,
        found,
    )


def sweeps(src: Sources) -> list[str]:
    found = src.load("generations_per_sec_*_sweep.json")
    rows = [
        [
            f"`{name}`",
            machine_label(d["machine"]),
            f"{s['conditions']:,}",
            f"{1e3 * s['seconds_per_generation']:.1f}",
            f"{1e6 * s['seconds_per_generation'] / s['conditions']:.2f}",
            f"{s['peak_memory_bytes'] / 2**30:.1f}",
            f"{s['compile_s']:.1f}",
        ]
        for name, d in found
        for s in d["sweep"]
    ]
    return section(
        "Generations per second by condition count (`benchmarks/generations_per_sec.py`)",
        "The paper's configuration at more conditions (the median generation after the first; "
        "from 2,048 conditions the neighbour search uses candidate lists). Ideal scaling: the "
        "same time per condition at every size.",
        table(
            (
                "file | machine | conditions | ms / generation | us / condition | "
                "peak GiB | compile s"
            ),
            rows,
            "llrrrrr",
        ),
        found,
    )


def sharded(src: Sources) -> list[str]:
    src.mark("sharded_generations_*.md")
    found = src.load("sharded_generations_*.json")
    rows = [
        [
            f"`{name}`",
            machine_label(d["machine"]),
            f"{p['conditions']:,}",
            p.get("step", "sharded"),
            p["devices"],
            f"{p['compile_s']:.1f}",
            f"{p['seconds_per_generation']:.3f}",
            *(
                "-" if x is None else f"{x:.2f}"
                for x in (p.get("speedup"), (p.get("vs_unsharded") or {}).get("time_ratio"))
            ),
            f"{max(p['peak_memory_bytes']) / 2**30:.1f}",
            f"{p['db_cost_mean'][-1]:.4f}",
        ]
        for name, d in found
        for p in d["points"]
    ]
    return section(
        "Several GPUs (`benchmarks/sharded_generations.py`)",
        "One process drives every device; each point runs in a process of its own. `unsharded`: "
        "the one-device step as `train` runs it (two programs), the reference of the time ratio.",
        table(
            (
                "file | machine | conditions | step | devices | compile s | s / generation | "
                "speed-up | time over unsharded | peak GiB / device | final `db_cost_mean`"
            ),
            rows,
            "llrlrrrrrrr",
        ),
        found,
    )


def train_loop(src: Sources) -> list[str]:
    src.mark("train_loop_*.md")
    found = src.load("train_loop_*.json")
    rows = [
        [
            f"`{name}`",
            machine_label(d["machine"]),
            r["checkpoint_every"],
            f"{1e3 * r['wall_s']:.1f}",
            _g(r["generations_per_s"]),
        ]
        for name, d in found
        for r in d["rows"]
    ]
    return section(
        "A training run's generations per second (`benchmarks/train_loop.py`)",
        "`evojax-motion train configs/catch_ball.yaml` with its files (metrics every generation, "
        "an orbax checkpoint every `train.checkpoint_every` generations); wall time between "
        "generation results, from `metrics.jsonl`.",
        table(
            "file | machine | checkpoint every | ms / generation | generations / s",
            rows,
            "llrrr",
        ),
        found,
    )


def cold_start(src: Sources) -> list[str]:
    src.mark("cold_start_*.md")
    found = src.load("cold_start_*.json")

    rows = []
    for name, d in found:
        by = {(r["command"], r["cache"]): r for r in d["rows"]}
        for command in dict.fromkeys(r["command"] for r in d["rows"]):
            cold, warm = by.get((command, "cold")), by.get((command, "warm"))
            both = (cold or {}, warm or {})
            rows.append([
                f"`{name}`", machine_label(d["machine"]), command,
                f"{cold['wall_s']:.1f}" if cold else NOT_RECORDED,
                f"{warm['wall_s']:.1f}" if warm else NOT_RECORDED,
                " / ".join(filter(None, (phases_text(r.get("phases", {})) for r in both))),
            ])  # fmt: skip
    return section(
        "From launch to result (`benchmarks/cold_start.py`)",
        "Each command in a fresh process, with an empty cache directory (cold) and again with "
        "what that run left (warm); wall time from launch to exit. `train` runs "
        "`configs/catch_ball.yaml` (10 generations; its phases cold / warm); `generate` and "
        "`catch` query its database with the README's target and ball.",
        table("file | machine | command | cold s | warm s | train phases (s)", rows, "lllrrl"),
        found,
    )


# --- quality ----------------------------------------------------------------------------------


def optimality(src: Sources) -> list[str]:
    found = src.load("optimality_*.json")
    rows = []
    for name, d in found:
        ref = d["reference"]
        for variant, v in d["variants"].items():
            g = v["gap"]
            settings = ", ".join(f"{k}={x}" for k, x in v.get("settings", {}).items())
            within = sum(x <= 1e-3 for x in v["gaps"]) / len(v["gaps"])  # the benchmark's 0.1 %
            per_gen = v.get("evolution", {}).get("seconds_per_generation")
            rows.append(
                [
                    f"`{name}`",
                    f"{variant}" + (f" ({settings})" if settings else ""),
                    f"{d['conditions']}",
                    _pct(g["median"]),
                    _pct(g["p95"]),
                    _pct(g["max"]),
                    f"{100 * within:.1f} %",
                    f"{v['iterations']['median']:.0f}",
                    _g(v["run_s"]),
                    _g(per_gen),
                    f"{ref['wall_s_per_condition_median']:.3f}",
                ]
            )
    return section(
        "Optimality gap against float64 SLSQP (`benchmarks/optimality.py`)",
        "The first conditions of generation 1 of a config's run (default "
        "`configs/catch_ball.yaml`, T = 100), each optimiser variant against SciPy SLSQP in "
        "float64 from the same start "
        "(gap as above). Within: the share of problems whose cost is at most SLSQP's + 0.1 %; "
        "run s: the optimiser on all of them; s / generation: the config's evolution with that "
        "variant's compiler (`--evolution`).",
        table(
            (
                "file | variant | conditions | median gap | p95 gap | max gap | within | "
                "iterations | run s | s / generation | SLSQP s / condition"
            ),
            rows,
            "llrrrrrrrrr",
        ),
        found,
    )


def online_latency(src: Sources) -> list[str]:
    found = src.load("online_latency_*.json")
    rows = []
    for name, d in found:
        q = d["single_query"]["end_to_end"]
        single = f"{q['p50_ms']:.2f} / {q['p99_ms']:.2f}"
        for b, p in zip(d["batched"], d["batched_projection"], strict=True):
            rows.append(
                [
                    f"`{name}`",
                    machine_label(d["machine"]),
                    single,
                    f"{b['batch']:,}",
                    f"{b['targets_per_s']:,.0f}",
                    f"{p['targets_per_s']:,.0f}",
                ]
            )
            single = ""
    return section(
        "Online latency (`benchmarks/online_latency.py`)",
        "Answering new targets by interpolation in a database of 611 demonstrations: one query "
        "at a time (end to end, including the host), and batches (targets per second, without "
        "and with the joint-limit projection forced on every target).",
        table(
            (
                "file | machine | one query p50 / p99 ms | batch | targets / s | "
                "with projection, targets / s"
            ),
            rows,
            "llrrrr",
        ),
        found,
    )


def online_quality(src: Sources) -> list[str]:
    found = src.load("online_quality*.json")
    images = src.mark("online_quality*.png")
    rows = [
        [
            f"`{name}`",
            c,
            _g(v["value"]),
            v.get("limit", "-"),
            "yes" if v["pass"] else "no",
        ]
        for name, d in found
        for c, v in d["criteria"].items()
        if not isinstance(v["value"], list)  # the medians' pair: the cost row below
    ]
    for name, d in found:
        c = d["cost"]
        rows.append(
            [
                f"`{name}`",
                "median eq. 5 cost: learned / optimised / human-only",
                f"{c['learned_interp']['p50']:.2f} / {c['optimised']['p50']:.2f} / "
                f"{c['human_interp']['p50']:.2f}",
                "-",
                "yes" if d["criteria"]["learned_below_human_median"]["pass"] else "no",
            ]
        )
    body = table("file | criterion | value | limit | met", rows, "llrrl")
    body += ["", *(f"![{i}](benchmarks/results/{i})" for i in images)]
    return section(
        "Online quality (`benchmarks/online_quality.py`)",
        "Motions generated online from a learned database against each target optimised "
        "directly (eq. 3-5) and against the human-only interpolation; the criteria are the "
        "benchmark's own (its `criteria` field).",
        body,
        found,
    )


def catch_success(src: Sources) -> list[str]:
    src.mark("catch_success_*.md")
    found = src.load("catch_success_*.json")
    rows = []
    for name, d in found:
        for db, r in d["databases"].items():
            opt = r.get("optimised")
            rows.append(
                [
                    f"`{name}`",
                    f"{db} ({r['entries']})",
                    f"{r['caught']} / {r['reachable']} = {r['success_rate']:.1%}",
                    f"{r['unreachable']} / {r['infeasible_plans']}",
                    f"{_g(r['cost']['mean'])} / {_g(r['cost']['median'])}",
                    f"{_g(r['hand_rms_mm']['p50'])} / {_g(r['hand_max_mm'])}",
                    "-" if r["at_torque_limit"] is None else f"{r['at_torque_limit']:.2%}",
                    latency_ms(r["planning_s"]),
                    latency_ms(r.get("planning_after_idle_s")),
                    "-" if not opt else _g(opt["ratio_online_over_optimised"]["p50"]),
                ]
            )
    return section(
        "Catch success in physics (`benchmarks/catch_success.py`)",
        "Random throws (a person 2-4 m away, release 1-2 m high, 0.5-1.2 s flight, aimed at the "
        "demonstrations' region), each planned online and executed in MuJoCo by the tracking "
        "controller (`docs/simulation.md`); success: caught / reachable throws; cost: eq. 5 "
        "(Fig. 5) of the planned motions [N^2 m^2 s]; last column: online / optimisation "
        "compiler cost on the same basis and BCs, median over a subset. Planning is timed back "
        "to back and again right after the previous throw's simulation (after idle).",
        table(
            "file | database (entries) | caught / reachable | unreachable / infeasible | "
            "cost mean / median | hand RMS p50 / max mm | steps at torque limit | "
            "plan p50 / p99 ms | after idle | online / optimised",
            rows,
            "llrrrrrrrr",
        ),
        found,
    )


# --- where the time goes ----------------------------------------------------------------------


def stage_table(found: list[tuple[str, dict]], scale: float = 1e3) -> list[str]:
    """Stages as rows, files as columns: the median time of each stage [ms]."""
    stages: list[str] = []
    for _, d in found:
        stages += [s for s in d["stages"] if s not in stages]
    rows = [
        [f"`{s}`"]
        + [
            f"{scale * d['stages'][s]['median_s']:.3g}" if s in d["stages"] else "-"
            for _, d in found
        ]
        for s in stages
    ]
    header = " | ".join(["stage", *(f"`{n}` ms" for n, _ in found)])
    return table(header, rows, "l" + "r" * len(found))


def profile_generation(src: Sources) -> list[str]:
    found = src.load("profile_generation_*.json")
    return section(
        "A generation's stages, timed one by one (`benchmarks/profile_generation.py`)",
        "Each stage of the generation step compiled and timed on its own at the size named in "
        "its command (median of the repeats).",
        stage_table(found),
        found,
    )


def trace_generation(src: Sources) -> list[str]:
    found = src.load("trace_generation_*.json")
    rows, sources = [], []
    for name, d in found:
        t = d.get("trace") or {}  # None where no device stream was traced (CPU)
        rows.append(
            [
                f"`{name}`",
                machine_label(d["machine"]),
                f"{d['conditions']:,}",
                f"{d['us_per_condition']:.2f}",
            ]
            + (
                [
                    f"{t['kernels_per_generation']:,.0f}",
                    f"{t['busy_us_per_generation'] / 1e3:.2f}",
                    f"{t['span_us_per_generation'] / 1e3:.2f}",
                ]
                if t
                else ["-"] * 3
            )
        )
        busy = t.get("busy_us_per_generation")
        sources += [
            [
                f"`{name}`",
                f"`{r['source']}`",
                f"{r['kernels_per_generation']:g}",
                f"{r['us_per_generation']:.1f}",
                f"{r['us_per_generation'] / busy:.0%}",
            ]
            for r in t.get("by_source", [])[:BY_SOURCE_ROWS]
        ]
    body = table(
        "file | machine | conditions | us / condition | kernels / generation | busy ms | span ms",
        rows,
        "llrrrrr",
    )
    if sources:
        body += [
            "",
            f"The device's kernels by the project function they come from (the "
            f"{BY_SOURCE_ROWS} largest per trace; share of the busy time):",
            "",
            *table(
                "file | function | kernels / generation | us / generation | share",
                sources,
                "llrrr",
            ),
        ]
    return section(
        "Where a generation's device time goes (`benchmarks/trace_generation.py`)",
        "Timed without the profiler (us / condition), then a `jax.profiler` trace of the "
        "busiest device stream: busy is the time its kernels run, span from the first kernel's "
        "start to the last one's end, per generation.",
        body,
        found,
    )


def linearity(src: Sources) -> list[str]:
    src.mark("linearity_*.md")
    found = src.load("linearity_*.json")
    rows = []
    for name, d in found:
        f = d["fit"]
        rows += [
            [f"`{name}`", "fit: L per optimiser batch / C per condition",
             f"{1e3 * f['L_s']:.2f} ms / {1e6 * f['C_s']:.2f} us"],
            [f"`{name}`", "smallest / largest size, time per condition", f"{d['ratio']:.2f}x"],
            [f"`{name}`", f"L for a ratio of {1 + d['tolerance']:.1f}x at this C",
             f"{1e3 * d['L_bound_s']:.2f} ms"],
        ]  # fmt: skip
        what = d.get("what_if") or {}
        rows += [
            [f"`{name}`", f"ratio with {w['part']} at zero cost", f"{w['ratio_without']:.2f}x"]
            for w in what.get("groups", [])[:4] + what.get("functions", [])[:1]
        ]
    # The fit's own record: the traces' machine and latest date, and the command that remakes it.
    made = [
        (
            name,
            {
                "machine": {
                    "device_kind": d["sizes"][-1]["device"],
                    "date": max(s["date"] for s in d["sizes"]),
                    "command": "python benchmarks/linearity.py "
                    + " ".join(d["traces"])
                    + f" --tag {name.removeprefix('linearity_').removesuffix('.json')}",
                }
            },
        )
        for name, d in found
    ]
    return section(
        "Time per condition against the number of conditions (`benchmarks/linearity.py`)",
        "A generation fitted to `T(m) = batches(m) L + m C` (`batches`: the optimiser's chunks "
        "of `compiler.max_batch`) from the traces in the command; the what-ifs remove a part's "
        "kernel time at both sizes (an optimistic bound).",
        table("file | quantity | value", rows, "llr"),
        made,
    )


def cholesky_kernels(src: Sources) -> list[str]:
    src.mark("cholesky_kernels_*.md")
    found = src.load("cholesky_kernels_*.json")
    rows = [
        [
            f"`{name}`",
            f"{r['batch']:,}",
            r["solver"],
            f"{r['us_per_solve']:.1f}",
            f"{r['compile_s']:.1f}",
            f"{r['max_rel_error']:.1e}",
        ]
        for name, d in found
        for r in d["rows"]
    ]
    return section(
        "The optimiser's Cholesky solve: XLA against a Pallas kernel "
        "(`benchmarks/cholesky_kernels.py`)",
        "31 dependent solves of 14 unknowns per call, as in a generation's optimiser passes.",
        table(
            "file | problems | solver | us / solve | compile s | max error vs float64",
            rows,
            "lrlrrr",
        ),
        found,
    )


def compiles(src: Sources) -> list[str]:
    found = src.load("profile_compiles_*.json")
    rows = [
        [f"`{name}`", phase, d["compiled_programs"][phase], f"{s:.1f}"]
        for name, d in found
        for phase, s in d["compile_seconds"].items()
    ]
    return section(
        "What a cold start compiles (`benchmarks/profile_compiles.py`)",
        "The programs a new `train` run compiles, by phase, without a compilation cache.",
        table("file | phase | programs | compile s", rows, "llrr"),
        found,
    )


def profile_online(src: Sources) -> list[str]:
    found = src.load("profile_online_*.json")
    return section(
        "An online batch's stages (`benchmarks/profile_online.py`)",
        "Each stage of answering a batch of targets, compiled and timed on its own.",
        stage_table(found),
        found,
    )


def small_eigh(src: Sources) -> list[str]:
    found = src.load("small_eigh_*.json")
    return section(
        "Batched small eigen-decompositions (`benchmarks/small_eigh.py`)",
        "The neighbour PCA's decompositions of a generation at the batch size in the command "
        "(10 x 10 Gram matrices), by each method.",
        stage_table(found),
        found,
    )


def dynamics(src: Sources) -> list[str]:
    found = src.load("dynamics_throughput_*.json")
    rows = []
    for name, d in found:
        m = machine_label(d["machine"])
        if d.get("mujoco_c"):
            rows.append([f"`{name}`", m, "C `mj_inverse`, Python loop",
                         _g(d["mujoco_c"]["evals_per_s"]), "-", "-", "-"])  # fmt: skip
        for backend, b in d["backends"].items():
            inv, vg = b["inverse"], b.get("value_and_grad", {})
            rows.append(
                [
                    f"`{name}`",
                    m,
                    backend,
                    _g(inv["evals_per_s"]),
                    _g(vg.get("evals_per_s")),
                    _g(inv.get("flops_per_eval")),
                    f"{vg['compile_s']:.1f}" if vg else "-",
                ]
            )
    return section(
        "Inverse dynamics throughput (`benchmarks/dynamics_throughput.py`)",
        "Evaluations per second of `mahru_arm`'s inverse dynamics (float32), vmapped over the "
        "states in the command; FLOPs from XLA's cost analysis.",
        table(
            (
                "file | machine | backend | inverse evals / s | "
                "value + grad evals / s | FLOP / eval | compile value + grad s"
            ),
            rows,
            "lllrrrr",
        ),
        found,
    )


def import_ue_adl(src: Sources) -> list[str]:
    found = src.load("import_ue_adl*.json")
    rows = [
        [
            f"`{name}`",
            robot,
            f"{s['imported']} / {s['trials']}",
            f"{1e3 * s['rms_error_median_m']:.1f} / {1e3 * s['rms_error_p95_m']:.1f} / "
            f"{1e3 * s['rms_error_max_m']:.1f}",
            s["trials_touching_limits"],
            f"{s['wall_s']:.0f}",
        ]
        for name, d in found
        for robot, r in d["robots"].items()
        for s in [r["summary"]]
    ]
    return section(
        "Importing real motion capture (`benchmarks/import_ue_adl.py`)",
        "The UE ADL reaching data set (10 subjects x 2 tasks x 5 trials) retargeted to each "
        "robot (`docs/importing.md`).",
        table(
            (
                "file | robot | imported | key-point RMS median / p95 / max mm | "
                "trials touching a limit | wall s"
            ),
            rows,
            "llrrrr",
        ),
        found,
    )


SECTIONS: tuple[Callable[[Sources], list[str]], ...] = (
    paper_scale,
    sweeps,
    sharded,
    train_loop,
    cold_start,
    optimality,
    online_latency,
    online_quality,
    catch_success,
    profile_generation,
    trace_generation,
    linearity,
    cholesky_kernels,
    compiles,
    profile_online,
    small_eigh,
    dynamics,
    import_ue_adl,
)

HEADER = [
    "# Benchmarks",
    "",
    "The current figures, one table per benchmark. Every row is read from the file in",
    "`benchmarks/results/` it names; under each table, the machine, date and command of each",
    "file. Made by `python benchmarks/make_report.py`; what was tried before and why it was kept",
    "or dropped: `CHANGELOG.md`. The 2-core CPU machines are shared and noisy: compare figures",
    "within one file rather than across files.",
    "",
]


def render(results: Path = RESULTS) -> str:
    """The page for the files in ``results``; raises ValueError if a file is left unrendered
    (every result must be current and shown) or the page grows past `MAX_LINES`."""
    src = Sources(results)
    lines = list(HEADER)
    for make in SECTIONS:
        lines += make(src)
    left = sorted(p.name for p in results.iterdir() if p.is_file()) if results.is_dir() else []
    left = [n for n in left if n not in src.used]
    if left:
        raise ValueError(f"{results.name}/: no section renders {', '.join(left)}")
    page = "\n".join(lines).rstrip() + "\n"
    if page.count("\n") > MAX_LINES:
        raise ValueError(f"BENCHMARKS.md: {page.count(chr(10))} lines, expected <= {MAX_LINES}")
    return page


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 if BENCHMARKS.md is out of date")
    args = p.parse_args(argv)
    try:
        page = render()
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.check:
        if PAGE.is_file() and PAGE.read_text() == page:
            return 0
        print("BENCHMARKS.md is out of date: run python benchmarks/make_report.py", file=sys.stderr)
        return 1
    tmp = PAGE.with_name(PAGE.name + ".tmp")
    tmp.write_text(page)
    tmp.replace(PAGE)
    print(f"written: {PAGE.relative_to(ROOT)} ({page.count(chr(10))} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
