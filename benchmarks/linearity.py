"""How far a generation's cost is from linear in the number of conditions, and why.

Reads `trace_generation.py` results at several condition counts (same machine, same code), or a
`generations_per_sec.py` sweep (the fit only), and reports:

- **the latency model** ``T(m) = chunks(m) * L + m * C`` fitted by least squares to the timed
  seconds per generation: ``C`` the time per condition once the device is full, ``L`` the time
  per optimisation batch that does not shrink with the batch (kernels whose duration is their
  dependency chain, not their work: a batch of 1,000 fills a few percent of a large GPU).
  ``chunks(m)`` is the optimiser's batch count, ``ceil(m / compiler.max_batch)``
  (`compiler.optimisation.in_chunks`). With it, the largest ``L`` at which the smallest size's time
  per
  condition stays within ``--tolerance`` of the largest's (the issue's linearity bar);
- **what-ifs**: the smallest over the largest size's time per condition if one part of the
  generation took no time at all (its kernels' device time removed at both sizes; an
  optimistic bound on what fusing or removing that part could give): each stage, the rigid-body
  dynamics against the rest of the optimiser, the device's idle time, and every project function
  (``by_source``).

Usage:
    cd benchmarks/results
    python ../linearity.py trace_generation_gpu_h100_{1000,10000,100000}.json --tag gpu_h100
Writes ``benchmarks/results/linearity_<tag>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from result_files import write_result  # noqa: E402

DYNAMICS = "dynamics_rnea:"  # sources of the rigid-body dynamics' kernels (`trace_summary`)


def batch_chunks(conditions: int, max_batch: int | None, starts: int = 1) -> int:
    """Optimiser batches of a generation at ``conditions``: `compiler.optimisation.in_chunks`'
    count."""
    b = conditions * starts
    return 1 if max_batch is None or b <= max_batch else -(-b // max_batch)


def fit_latency(conditions, chunks, seconds) -> dict:
    """``seconds = chunks * L + conditions * C`` fitted over the sizes given (at least two, with
    ``chunks / conditions`` not all equal) by least squares on the relative residuals (every size
    counts alike, not the largest times most): ``{"L_s", "C_s", "relative_residuals"}``."""
    m = np.asarray(conditions, float)
    a = np.stack([np.asarray(chunks, float), m], axis=1)
    t = np.asarray(seconds, float)
    if len(t) < 2 or np.linalg.matrix_rank(a) < 2:
        raise ValueError("fit_latency: expected two or more sizes with different chunks/conditions")
    (lat, per), *_ = np.linalg.lstsq(a / t[:, None], np.ones_like(t), rcond=None)
    return {
        "L_s": float(lat),
        "C_s": float(per),
        "relative_residuals": list((a @ [lat, per]) / t - 1),
    }


def latency_bound(per_condition_s: float, small: tuple, large: tuple, tolerance: float) -> float:
    """The largest ``L`` at which ``T(m) / m`` of ``small = (conditions, chunks)`` is within
    ``1 + tolerance`` of ``large``'s, at ``C = per_condition_s``; inf where any L is."""
    slope = small[1] / small[0] - (1 + tolerance) * large[1] / large[0]
    return float("inf") if slope <= 0 else tolerance * per_condition_s / slope


def _us_per_condition(d: dict, removed_us: float = 0.0) -> float:
    return (1e6 * d["seconds_per_generation"] - removed_us) / d["conditions"]


def parts(d: dict) -> tuple[dict[str, float], dict[str, float]]:
    """Device time per generation [us] of the parts of a `trace_generation` result:
    ``(groups, functions)``. Groups: each stage; the dynamics (`DYNAMICS` sources); the rest of
    the last stage (the optimiser's own arithmetic); the time the device is not busy (timed
    generation minus busy); and the last two together. Functions: ``by_source``. The trace
    attributes kernels to functions, not stages, so the dynamics' few kernels in earlier stages
    (the Gauss-Newton start's) are subtracted from the last stage too: its rest is slightly
    underestimated, and the ratio without it slightly overestimated."""
    t = d["trace"]
    stages = t.get("stages") or {"generation": t}
    groups = {f"stage `{k}`": v["busy_us_per_generation"] for k, v in stages.items()}
    rows = t.get("by_source", [])
    dynamics = sum(r["us_per_generation"] for r in rows if r["source"].startswith(DYNAMICS))
    groups["dynamics (all stages)"] = dynamics
    rest = list(stages.values())[-1]["busy_us_per_generation"] - dynamics
    groups["last stage without the dynamics"] = rest
    idle = max(0.0, 1e6 * d["seconds_per_generation"] - t["busy_us_per_generation"])
    groups["device not busy"] = idle
    groups["last stage without the dynamics, and not busy"] = rest + idle
    return groups, {f"`{r['source']}`": r["us_per_generation"] for r in rows}


