"""Render BENCHMARKS.md from the JSON files in benchmarks/results/ (no figure is typed by hand).

Usage: ``python benchmarks/make_report.py`` (rewrites BENCHMARKS.md). Each section names the
script and command that produced its JSON, the machine and the date; rerun that command to
reproduce a figure, then this script to refresh the page.
"""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _load(pattern: str) -> list[tuple[Path, dict]]:
    return [(p, json.loads(p.read_text())) for p in sorted(RESULTS.glob(pattern))]


def cpu_label(machine: dict) -> str:
    """``"2 CPUs, AMD EPYC"`` from a benchmark's ``machine`` record (`dynamics_throughput.
    machine_info`; the CPU model where it was recorded)."""
    model = machine.get("cpu_model")
    return f"{machine.get('cpu_count', '?')} CPUs" + (f", {model}" if model else "")


def _machine(m: dict) -> str:
    kind = m.get("device_kind") or ", ".join(m.get("devices", [])) or m.get("platform", "?")
    extra = f", {cpu_label(m)}" if m.get("cpu_count") else ""
    load = f", load average {m['load_average'][0]:.1f}" if m.get("load_average") else ""
    return f"{kind}{extra}, jax {m.get('jax', '?')}, {str(m.get('date', '?'))[:10]}{load}"


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}"


