"""What the newer benchmark scripts share: their machine line and how they write a result."""

from __future__ import annotations

import json
from pathlib import Path


def machine_line(m: dict) -> str:
    """``Machine: <device> (<platform>), jax <v>, <date>. Command: `...` `` of a `machine_info`."""
    return (
        f"Machine: {m.get('device_kind')} ({m['platform']}), jax {m['jax']}, {m['date']}. "
        f"Command: `{m['command']}`"
    )


def write_result(stem: Path, result: dict, markdown: str) -> None:
    """``<stem>.json`` (``result``) and ``<stem>.md`` (``markdown``, also printed)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_name(stem.name + ".json").write_text(json.dumps(result, indent=2) + "\n")
    stem.with_name(stem.name + ".md").write_text(markdown.rstrip("\n") + "\n")
    print(markdown)


def phases_text(phases: dict[str, float]) -> str:
    """``"demos 11.9, conditions 9.5"`` of ``{"demos_seconds": 11.9, ...}`` (a run's phases)."""
    return ", ".join(f"{k.removesuffix('_seconds')} {v:.1f}" for k, v in phases.items())


def latency_ms(pct: dict | None) -> str:
    """``{"p50": s, "p99": s}`` -> ``"p50 / p99"`` in ms (``-`` where absent)."""
    return "-" if pct is None else f"{1e3 * pct['p50']:.1f} / {1e3 * pct['p99']:.1f}"


def shown_path(path: str) -> str:
    """``path`` relative to the repository where it lies inside it (no machine's folders in a
    result file), else as given."""
    root = Path(__file__).resolve().parents[1]
    full = Path(path).resolve()
    return str(full.relative_to(root)) if full.is_relative_to(root) else path
