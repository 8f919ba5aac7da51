"""Summaries of `jax.profiler` traces (Chrome trace format): what the device ran, and when.

Standard library only, no side effects: `trace_generation.py` uses it, and the tests.
"""

from __future__ import annotations

import collections
import gzip
import itertools
import json
import re
from pathlib import Path

TOP = 25  # kernels, host events and gaps listed


def summarise_trace(events: list[dict], generations: int, hlo_text: str | None = None) -> dict:
    """Summary of a Chrome-format trace (``traceEvents``) of ``generations`` generations.

    Complete events (``ph == "X"``) of processes whose name holds ``"GPU"`` are device kernels
    and copies, grouped by stream (thread); the stream with the most events is summarised as the
    device's. All other complete events are host events. Times in microseconds, per generation
    where named so. With ``hlo_text`` (the compiled program's optimised HLO, ``as_text()``), the
    device's kernels are also totalled by the project function they come from
    (``by_source``, `kernel_sources`).
    """
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("name") == "process_name"}
    threads = {
        (e["pid"], e["tid"]): e["args"]["name"] for e in events if e.get("name") == "thread_name"
    }
    done = [e for e in events if e.get("ph") == "X"]
    streams: dict = {}
    host: dict = {}
    for e in done:
        if "GPU" in names.get(e["pid"], ""):
            streams.setdefault(threads.get((e["pid"], e["tid"]), str(e["tid"])), []).append(e)
        else:
            entry = host.setdefault(e["name"], [0, 0.0])
            entry[0] += 1
            entry[1] += e["dur"]
    if not streams:
        raise ValueError("the trace holds no device events (is this a GPU run?)")
    stream, kernels = max(streams.items(), key=lambda kv: len(kv[1]))
    kernels = sorted(kernels, key=lambda e: e["ts"])
    busy = sum(e["dur"] for e in kernels)
    span = kernels[-1]["ts"] + kernels[-1]["dur"] - kernels[0]["ts"]
    gaps = [
        (b["ts"] - (a["ts"] + a["dur"]), a["name"], b["name"])
        for a, b in itertools.pairwise(kernels)
    ]
    by_name: dict = {}
    for e in kernels:
        entry = by_name.setdefault(e["name"], [0, 0.0])
        entry[0] += 1
        entry[1] += e["dur"]
    top = sorted(by_name.items(), key=lambda kv: -kv[1][1])[:TOP]
    g = float(generations)
    extra = {}
    if hlo_text is not None:
        sources = kernel_sources(hlo_text)
        by_source: dict = {}
        for name, (n, t) in by_name.items():
            entry = by_source.setdefault(sources.get(name, NOT_IN_HLO), [0, 0.0])
            entry[0] += n
            entry[1] += t
        extra["by_source"] = [
            {"source": k, "kernels_per_generation": n / g, "us_per_generation": round(t / g, 1)}
            for k, (n, t) in sorted(by_source.items(), key=lambda kv: -kv[1][1])
        ]
    return {
        "stream": stream,
        "kernels_per_generation": len(kernels) / g,
        "busy_us_per_generation": busy / g,
        "span_us_per_generation": span / g,
        "busy_fraction": busy / span if span > 0 else float("nan"),
        "idle_us_per_generation": sum(max(gap, 0.0) for gap, _, _ in gaps) / g,
        "largest_gaps": [
            {"us": round(gap, 1), "after": a[:80], "before": b[:80]}
            for gap, a, b in sorted(gaps, reverse=True)[:TOP]
        ],
        "top_kernels": [
            {"name": k[:100], "per_generation": n / g, "mean_us": round(t / n, 2)}
            for k, (n, t) in top
        ],
        "top_host_events": [
            {"name": k[:100], "per_generation": n / g, "us_per_generation": round(t / g, 1)}
            for k, (n, t) in sorted(host.items(), key=lambda kv: -kv[1][1])[:TOP]
        ],
        **extra,
    }


def merge_stages(stages: dict[str, dict]) -> dict:
    """One summary of programs traced one after another (``{name: summarise_trace(...)}``, the
    same generations each): kernels, busy time and idle time per generation added up, the
    programs' largest kernels together (``top_kernels``, named ``program:kernel``), ``by_source``
    merged by source (each program's kernels traced to its own HLO: two programs
    may name different kernels alike), and each program's own summary under ``stages``. The
    span is the sum of the programs' spans (they are traced apart, so the gap between them is
    not measured)."""
    sums = ("kernels_per_generation", "busy_us_per_generation", "span_us_per_generation",
            "idle_us_per_generation")  # fmt: skip
    out: dict = {k: sum(st[k] for st in stages.values()) for k in sums}
    out["busy_fraction"] = (
        out["busy_us_per_generation"] / out["span_us_per_generation"]
        if out["span_us_per_generation"] > 0
        else float("nan")
    )
    kernels = [
        dict(k, name=f"{name}:{k['name']}")
        for name, st in stages.items()
        for k in st["top_kernels"]
    ]
    out["top_kernels"] = sorted(kernels, key=lambda k: -k["mean_us"] * k["per_generation"])[:TOP]
    if all("by_source" in st for st in stages.values()):
        by_source: dict = {}
        for st in stages.values():
            for row in st["by_source"]:
                entry = by_source.setdefault(row["source"], [0.0, 0.0])
                entry[0] += row["kernels_per_generation"]
                entry[1] += row["us_per_generation"]
        out["by_source"] = [
            {"source": k, "kernels_per_generation": n, "us_per_generation": round(t, 1)}
            for k, (n, t) in sorted(by_source.items(), key=lambda kv: -kv[1][1])
        ]
    out["stages"] = stages
    return out