def dynamics_section() -> list[str]:
    out = ["## Dynamics throughput (`benchmarks/dynamics_throughput.py`)", ""]
    out += [
        "Evaluations per second of inverse dynamics (float32, mahru_arm unless named), "
        "vmapped over N states; FLOPs and bytes per evaluation from XLA's cost analysis.",
        "",
    ]
    for path, d in _load("dynamics_throughput_*.json"):
        m = d["machine"]
        out += [
            f"### {path.name}",
            "",
            f"Machine: {_machine(m)}. "
            f"Command: `{m.get('command', '?')}`. XLA_FLAGS: `{m.get('xla_flags', '')}`",
            "",
        ]
        out += [
            "| backend | inverse evals/s | value+grad evals/s | FLOP/eval | bytes/eval "
            "| compile value+grad s |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        if d.get("mujoco_c"):
            out.append(
                f"| C mj_inverse, Python loop | {_fmt(d['mujoco_c']['evals_per_s'])} "
                "| - | - | - | - |"
            )
        for name, b in d.get("backends", {}).items():
            inv, vg = b.get("inverse", {}), b.get("value_and_grad", {})
            out.append(
                f"| {name} | {_fmt(inv.get('evals_per_s', float('nan')))} "
                f"| {_fmt(vg.get('evals_per_s', float('nan')))} "
                f"| {_fmt(inv.get('flops_per_eval', float('nan')))} "
                f"| {_fmt(inv.get('bytes_per_eval', float('nan')))} "
                f"| {vg.get('compile_s', float('nan')):.1f} |"
            )
        out.append("")
    return out


def markdown_tables(pattern: str, title: str) -> list[str]:
    out = [f"## {title}", ""]
    paths = sorted(RESULTS.glob(pattern))
    out += [f"### {p.name}\n\n{p.read_text().strip()}\n" for p in paths] or [
        "Not measured yet.",
        "",
    ]
    return out


def import_section() -> list[str]:
    out = ["## Importing real motion capture (`benchmarks/import_ue_adl.py`)", ""]
    for _path, d in _load("import_ue_adl*.json"):
        out += [
            f"Data: UE ADL, 10 subjects x 2 tasks x 5 trials. Machine: {_machine(d['machine'])}.",
            "",
            "| robot | imported | key-point RMS median / p95 / max [mm] | within limits | wall s |",
            "|---|---:|---:|---|---:|",
        ]
        for robot, r in d["robots"].items():
            s = r["summary"]
            out.append(
                f"| {robot} | {s['imported']} / {s['trials']} | "
                f"{1e3 * s['rms_error_median_m']:.1f} / {1e3 * s['rms_error_p95_m']:.1f} / "
                f"{1e3 * s['rms_error_max_m']:.1f} | {s['within_joint_limits']} "
                f"| {s['wall_s']:.0f} |"
            )
        out.append("")
    return out


def json_summaries(pattern: str, title: str, keys: list[str]) -> list[str]:
    out = [f"## {title}", ""]
    found = _load(pattern)
    for path, d in found:
        m = d.get("machine", {})
        out += [
            f"### {path.name}",
            "",
            f"Machine: {_machine(m)}. Command: `{m.get('command', '?')}`",
            "",
        ]
        flat = {k: d[k] for k in keys if k in d}
        out += ["```json", json.dumps(flat, indent=1)[:4000], "```", ""]
    return out or [*out, "Not measured yet.", ""]


def optimality_section() -> list[str]:
    out = ["## Optimality gap vs float64 SLSQP (`benchmarks/optimality.py`)", ""]
    for path, d in _load("optimality_*.json"):
        ref = d["reference"]
        out += [
            f"### {path.name}",
            "",
            f"{d['conditions']} conditions, T = {d['samples']}, platform {d['platform']}. "
            f"Reference: {ref['solver']} ({ref['wall_s_per_condition_median']:.3f} s/condition).",
            "Gap = (ours - SLSQP) / SLSQP of the float64 eq. 5 cost (negative: ours is lower).",
            "",
            "| variant | median gap | p95 gap | max gap | iterations (median) | run s |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for name, v in d["variants"].items():
            g = v["gap"]
            out.append(
                f"| {name} | {100 * g['median']:.4f} % | {100 * g['p95']:.3f} % "
                f"| {100 * g['max']:.2f} % | {v['iterations']['median']:.0f} | {v['run_s']:.0f} |"
            )
        out.append("")
    return out or [*out, "Not measured yet.", ""]


BY_SOURCE_ROWS = 8  # functions listed per trace


def trace_section() -> list[str]:
    out = ["## Where a generation's device time goes (`benchmarks/trace_generation.py`)", ""]
    found = _load("trace_generation_*.json")
    if found:
        out += [
            "Timed without the profiler; then a `jax.profiler` trace of the busiest device "
            "stream. Busy: the time its kernels run; span: first kernel's start to last one's "
            "end (per generation, profiled).",
            "",
            "| file | conditions | us / condition | ms / generation | kernels / generation "
            "| busy ms | span ms | busy / span | largest kernels (mean us x per generation) |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
    for path, d in found:
        t = d.get("trace")
        cells = ["-"] * 5
        if t:
            top = "; ".join(
                f"`{k['name'][:40]}` {k['mean_us']:.1f} x {k['per_generation']:g}"
                for k in t["top_kernels"][:3]
            )
            cells = [
                f"{t['kernels_per_generation']:.0f}",
                f"{t['busy_us_per_generation'] / 1e3:.2f}",
                f"{t['span_us_per_generation'] / 1e3:.2f}",
                f"{t['busy_fraction']:.2f}",
                top,
            ]
        out.append(
            f"| {path.name} | {d['conditions']} | {d['us_per_condition']:.2f} "
            f"| {1e3 * d['seconds_per_generation']:.2f} | " + " | ".join(cells) + " |"
        )
    for path, d in found:
        m = d["machine"]
        out.append(
            f"\n{path.name}: {_machine(m)}. Command: `{m.get('command', '?')}`. "
            f"XLA_FLAGS: {('`' + m['xla_flags'] + '`') if m.get('xla_flags') else 'none'}"
        )
    for path, d in found:
        t = d.get("trace") or {}
        if "by_source" not in t:
            continue
        busy = t["busy_us_per_generation"]
        out += [
            f"\n{path.name}, the device's kernels by the project function they come from "
            f"(`by_source`, the {BY_SOURCE_ROWS} largest):",
            "",
            "| function | kernels / generation | us / generation | share of busy |",
            "|---|---:|---:|---:|",
        ]
        out += [
            f"| `{r['source']}` | {r['kernels_per_generation']:g} | {r['us_per_generation']:.1f} "
            f"| {r['us_per_generation'] / busy:.0%} |"
            for r in t["by_source"][:BY_SOURCE_ROWS]
        ]
    return [*out, ""] if found else [*out, "Not measured yet.", ""]


def main() -> None:
    lines = [
        "# Benchmarks",
        "",
        "Every figure below is read from a JSON file in `benchmarks/results/`, written by the",
        "script named in its section, on the machine and date given there. This page is made by",
        "`python benchmarks/make_report.py`. The 2-core CPU machine is shared and noisy:",
        "compare figures as ratios within one JSON, not across files.",
        "",
    ]
    lines += markdown_tables(
        "generations_per_sec_*.md", "Generations per second (`benchmarks/generations_per_sec.py`)"
    )
    lines += [*(RESULTS.parent / "changes.md").read_text().strip().splitlines(), ""]
    lines += markdown_tables(
        "sharded_generations_*.md",
        "Generations per second over several GPUs (`benchmarks/sharded_generations.py`)",
    )
    lines += optimality_section()
    lines += json_summaries(
        "online_latency_*.json",
        "Online latency (`benchmarks/online_latency.py`)",
        ["single_query", "batched", "database", "targets"],
    )
    lines += json_summaries(
        "online_quality*.json",
        "Online quality (`benchmarks/online_quality.py`)",
        [
            "run",
            "targets",
            "criteria",
            "ratio_learned_over_optimised",
            "limit_violations",
            "hand_error_m",
        ],
    )
    lines += json_summaries(
        "profile_generation_*.json",
        "Where a generation's time goes (`benchmarks/profile_generation.py`)",
        ["conditions", "samples", "overrides", "stages", "iterations_median", "iterations_max"],
    )
    lines += trace_section()
    lines += markdown_tables(
        "linearity_*.md", "Linearity in the number of conditions (`benchmarks/linearity.py`)"
    )
    lines += markdown_tables(
        "train_loop_*.md", "A training run's own cost per generation (`benchmarks/train_loop.py`)"
    )
    lines += markdown_tables(
        "cholesky_kernels_*.md",
        "The optimiser's Cholesky solve: XLA against a Pallas kernel "
        "(`benchmarks/cholesky_kernels.py`)",
    )
    lines += json_summaries(
        "profile_online_*.json",
        "Where an online batch's time goes (`benchmarks/profile_online.py`)",
        ["batch", "stages"],
    )
    lines += json_summaries(
        "small_eigh_*.json",
        "Batched small eigen-decompositions (`benchmarks/small_eigh.py`)",
        ["batch", "k", "T", "stages", "sv_max_rel_diff"],
    )
    lines += dynamics_section()
    lines += import_section()
    (ROOT / "BENCHMARKS.md").write_text("\n".join(lines).rstrip() + "\n")
    print(f"written: {ROOT / 'BENCHMARKS.md'}")


if __name__ == "__main__":
    main()
