"""Summaries of `jax.profiler` traces (Chrome trace format): what the device ran, and when.

Standard library only, no side effects: `trace_generation.py` uses it, and the tests.
"""

from __future__ import annotations

import gzip
import itertools
import json
from pathlib import Path

TOP = 25  # kernels, host events and gaps listed


def summarise_trace(events: list[dict], generations: int) -> dict:
    """Summary of a Chrome-format trace (``traceEvents``) of ``generations`` generations.

    Complete events (``ph == "X"``) of processes whose name holds ``"GPU"`` are device kernels
    and copies, grouped by stream (thread); the stream with the most events is summarised as the
    device's. All other complete events are host events. Times in microseconds, per generation
    where named so.
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
    }


def read_trace(folder: Path) -> list[dict]:
    """The events of the one perfetto trace `jax.profiler.trace` wrote under ``folder``."""
    found = sorted(folder.rglob("*.trace.json.gz"))
    if len(found) != 1:
        raise FileNotFoundError(f"{folder}: expected one *.trace.json.gz, found {len(found)}")
    with gzip.open(found[0]) as f:
        return json.load(f)["traceEvents"]