NOT_IN_HLO = "(not in the HLO)"  # copies, library kernels (e.g. cuBLAS) named otherwise
NO_SOURCE = "(no project frame)"
_COMPUTATION = re.compile(r"^(?:ENTRY )?%([\w.\-]+) .*\{$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%([\w.\-]+) = ")


def kernel_sources(hlo_text: str, package: str = "evojax_motion") -> dict[str, str]:
    """``{kernel name: "module:function"}`` from a compiled program's optimised HLO text.

    A GPU kernel is named after its fusion (or its deduplicated name), dots and dashes as
    underscores. Its source is the most common innermost frame inside ``package`` among the
    stack frames (the HLO's ``StackFrames`` table) of the instructions it fuses, so a kernel
    that fuses code of several functions is counted once, under the one most of it comes from.
    Instructions without a frame in ``package`` count as `NO_SOURCE`.
    """
    tables: dict[str, dict[int, str]] = {}
    section = None
    computations: dict[str, list[str]] = {}
    current = None
    for line in hlo_text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = line
            tables[section] = {}
            continue
        if section is not None:
            if line.strip():
                key, _, value = line.partition(" ")
                tables[section][int(key)] = value
                continue
            section = None
        m = _COMPUTATION.match(line)
        if m:
            current = computations.setdefault(m.group(1), [])
        elif current is not None:
            current.append(line)
    files = {k: v.strip('"') for k, v in tables.get("FileNames", {}).items()}
    functions = {k: v.strip('"') for k, v in tables.get("FunctionNames", {}).items()}
    locations = {}
    for k, v in tables.get("FileLocations", {}).items():
        ids = dict(re.findall(r"(\w+)=(\d+)", v))
        locations[k] = (files[int(ids["file_name_id"])], functions[int(ids["function_name_id"])])
    frames = {}
    for k, v in tables.get("StackFrames", {}).items():
        ids = dict(re.findall(r"(\w+)=(\d+)", v))
        frames[k] = (int(ids["file_location_id"]), int(ids["parent_frame_id"]))

    def label(frame: int) -> str:
        seen = set()
        while frame in frames and frame not in seen:  # innermost first
            seen.add(frame)
            location, parent = frames[frame]
            path, function = locations[location]
            if f"/{package}/" in path:
                return f"{Path(path).stem}:{function}"
            frame = parent
        return NO_SOURCE

    def labels(computation: str, depth: int = 0) -> collections.Counter:
        out: collections.Counter = collections.Counter()
        for line in computations.get(computation, []):
            frame = re.search(r"stack_frame_id=(\d+)", line)
            if frame:
                out[label(int(frame.group(1)))] += 1
            called = re.search(r"calls=%([\w.\-]+)", line)
            if called and depth < 4:
                out.update(labels(called.group(1), depth + 1))
        return out

    sources: dict[str, str] = {}
    for lines in computations.values():
        for line in lines:
            m = _INSTRUCTION.match(line)
            if not m or not re.search(r"\b(fusion|custom-call)\(", line):
                continue
            called = re.search(r"calls=%([\w.\-]+)", line)
            found = labels(called.group(1)) if called else collections.Counter()
            frame = re.search(r"stack_frame_id=(\d+)", line)
            if not found and frame:
                found[label(int(frame.group(1)))] += 1
            source = found.most_common(1)[0][0] if found else NO_SOURCE
            dedup = re.search(r'deduplicated_name="([^"]+)"', line)
            for name in (m.group(1), dedup.group(1) if dedup else None):
                if name:
                    sources.setdefault(re.sub(r"[.\-]", "_", name), source)
    return sources


def read_trace(folder: Path) -> list[dict]:
    """The events of the one perfetto trace `jax.profiler.trace` wrote under ``folder``."""
    found = sorted(folder.rglob("*.trace.json.gz"))
    if len(found) != 1:
        raise FileNotFoundError(f"{folder}: expected one *.trace.json.gz, found {len(found)}")
    with gzip.open(found[0]) as f:
        return json.load(f)["traceEvents"]
