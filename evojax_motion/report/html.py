"""The report's HTML page: one self-contained file (`HTML_FILE`) with every figure inlined."""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import TYPE_CHECKING

from evojax_motion.report.figures import CATCH_CAPTION, CATCH_FIGURE, CATCH_TITLE, FIGURES
from evojax_motion.report.run_folder import RunData

if TYPE_CHECKING:
    from evojax_motion.report.build import Report

HTML_FILE = "report.html"


def _data_uri(path: Path) -> str:
    mime = "image/gif" if path.suffix == ".gif" else "image/png"
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _summary_rows(data: RunData) -> list[tuple[str, str]]:
    if data.summary:
        rows = []
        for k, v in data.summary.items():
            if not isinstance(v, (list, dict)):
                rows.append((k, f"{v:.5g}" if isinstance(v, float) else str(v)))
        return rows
    if data.metrics:
        first, last = data.metrics[0], data.metrics[-1]
        rows = [("generations", str(last["generation"]))]
        for key in ("db_cost_mean", "torque_sum_mean", "human_deviation_deg", "n_valid"):
            rows.append(
                (
                    f"{key} (gen {first['generation']} -> {last['generation']})",
                    f"{first.get(key)} -> {last.get(key)}",
                )
            )
        return rows
    return []


def write_html(rep: Report, data: RunData) -> Path:
    """One self-contained page (images inlined as base64) of everything in ``rep``."""
    from evojax_motion.run.atomic import atomic_write_text

    esc = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>evojax-motion report: {esc(str(data.run_dir))}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "img{max-width:100%;border:1px solid #ddd}table{border-collapse:collapse}"
        "td{padding:2px 10px;border-bottom:1px solid #eee}.warn{background:#fff3f0;"
        "border:1px solid #e0a090;padding:0.6em 1em}.note{color:#555}</style></head><body>",
        "<h1>evojax-motion: training run report</h1>",
        f"<p>run directory: <code>{esc(str(data.run_dir.resolve()))}</code><br>",
        f"snapshots: {esc(rep.renderer)} &mdash; {esc(rep.gl_message)}</p>",
    ]
    if rep.problems or rep.skipped:
        parts.append("<div class='warn'><b>Incomplete run folder.</b><ul>")
        parts += [f"<li>{esc(msg)}</li>" for msg in rep.problems.values()]
        parts += [f"<li>{esc(n)} not made: {esc(why)}</li>" for n, why in rep.skipped.items()]
        parts.append("</ul></div>")
    if rep.renderer.startswith("stick"):
        parts.append(
            "<p class='warn'>No OpenGL backend for MuJoCo's renderer: the snapshots "
            "and the animation are matplotlib stick figures from forward kinematics "
            "(fallback).</p>"
        )
    rows = _summary_rows(data)
    if rows:
        parts.append("<h2>Summary</h2><table>")
        parts += [f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in rows]
        parts.append("</table>")
    if rep.notes:
        parts.append(
            "<ul class='note'>" + "".join(f"<li>{esc(n)}</li>" for n in rep.notes) + "</ul>"
        )
    for name, (title, _, caption) in FIGURES.items():
        parts.append(f"<h2>{esc(title)}</h2>")
        if name in rep.figures:
            parts.append(
                f"<p>{esc(caption)}</p><img alt='{esc(name)}' src='{_data_uri(rep.figures[name])}'>"
            )
        else:
            parts.append(f"<p class='note'>not made: {esc(rep.skipped.get(name, '?'))}</p>")
    if CATCH_FIGURE in rep.figures:  # optional (`report.run_folder.CATCH_FILE`)
        parts.append(f"<h2>{esc(CATCH_TITLE)}</h2><p>{esc(CATCH_CAPTION)}</p>")
        parts.append(f"<img alt='{CATCH_FIGURE}' src='{_data_uri(rep.figures[CATCH_FIGURE])}'>")
    parts.append("</body></html>\n")
    return atomic_write_text(rep.out_dir / HTML_FILE, "\n".join(parts))