def what_ifs(small: dict, large: dict) -> dict[str, list[dict]]:
    """Per part (`parts`; ``{"groups": [...], "functions": [...]}``, each sorted by the ratio):
    its microseconds per condition at both sizes and the small / large time-per-condition ratio
    with that part removed at both."""
    out = {}
    for kind, ps, pl_ in zip(("groups", "functions"), parts(small), parts(large)):
        rows = []
        for name in ps.keys() | pl_.keys():
            xs, xl = ps.get(name, 0.0), pl_.get(name, 0.0)
            ratio = _us_per_condition(small, xs) / _us_per_condition(large, xl)
            rows.append({"part": name, "us_small": xs / small["conditions"],
                         "us_large": xl / large["conditions"], "ratio_without": ratio})  # fmt: skip
        out[kind] = sorted(rows, key=lambda r: r["ratio_without"])
    return out


def runs(d: dict) -> list[dict]:
    """The timed runs in a result file: a `trace_generation` result as it is, or each size of a
    `generations_per_sec` sweep (no trace: no what-ifs)."""
    if "sweep" not in d:
        return [d]
    return [{"conditions": r["conditions"], "seconds_per_generation": r["seconds_per_generation"],
             "machine": d["machine"]} for r in d["sweep"]]  # fmt: skip


def analyse(results: list[dict], max_batch: int | None, tolerance: float) -> dict:
    """The fit (`fit_latency`), its `latency_bound` and the `what_ifs` of the smallest against
    the largest size, for timed runs (`runs`) at two or more condition counts."""
    res = sorted(results, key=lambda d: d["conditions"])
    m = [d["conditions"] for d in res]
    ch = [batch_chunks(x, max_batch) for x in m]
    fit = fit_latency(m, ch, [d["seconds_per_generation"] for d in res])
    small, large = res[0], res[-1]
    return {
        "sizes": [
            {
                "conditions": x,
                "chunks": c,
                "us_per_condition": _us_per_condition(d),
                "date": d["machine"]["date"],
                "device": d["machine"].get("device_kind"),
            }
            for x, c, d in zip(m, ch, res)
        ],
        "max_batch": max_batch,
        "ratio": _us_per_condition(small) / _us_per_condition(large),
        "tolerance": tolerance,
        "fit": fit,
        "L_bound_s": latency_bound(fit["C_s"], (m[0], ch[0]), (m[-1], ch[-1]), tolerance),
        "what_if": what_ifs(small, large) if small.get("trace") and large.get("trace") else {},
    }


def markdown(r: dict, sources: list[str], rows: int) -> str:
    s = r["sizes"]
    lines = [
        f"Results: {', '.join(f'`{Path(p).name}`' for p in sources)} ({s[0]['device']}). "
        f"Command: `python benchmarks/linearity.py {' '.join(sources)}`",
        "",
        "| conditions | optimiser batches | us / condition | fit: relative residual |",
        "|---:|---:|---:|---:|",
        *(
            f"| {x['conditions']} | {x['chunks']} | {x['us_per_condition']:.2f} | {e:+.1%} |"
            for x, e in zip(s, r["fit"]["relative_residuals"])
        ),
        "",
        f"Fit `T(m) = batches(m) L + m C`: **L = {1e3 * r['fit']['L_s']:.2f} ms** per batch, "
        f"**C = {1e6 * r['fit']['C_s']:.2f} us** per condition. {s[0]['conditions']:,} against "
        f"{s[-1]['conditions']:,} conditions: {r['ratio']:.2f}x the time per condition; within "
        f"{r['tolerance']:.0%} needs L <= {1e3 * r['L_bound_s']:.2f} ms at this C.",
    ]
    if r["what_if"]:
        lines += [
            "",
            f"If one part took no time ({s[0]['conditions']:,} / {s[-1]['conditions']:,} "
            "conditions; the device time of its kernels removed at both sizes, an optimistic "
            f"bound), the parts and the {rows} functions that would do most:",
            "",
            "| part | us / condition, small | us / condition, large | ratio without it |",
            "|---|---:|---:|---:|",
            *(
                f"| {w['part']} | {w['us_small']:.3f} | {w['us_large']:.3f} "
                f"| {w['ratio_without']:.2f} |"
                for w in r["what_if"]["groups"] + r["what_if"]["functions"][:rows]
            ),
        ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    from evojax_motion.settings.compiler import MAX_BATCH

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "results", nargs="+", help="trace_generation_*.json, or a generations_per_sec sweep"
    )
    p.add_argument(
        "--max-batch", type=int, default=MAX_BATCH, help="compiler.max_batch of the runs"
    )
    p.add_argument("--tolerance", type=float, default=0.2)
    p.add_argument("--rows", type=int, default=8, help="functions shown in the markdown")
    p.add_argument("--tag", default="")
    p.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args(argv)
    sources = [str(Path(t)) for t in args.results]
    found = []
    for path in sources:
        try:
            found += runs(json.loads(Path(path).read_text()))
        except (OSError, ValueError, KeyError, TypeError) as e:
            p.error(f"{path}: expected a trace_generation or generations_per_sec result ({e!r})")
    try:
        r = analyse(found, args.max_batch, args.tolerance)
    except (ValueError, KeyError, TypeError) as e:
        p.error(f"expected results at two or more condition counts of one machine ({e!r})")
    r["traces"] = sources
    md = markdown(r, sources, args.rows)
    write_result(Path(args.out_dir) / f"linearity_{args.tag or 'result'}", r, md)
    return r


if __name__ == "__main__":
    main()
