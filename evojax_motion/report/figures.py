"""The report's paper figures (Fig. 4, the cost vs human-likeness trade-off, the snapshot grids of
Fig. 7 and 9) and `FIGURES`: every file of the report with its title, the run files it needs and
its caption. Fig. 5, 8 and 10 are drawn by `report.plots`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.report.condition import Context, neighbour_basis
from evojax_motion.report.run_folder import (
    CONFIG_FILE,
    DB_FINAL,
    DB_GEN1,
    DB_INITIAL,
    METRICS_FILE,
    RunData,
)

BASIS_COMPONENTS = 4  # Fig. 4: "their first four dominant principal components"

# figure file -> (title, run files it needs, caption)
FIGURES: dict[str, tuple[str, tuple[str, ...], str]] = {
    "fig4_basis.png": (
        "Neighbours and principal components (Fig. 4)",
        (DB_INITIAL, CONFIG_FILE),
        "Left: one joint's trajectories in the primitives selected for the condition (eq. 6, "
        "within the basis radius). Right: their first four principal components (unit norm), "
        "with the share of the neighbours' variance each explains. Top: the human demonstrations; "
        "bottom: the learned database (human and evolved primitives).",
    ),
    "fig5_costs.png": (
        "Cost per generation (Fig. 5)",
        (METRICS_FILE,),
        "Mean torque sum (time-averaged |tau| summed over joints, the paper's Fig. 5 quantity) "
        "and mean eq. 5 cost of the evolved slots after each generation.",
    ),
    "tradeoff.png": (
        "Optimality vs human-likeness",
        (METRICS_FILE,),
        "Per generation: mean eq. 5 cost against the RMS joint-angle deviation from each "
        "condition's human-only interpolation. Down is cheaper, right is less human-like.",
    ),
    "fig8_generations.png": (
        "First vs last generation (Fig. 8)",
        (DB_GEN1, DB_FINAL),
        "Joint angles of the condition's primitive in the first (black dashed) and last (red "
        "solid) generation's database, with the human-only interpolation (blue dotted).",
    ),
    "fig10_interp_vs_optim.png": (
        "Interpolation vs optimisation (Fig. 10)",
        (DB_FINAL, CONFIG_FILE),
        "Both compilers on the last database (leave-one-out) with the same boundary conditions: "
        "interpolation, eq. 1-2 (black dashed), and optimisation, eq. 3-5 (red solid).",
    ),
    "fig7_snapshots.png": (
        "Snapshots, first vs last generation (Fig. 7)",
        (DB_GEN1, DB_FINAL),
        "Front and side views of the condition's motion in the first and the last generation's "
        "database; the ball marks the catch point.",
    ),
    "fig9_snapshots.png": (
        "Snapshots, interpolation vs optimisation (Fig. 9)",
        (DB_FINAL, CONFIG_FILE),
        "The two motions of Fig. 10, front and side.",
    ),
    "catch.gif": (
        "An online catch",
        (DB_FINAL, CONFIG_FILE),
        "A ball thrown through the condition's catch point and caught with the last database: "
        "the catch planner picks where and when, the online process (sec. 3.2: neighbours, "
        "human-like IK, interpolation within the joint limits) moves the arm. Half speed.",
    ),
}


# the optional catch figure: drawn where the run folder holds `run_folder.CATCH_FILE`
CATCH_FIGURE = "catch_success.png"
CATCH_TITLE = "Catches in physics, per database"
CATCH_CAPTION = (
    "benchmarks/catch_success.py on this run: random throws planned online and executed in "
    "MuJoCo by the tracking controller (docs/simulation.md). Left: caught / reachable throws; "
    "right: eq. 5 cost of the planned motions (median, bar; mean, dot) [N^2 m^2 s]."
)


def plot_catch_success(result: dict, path: Path) -> Path:
    """Catch success and eq. 5 cost side by side for each database of a catch_success result."""
    import matplotlib.pyplot as plt

    names = list(result["databases"])
    rows = [result["databases"][n] for n in names]
    rate = [100.0 * r["caught"] / max(r["reachable"], 1) for r in rows]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4))
    bars = left.bar(names, rate, color="tab:blue")
    for bar, r in zip(bars, rows, strict=True):
        left.annotate(
            f"{r['caught']} / {r['reachable']}",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    left.set(ylabel="caught [% of reachable throws]", ylim=(0, 105))
    right.bar(names, [r["cost"]["median"] for r in rows], color="tab:red", alpha=0.7)
    right.plot(names, [r["cost"]["mean"] for r in rows], "ko", label="mean")
    right.set(ylabel="eq. 5 cost [N^2 m^2 s]")
    right.legend(fontsize=8)
    fig.suptitle(f"{result.get('throws', '?')} throws")
    return _save(fig, path)


def _save(fig, path: Path) -> Path:
    from evojax_motion.report.plots import save_figure

    return save_figure(fig, path)


def plot_basis(data: RunData, ctx: Context, path: Path, joint: str | None = None) -> Path:
    """Fig. 4: a joint's trajectories in the condition's neighbours and their first four
    principal components, for the human database and (if read) the learned one."""
    import matplotlib.pyplot as plt

    from evojax_motion.motion.database import EVOLVED, humans_only

    basis_settings = data.config.basis
    rows = [("human demonstrations (generation 0)", humans_only(data.db_initial[0]))]
    if data.db_final is not None:
        gen = data.metrics[-1]["generation"] if data.metrics else "last"
        rows.append((f"learned database (generation {gen})", data.db_final[0]))
    names = list(ctx.robot.joint_names)
    fits = [
        (title, db, *neighbour_basis(db, ctx.target, basis_settings, BASIS_COMPONENTS))
        for title, db in rows
    ]
    if joint is None:  # the joint the human neighbours vary most in
        k = int(np.argmax(np.asarray(fits[0][3].variance[0]).sum(axis=0)))
    elif joint in names:
        k = names.index(joint)
    else:
        raise UserError(f"--joint: expected one of {names}, got {joint!r}")
    s = np.asarray(ctx.grid.s)
    fig, axes = plt.subplots(len(fits), 2, figsize=(11, 3.4 * len(fits)), squeeze=False)
    for r, (title, db, nb, basis) in enumerate(fits):
        ax_l, ax_r = axes[r]
        idx = np.asarray(nb.index[0])[np.asarray(nb.mask[0])]
        x = np.degrees(np.asarray(db.q)[idx][:, :, k])  # (n, T)
        evolved = np.asarray(db.origin)[idx] == EVOLVED
        for i in range(len(idx)):
            ax_l.plot(s, x[i], color="tab:red" if evolved[i] else "tab:blue", lw=1, alpha=0.8)
        ax_l.plot(s, np.degrees(np.asarray(basis.mean[0, :, k])), "k--", lw=1.5, label="mean")
        ax_l.plot([], [], color="tab:blue", label="human")
        if evolved.any():
            ax_l.plot([], [], color="tab:red", label="evolved")
        ax_l.set_title(f"{title}: {len(idx)} neighbours, joint {names[k]}", fontsize=9)
        ax_l.set_ylabel("angle [deg]")
        ax_l.legend(fontsize=7)
        centred = x - x.mean(axis=0)
        total = float(np.sum(np.radians(centred) ** 2) / max(len(idx) - 1, 1))
        var = np.asarray(basis.variance[0, :, k])
        comps = np.asarray(basis.components[0, :, :, k])
        for i in range(comps.shape[0]):
            share = 100.0 * var[i] / total if total > 0 else 0.0
            ax_r.plot(s, comps[i], lw=1.5, label=f"PC {i + 1} ({share:.0f} %)")
        ax_r.set_title("first four principal components (unit norm)", fontsize=9)
        ax_r.legend(fontsize=7)
        for ax in (ax_l, ax_r):
            ax.grid(alpha=0.3)
            ax.set_xlabel("normalised time s")
    fig.suptitle(
        f"condition {ctx.condition}: catch point {np.round(ctx.target, 3).tolist()} m (Fig. 4)",
        fontsize=10,
    )
    fig.tight_layout()
    return _save(fig, path)


# Where a generation's label may go, relative to its point [points], in order of preference.
LABEL_OFFSETS = ((4, 4), (4, -11), (-11, 4), (-11, -11), (6, -3), (-14, -3), (-3, 7), (-3, -14))
MARKER_SIZE = 40.0  # [pt^2] the trade-off plot's points
SAME_POINT_PX = 3.0  # consecutive generations this close on screen share one label ("3-4")


def _generation_groups(gen, xy_px) -> list[tuple[str, int]]:
    """Runs of consecutive generations at (nearly) the same screen point ``xy_px (G, 2)``:
    ``[(label, index of the run's last point)]``, e.g. ``("3-4", 3)``."""
    groups: list[tuple[str, int]] = []
    start = None
    for i in range(len(gen)):
        if not np.isfinite(xy_px[i]).all():
            start = None
            continue
        if start is None:
            start = i
        nxt = i + 1
        same = nxt < len(gen) and np.hypot(*(xy_px[nxt] - xy_px[i])) <= SAME_POINT_PX
        if not same:
            first, last = gen[start], gen[i]
            groups.append((str(first) if first == last else f"{first}-{last}", i))
            start = None
    return groups


def label_points(ax, gen, x, y, marker_size: float = MARKER_SIZE, fontsize: float = 7.0) -> list:
    """Label the points ``(x, y) (G,)`` with their generations ``gen (G,)`` without overlaps.

    Consecutive generations at the same spot share a label ("3-4"). Each label takes the first
    of `LABEL_OFFSETS` where it lies inside the axes and overlaps neither the legend, nor a
    point's marker (scatter size ``marker_size`` [pt^2]), nor a label placed before it (the last
    generation's first, then the first's, then in order); a label with no free place is left
    out (the colour still tells the generation). Call after the axes' limits and size are
    final. Returns the placed texts.
    """
    from matplotlib.transforms import Bbox

    fig = ax.figure
    fig.canvas.draw()  # final limits and layout: screen positions of the points
    renderer = fig.canvas.get_renderer()
    xy = np.column_stack([x, y]).astype(float)
    ok = np.isfinite(xy).all(axis=1)
    xy_px = np.full_like(xy, np.nan)
    if ok.any():
        xy_px[ok] = ax.transData.transform(xy[ok])
    groups = _generation_groups(np.asarray(gen), xy_px)
    if len(groups) > 1:  # the last generation, then the first, then the rest
        groups = [groups[-1], groups[0], *groups[1:-1]]
    legend = ax.get_legend()
    taken: list = [] if legend is None else [legend.get_window_extent(renderer)]
    r = 0.5 * np.sqrt(marker_size) * fig.dpi / 72.0  # marker radius [px]
    markers = [Bbox.from_bounds(u - r, v - r, 2 * r, 2 * r) for u, v in xy_px[ok]]
    frame = ax.get_window_extent(renderer)
    placed: list = []
    for label, i in groups:
        for dx, dy in LABEL_OFFSETS:
            text = ax.annotate(
                label, (x[i], y[i]), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize
            )
            box = text.get_window_extent(renderer)
            inside = frame.contains(box.x0, box.y0) and frame.contains(box.x1, box.y1)
            if inside and not any(box.overlaps(b) for b in taken + markers):
                placed.append(text)
                taken.append(box)
                break
            text.remove()
    return placed


def tradeoff_figure(metrics: list[dict], baseline: dict | None = None):
    """The figure of `plot_tradeoff` (a matplotlib ``Figure``, not yet saved)."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    gen = np.array([r["generation"] for r in metrics])

    def col(name):
        return np.array([np.nan if r.get(name) is None else r[name] for r in metrics], float)

    dev, cost = col("human_deviation_deg"), col("db_cost_mean")
    fig, ax = plt.subplots(figsize=(6, 4.2), layout="constrained")
    human = (baseline or {}).get("human_only_cost_mean")
    ax.plot(dev, cost, "-", color="0.6", lw=1, zorder=1, label="generations, in order")
    if human is not None:
        ax.plot([0.0], [human], "s", color="tab:blue", label="human-only interpolation")
        ax.plot([0.0, dev[0]], [human, cost[0]], ":", color="0.6", lw=1, zorder=1)
    ax.legend(fontsize=8)
    sc = ax.scatter(dev, cost, c=gen, cmap="viridis", s=MARKER_SIZE, zorder=2)
    bar = fig.colorbar(sc, ax=ax, label="generation")
    bar.locator = MaxNLocator(integer=True)
    bar.update_ticks()
    ax.set_xlabel("deviation from human-only interpolation [deg RMS]")
    ax.set_ylabel(r"mean eq. 5 cost [N$^2$ m$^2$ s]")
    ax.set_title("optimality vs human-likeness per generation")
    ax.grid(alpha=0.3)
    # the limits of every point, with room for labels at the edges, fixed before they are placed
    ax.margins(0.1)
    ax.set_xlim(ax.get_xlim())
    ax.set_ylim(ax.get_ylim())
    fig.canvas.draw()
    fig.set_layout_engine("none")  # freeze the layout the labels are placed in
    label_points(ax, gen, dev, cost)
    return fig


def plot_tradeoff(metrics: list[dict], path: Path, baseline: dict | None = None) -> Path:
    """Per generation: mean eq. 5 cost against mean ``human_deviation_deg``, in order.

    ``baseline`` (``summary.json``): its ``human_only_cost_mean`` is drawn at deviation 0, the
    human-only interpolation of the same conditions (the starting point of the trade-off).
    Generation labels never overlap (`label_points`).
    """
    return _save(tradeoff_figure(metrics, baseline), path)


def snapshot_figure(
    frames, row_labels, times, path: Path, title: str, renderer: str, asked: bool = False
) -> Path:
    """Grid of rendered frames ``(rows, cols, H, W, 3)`` with row labels and times [s]."""
    import matplotlib.pyplot as plt

    rows, cols, h, w, _ = frames.shape
    fig, axes = plt.subplots(
        rows, cols, figsize=(cols * w / 100, rows * h / 100 + 0.6), squeeze=False
    )
    for r in range(rows):
        for c in range(cols):
            ax = axes[r, c]
            ax.imshow(frames[r, c])
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"t = {times[c]:.2f} s", fontsize=8)
        axes[r, 0].set_ylabel(row_labels[r], fontsize=8)
    fallback = "" if renderer.startswith("mujoco") else " [stick-figure fallback: no OpenGL]"
    if asked and not renderer.startswith("mujoco"):
        fallback = " [stick figures]"
    fig.suptitle(f"{title}{fallback}", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
