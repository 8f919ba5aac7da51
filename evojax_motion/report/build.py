"""The report of a training run: the paper's figures from a run folder, and one self-contained HTML
page (``evojax-motion report RUN_DIR [--out DIR]``).

Files written (paper figure; run files needed, in brackets the optional ones):

- ``fig4_basis.png``: one condition's neighbours (one joint's trajectories) and their first four
  principal components, human and learned database (Fig. 4; db_initial, config [db_final]);
- ``fig5_costs.png``: mean torque sum and eq. 5 cost per generation (Fig. 5; metrics);
- ``tradeoff.png``: eq. 5 cost against ``human_deviation_deg`` per generation (metrics);
- ``fig8_generations.png``: the condition's joint angles, first vs last generation (Fig. 8;
  db_gen1, db_final [db_initial, config]);
- ``fig10_interp_vs_optim.png``: interpolation (eq. 1-2) vs optimisation (eq. 3-5) from the last
  database (Fig. 10; db_final, config);
- ``fig7_snapshots.png``: snapshots, front and side, first vs last generation (Fig. 7; db_gen1,
  db_final);
- ``fig9_snapshots.png``: the same for interpolation vs optimisation (Fig. 9; db_final, config);
- ``catch.gif``: a thrown ball caught online (sec. 3.2) with the last database (db_final, config);
- ``report.html``: all of the above, images inlined (base64).

The condition is ``--condition`` (default: the config's ``train.plot_condition``, or when that is
null, as in ``train.py``, the condition whose cost fell most from generation 1 to the last; when
its slot is empty in a database another is chosen and the page says so). Fig. 10 and Fig. 9 use
the last database *without the condition's own evolved primitive* (leave-one-out), so that the
interpolation compiler sees what it would for a new target and cannot copy the optimised answer.
The boundary conditions are the evolved slot's (rest start, IK final posture, rest to rest).
The catch animation throws a ball through the condition's catch point (`catch_animation`).

Snapshots come from MuJoCo's offscreen renderer when an OpenGL backend works
(`report.render.gl_status`),
else from the matplotlib stick-figure fallback, labelled as such; the plots never need GL.

Exit status of the command: 0 every figure written; 1 some run file missing or unreadable (each
named on stderr and in the page) and only the figures that do not need it written; 2 ``RUN_DIR``
does not exist or holds no run (no ``config.yaml``, ``metrics.jsonl`` or database), or a bad
option.
"""

from __future__ import annotations

import base64
import html
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evojax_motion.console import log
from evojax_motion.errors import UserError

# The run folder's files (train.py writes them; names repeated here so that reading a report needs
# no JAX import before it is needed).
CONFIG_FILE, METRICS_FILE, SUMMARY_FILE = "config.yaml", "metrics.jsonl", "summary.json"
DB_INITIAL, DB_GEN1, DB_FINAL = "db_initial.npz", "db_gen1.npz", "db_final.npz"
RUN_FILES = (CONFIG_FILE, METRICS_FILE, DB_INITIAL, DB_GEN1, DB_FINAL)
REPORT_DIR, HTML_FILE = "report", "report.html"
INTERP_COMPONENTS = 3  # eq. 1: three principal components + a constant (as conditions.py)
BASIS_COMPONENTS = 4  # Fig. 4: "their first four dominant principal components"
# The thrown ball of catch.gif: released this far from the catch point [m] (in front, a little to
# the right), passing it THROW_SLACK [s] after a motion started at the reaction time would end.
THROW_OFFSET = np.array([1.5, -0.3, 0.0])
THROW_SLACK = 0.1
GIF_SPEED = 0.5  # playback speed of catch.gif (half speed)

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


class RunData(NamedTuple):
    """What could be read from a run folder; None where a file is missing or unreadable."""

    run_dir: Path
    config: Any  # evojax_motion.settings.Config
    metrics: list[dict] | None
    summary: dict | None
    db_initial: Any  # (Database, DatabaseMeta)
    db_gen1: Any
    db_final: Any
    problems: dict[str, str]  # file name -> what is wrong


@dataclass
class Report:
    """The outcome of `make_report`: written ``figures`` (name -> path), ``skipped`` figures
    (name -> why), file ``problems`` (name -> what), the ``renderer`` used, notes, the page."""

    out_dir: Path
    html: Path | None = None
    figures: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    problems: dict[str, str] = field(default_factory=dict)
    renderer: str = "-"
    gl_message: str = ""
    condition: int | None = None
    notes: list[str] = field(default_factory=list)
    captions: dict[str, str] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return not self.problems and not self.skipped


# --------------------------------------------------------------------------------- reading


def _read_metrics(path: Path) -> list[dict]:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as e:
            raise UserError(f"{path}: line {n}: not JSON ({e.msg})") from None
        if not isinstance(row, dict) or "generation" not in row:
            raise UserError(f"{path}: line {n}: expected an object with a 'generation' field")
        rows.append(row)
    if not rows:
        raise UserError(f"{path}: holds no generation yet")
    return rows


def load_run(run_dir: str | Path) -> RunData:
    """Read everything a report can use from ``run_dir``; missing or unreadable files become
    ``problems``. Raises `UserError` when ``run_dir`` does not exist or holds none of the run's
    files (`RUN_FILES`)."""
    from evojax_motion.motion.database import load_database
    from evojax_motion.settings import load_config

    run = Path(run_dir)
    if not run.is_dir():
        what = "is a file, not a run directory" if run.exists() else "no such directory"
        raise UserError(f"{run}: {what}")
    if not any((run / name).is_file() for name in RUN_FILES):
        raise UserError(
            f"{run}: holds no training run (none of {', '.join(RUN_FILES)}); "
            "expected the --out folder of `evojax-motion train`"
        )
    problems: dict[str, str] = {}

    def attempt(name, reader):
        path = run / name
        if not path.is_file():
            problems[name] = f"{path}: missing"
            return None
        try:
            return reader(path)
        except UserError as e:
            problems[name] = str(e)
        except (OSError, ValueError) as e:
            problems[name] = f"{path}: unreadable ({e})"
        return None

    summary = None
    if (run / SUMMARY_FILE).is_file():  # optional: written at the end of a run
        try:
            summary = json.loads((run / SUMMARY_FILE).read_text())
        except (OSError, json.JSONDecodeError):
            summary = None
    return RunData(
        run_dir=run,
        config=attempt(CONFIG_FILE, load_config),
        metrics=attempt(METRICS_FILE, _read_metrics),
        summary=summary,
        db_initial=attempt(DB_INITIAL, load_database),
        db_gen1=attempt(DB_GEN1, load_database),
        db_final=attempt(DB_FINAL, load_database),
        problems=problems,
    )


# ------------------------------------------------------------------------------ the context


class Context(NamedTuple):
    """Shared objects for the figures of one condition (built once)."""

    robot: Any
    dyn: Any  # None without a config
    grid: Any
    n_human: int
    condition: int  # index in the condition set
    slot: int  # database row of its evolved primitive
    target: np.ndarray  # (3,) [m]
    duration: float  # [s]
    boundary: Any  # compile_interp.Boundary of one condition


def _pick_condition(data: RunData, requested: int | None, notes: list[str]) -> tuple[int, int]:
    """``(condition, slot)``: the requested one, or the first whose slot is filled in every
    database read. Raises `UserError` for an index out of range."""
    from evojax_motion.motion.database import count_human

    dbs = [x[0] for x in (data.db_gen1, data.db_final) if x is not None]
    ref = dbs[-1] if dbs else data.db_initial[0]
    n_human = count_human(ref)
    m = ref.q.shape[0] - n_human
    if m <= 0:
        raise UserError(f"{data.run_dir}: its databases hold no evolved slot (no condition)")
    c = requested
    if c is None and data.config is not None:
        c = data.config.train.plot_condition
    if c is None:  # as train.py: the condition whose cost fell most, the most telling Fig. 8
        c = 0
        if data.db_gen1 is not None and data.db_final is not None:
            first, last = data.db_gen1[0], data.db_final[0]
            both = np.asarray(first.valid[n_human:]) & np.asarray(last.valid[n_human:])
            if both.any():
                drop = np.where(both, first.cost[n_human:] - last.cost[n_human:], -np.inf)
                c = int(np.argmax(drop))
    if not 0 <= c < m:
        raise UserError(f"--condition: expected an index in 0..{m - 1}, got {c}")
    filled = np.ones(m, bool)
    for db in dbs:
        filled &= np.asarray(db.valid[n_human:])
    if dbs and not filled[c]:
        if not filled.any():
            notes.append("no condition has an evolved primitive in every database")
            return c, n_human + c
        new = int(np.flatnonzero(filled)[0])
        notes.append(f"condition {c} has no evolved primitive in every database; shown: {new}")
        c = new
    return c, n_human + c


def condition_context(
    data: RunData, requested: int | None = None, notes: list[str] | None = None
) -> Context:
    """The robot, dynamics (None without a config), time grid and one condition of a run.

    ``requested``: condition index (None: the config's ``train.plot_condition``); when its slot is
    empty in a database read, the first filled one is taken and ``notes`` says so. The boundary
    conditions are the evolved primitive's own end points (rest start, IK final posture, zero end
    velocities). Raises `UserError` for an index out of range.
    """
    import jax.numpy as jnp

    from evojax_motion.compiler.interpolation import Boundary
    from evojax_motion.motion.database import count_human
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.report.render import robot_from_meta

    pair = data.db_final or data.db_gen1 or data.db_initial
    db, meta = pair
    robot = robot_from_meta(meta, source=f"{data.run_dir} (robot of the database)")
    dyn = None
    if data.config is not None:
        from evojax_motion.model.dynamics import make_dynamics

        dyn = make_dynamics(robot, backend=data.config.dynamics)
    c, slot = _pick_condition(data, requested, [] if notes is None else notes)
    q = np.asarray(db.q[slot], np.float32)
    j = q.shape[1]
    dur = float(db.duration[slot])
    if bool(db.valid[slot]):
        q0, qf = q[0], q[-1]
    else:  # an empty slot: rest to the IK posture is unknown; rest to rest keeps plots possible
        q0 = qf = np.asarray(robot.rest, np.float32)
    zeros = jnp.zeros((1, j), jnp.float32)
    boundary = Boundary(
        q0=jnp.asarray(q0[None]),
        qf=jnp.asarray(qf[None]),
        qd0=zeros,
        qdf=zeros,
        duration=jnp.asarray([dur], jnp.float32),
    )
    return Context(
        robot=robot,
        dyn=dyn,
        grid=make_time_grid(q.shape[0]),
        n_human=count_human(db),
        condition=c,
        slot=slot,
        target=np.asarray(db.condition[slot], np.float64),
        duration=dur,
        boundary=boundary,
    )


def neighbour_basis(db, target, basis_settings, n_components: int, exclude=None):
    """``(Neighbours, Basis)`` of one target on ``db`` (row ``exclude`` left out)."""
    import jax.numpy as jnp

    from evojax_motion.compiler.basis import pca_basis, select_neighbours

    valid = np.asarray(db.valid).copy()
    if exclude is not None:
        valid[exclude] = False
    nb = select_neighbours(
        jnp.asarray(db.condition),
        jnp.asarray(valid),
        jnp.asarray(target, jnp.float32)[None],
        basis_settings.neighbours,
        basis_settings.radius,
        basis_settings.w_pos,
    )
    basis = pca_basis(jnp.asarray(db.q), jnp.asarray(db.duration), nb, n_components)
    return nb, basis


def interpolate(db, ctx: Context, basis_settings, exclude=None) -> np.ndarray:
    """Eq. 1-2 trajectory ``(T, J)`` of the condition on ``db``."""
    from evojax_motion.compiler.interpolation import compile_interpolation

    _, basis = neighbour_basis(db, ctx.target, basis_settings, INTERP_COMPONENTS, exclude)
    out = compile_interpolation(basis, ctx.boundary, ctx.grid, n_components=INTERP_COMPONENTS)
    return np.asarray(out.q[0])


def motion_cost(ctx: Context, q) -> tuple[float, float]:
    """Eq. 5 cost and torque sum [N m] of ``q (T, J)``."""
    import jax.numpy as jnp

    from evojax_motion.motion.objective import cost_from_torques, torque_sum, trajectory_torques

    tau = trajectory_torques(ctx.dyn, ctx.grid, jnp.asarray(q), ctx.duration)
    return float(cost_from_torques(ctx.grid, tau, ctx.duration)), float(torque_sum(ctx.grid, tau))


# ------------------------------------------------------------------------------ the figures


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


def snapshot_figure(frames, row_labels, times, path: Path, title: str, renderer: str) -> Path:
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
    fig.suptitle(f"{title}{fallback}", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


class _Batch(NamedTuple):
    q: np.ndarray  # (F, J)
    cameras: list
    balls: np.ndarray  # (F, 3)


def _render_batches(
    robot, batches: list[_Batch], renderer: str, width: int, height: int, floor: float
):
    """Render several frame lists in one renderer call; returns ``(list of images, renderer)``."""
    from evojax_motion.report.render import render_motion

    q = np.concatenate([b.q for b in batches])
    cams = [
        c for b in batches for c in (b.cameras * len(b.q) if len(b.cameras) == 1 else b.cameras)
    ]
    balls = np.concatenate([b.balls for b in batches])
    frames = render_motion(robot, q, cams, balls, width, height, floor, renderer)
    out, start = [], 0
    for b in batches:
        out.append(frames.images[start : start + len(b.q)])
        start += len(b.q)
    return out, frames.renderer


def optimise(data: RunData, ctx: Context) -> np.ndarray:
    """Eq. 3-5 trajectory ``(T, J)`` of the condition on the last database (leave-one-out)."""
    from evojax_motion.compiler.optimisation import make_optimisation_compiler

    cfg = data.config
    settings = cfg.compiler
    _, basis = neighbour_basis(
        data.db_final[0],
        ctx.target,
        cfg.basis,
        max(settings.n_components, INTERP_COMPONENTS),
        exclude=ctx.slot,
    )
    compile_opt = make_optimisation_compiler(
        ctx.dyn, ctx.grid, ctx.robot.lower, ctx.robot.upper, settings
    )
    out = compile_opt(basis, ctx.boundary)
    return np.asarray(out.q[0])


def _online_catch(data: RunData, ctx: Context):
    """The online query (`online.generation.make_online_generator`) for the condition's catch
    point."""
    from evojax_motion.online.generation import make_online_generator, online_database, to_numpy

    gen = make_online_generator(ctx.robot, ctx.dyn, ctx.grid, data.config.basis)
    res = gen(
        online_database(data.db_final[0]),
        np.asarray(ctx.target, np.float32)[None],
        np.asarray([ctx.duration], np.float32),
        np.asarray(ctx.robot.rest, np.float32)[None],
    )
    return to_numpy(res)


def throw(target, duration: float, gravity, reaction_time: float):
    """The ball of ``catch.gif``: released `THROW_OFFSET` from ``target (3,)`` [m], passing it
    when a motion of ``duration`` [s] started after ``reaction_time`` [s] would end, plus
    `THROW_SLACK`. Returns the release point ``(3,)`` [m], velocity ``(3,)`` [m/s] and that
    passing time [s]."""
    target = np.asarray(target, float)
    t_pass = reaction_time + duration + THROW_SLACK
    p0 = target + THROW_OFFSET
    v0 = (target - p0 - 0.5 * np.asarray(gravity, float) * t_pass**2) / t_pass
    return p0, v0, t_pass


def catch_animation(data: RunData, ctx: Context, frames: int, notes: list[str]):
    """A ball thrown through the condition's catch point, caught on the last database.

    The ball is released `THROW_OFFSET` from the catch point, timed to pass it when a motion of
    the condition's duration started after the reaction time would end (+ `THROW_SLACK`);
    `online.catching.make_catcher` plans where and when to catch it and generates the motion.
    Should it
    find no catch, the online query to the catch point itself is shown, timed to the ball.
    Returns ``q (F, J)``, ``ball (F, 3)`` at ``frames`` instants and the real-time fps.
    """
    import jax

    from evojax_motion.online.catching import CatchSettings, explain_plan, make_catcher
    from evojax_motion.online.generation import online_database
    from evojax_motion.report import render as rnd

    settings = CatchSettings()
    gravity = np.asarray(ctx.robot.mj_model.opt.gravity, float)
    p0, v0, t_pass = throw(ctx.target, ctx.duration, gravity, settings.reaction_time)
    catcher = make_catcher(ctx.robot, ctx.dyn, ctx.grid, data.config.basis, None, settings)
    rest = np.asarray(ctx.robot.rest, np.float32)[None]
    f32 = np.float32
    db = online_database(data.db_final[0])
    plan, motion = jax.device_get(catcher(db, p0[None].astype(f32), v0[None].astype(f32), rest))
    ball_t, ball = np.asarray(plan.times[0], float), np.asarray(plan.ball[0], float)
    release = f"ball released at {np.round(p0, 2).tolist()} m, {np.round(v0, 2).tolist()} m/s"
    if bool(plan.feasible[0]):
        t_motion, q, t_catch = motion.t[0], motion.q[0], float(plan.catch_time[0])
        notes.append(f"catch.gif: {release}; {explain_plan(plan, 0)}")
    else:
        online = _online_catch(data, ctx)
        t_catch = t_pass
        t_motion = online.t[0] + (t_pass - float(online.duration[0]))
        q = online.q[0]
        notes.append(
            f"catch.gif: {release}; no catch planned ({explain_plan(plan, 0)}); "
            "shown: the online query to the catch point"
        )
    t_end = 1.25 * t_catch  # hold the catch a moment
    times = np.linspace(0.0, t_end, frames)
    q_f, ball_f = rnd.catch_frames(ctx.robot, t_motion, q, ball_t, ball, t_catch, times)
    return q_f, ball_f, frames / t_end


def catch_camera(robot, q, balls):
    """The camera of ``catch.gif``: the arm's motion ``q (F, J)`` and every ball position
    ``balls (F, 3)`` [m] in the picture (the ball never leaves the view), ball's radius included."""
    from evojax_motion.report import render as rnd

    balls = np.asarray(balls, float)
    # the ball's extent: its centre +- the radius along each axis
    offsets = rnd.BALL_RADIUS * np.concatenate([np.eye(3), -np.eye(3)])
    points = (balls[:, None, :] + offsets[None]).reshape(-1, 3)
    return rnd.fit_camera(robot, [q], rnd.VIEWS["catch"], points)


def make_report(
    run_dir: str | Path,
    out_dir: str | Path | None = None,
    condition: int | None = None,
    joint: str | None = None,
    renderer: str = "auto",
    snapshots: int = 5,
    gif_frames: int = 36,
    animation: bool = True,
    quiet: bool = False,
) -> Report:
    """Write the figures of the module table and ``report.html`` into ``out_dir`` (default
    ``RUN_DIR/report``). Figures whose run files are missing are skipped and named in
    ``Report.skipped``; raises `UserError` for a folder without a run or a bad option."""
    from evojax_motion.report import render as rnd
    from evojax_motion.report.plots import plot_costs

    if renderer not in ("auto", "mujoco", "stick"):
        raise UserError(f"--renderer: expected auto, mujoco or stick, got {renderer!r}")
    if snapshots < 2:
        raise UserError(f"--snapshots: expected an integer >= 2, got {snapshots}")
    if gif_frames < 2:
        raise UserError(f"--gif-frames: expected an integer >= 2, got {gif_frames}")
    data = load_run(run_dir)
    out = Path(out_dir) if out_dir is not None else data.run_dir / REPORT_DIR
    rep = Report(out_dir=out, problems=dict(data.problems))
    # Options are checked before anything is written (status 2 leaves no partial report).
    ctx = None
    if any(x is not None for x in (data.db_initial, data.db_gen1, data.db_final)):
        ctx = condition_context(data, condition, rep.notes)
        rep.condition = ctx.condition
        if joint is not None and joint not in ctx.robot.joint_names:
            raise UserError(
                f"--joint: expected one of {list(ctx.robot.joint_names)}, got {joint!r}"
            )
    say = (lambda msg: None) if quiet else log
    for msg in rep.problems.values():
        say(f"warning: {msg}")
    if renderer != "stick":
        status = rnd.gl_status()
        rep.gl_message = status.message
        if not status.available:
            if renderer == "mujoco":
                raise UserError(f"--renderer mujoco: {status.message}")
            say(
                f"warning: {status.message}; snapshots are matplotlib stick figures instead "
                "(see docs/report.md)"
            )
    else:
        rep.gl_message = "stick figures requested (--renderer stick)"
    have = {name for name in RUN_FILES if name not in rep.problems}

    def blocked(name: str) -> bool:
        missing = [f for f in FIGURES[name][1] if f not in have]
        if missing:
            rep.skipped[name] = f"needs {', '.join(missing)}"
            say(f"skipped {name}: needs {', '.join(missing)}")
        return bool(missing)

    def wrote(name: str, path: Path) -> None:
        rep.figures[name] = path
        say(f"wrote {path}")

    out.mkdir(parents=True, exist_ok=True)
    if not blocked("fig5_costs.png"):
        fig5 = plot_costs(data.metrics or [], out / "fig5_costs.png", baseline=data.summary)
        wrote("fig5_costs.png", fig5)
    if not blocked("tradeoff.png"):
        trade = plot_tradeoff(data.metrics or [], out / "tradeoff.png", baseline=data.summary)
        wrote("tradeoff.png", trade)

    if ctx is not None:
        _condition_figures(
            data,
            ctx,
            rep,
            out,
            joint,
            renderer,
            snapshots,
            gif_frames,
            animation,
            blocked,
            wrote,
            say,
        )
    else:
        for name in FIGURES:
            if name not in rep.figures:
                blocked(name)
    for note in rep.notes:
        say(f"note: {note}")
    rep.captions = {name: FIGURES[name][2] for name in FIGURES}
    rep.html = write_html(rep, data)
    say(f"wrote {rep.html}")
    return rep


def _condition_figures(
    data, ctx, rep, out, joint, renderer, snapshots, gif_frames, animation, blocked, wrote, say
) -> None:
    """The figures of one condition: Fig. 4, 8, 10, 7, 9 and the catch animation."""
    from evojax_motion.report import render as rnd
    from evojax_motion.report.plots import plot_joint_angles

    robot = ctx.robot
    target_txt = np.round(ctx.target, 3).tolist()
    last_gen = data.metrics[-1]["generation"] if data.metrics else "last"
    if not blocked("fig4_basis.png"):
        wrote("fig4_basis.png", plot_basis(data, ctx, out / "fig4_basis.png", joint))

    # Any: each is set exactly when the figures that use them are not blocked
    q_first: Any = None
    q_last: Any = None
    q_interp: Any = None
    q_opt: Any = None
    if data.db_gen1 is not None and data.db_final is not None:
        q_first = np.asarray(data.db_gen1[0].q[ctx.slot])
        q_last = np.asarray(data.db_final[0].q[ctx.slot])
    if not blocked("fig8_generations.png"):
        q_human = None
        if data.db_initial is not None and data.config is not None:
            from evojax_motion.motion.database import humans_only

            q_human = interpolate(humans_only(data.db_initial[0]), ctx, data.config.basis)
        wrote(
            "fig8_generations.png",
            plot_joint_angles(
                q_first,
                q_last,
                ctx.duration,
                robot.joint_names,
                out / "fig8_generations.png",
                q_human=q_human,
                first_label="generation 1",
                last_label=f"generation {last_gen}",
                title=f"condition {ctx.condition}: catch point {target_txt} m (Fig. 8)",
            ),
        )

    if data.db_final is not None and data.config is not None:
        say("compiling the condition by interpolation and by optimisation (JAX compile) ...")
        q_interp = interpolate(data.db_final[0], ctx, data.config.basis, exclude=ctx.slot)
        q_opt = optimise(data, ctx)
    if not blocked("fig10_interp_vs_optim.png"):
        ci, ti = motion_cost(ctx, q_interp)
        co, to = motion_cost(ctx, q_opt)
        rep.notes.append(
            f"condition {ctx.condition}: interpolation cost {ci:.4g} "
            f"(torque sum {ti:.4g} N m), optimisation {co:.4g} ({to:.4g} N m)"
        )
        if co > ci:
            opt = data.config.compiler.resolved()
            rep.notes.append(
                f"the optimisation compiler ended above the interpolation's cost "
                f"(compiler.method {opt.method}, max_iters {opt.max_iters}): its budget is small"
            )
        wrote(
            "fig10_interp_vs_optim.png",
            plot_joint_angles(
                q_interp,
                q_opt,
                ctx.duration,
                robot.joint_names,
                out / "fig10_interp_vs_optim.png",
                first_label=f"interpolation (cost {ci:.3g})",
                last_label=f"optimisation (cost {co:.3g})",
                title=f"generation {last_gen}, condition {ctx.condition} left out: "
                f"catch point {target_txt} m (Fig. 10)",
            ),
        )

    # --- rendered figures: every frame in one renderer call (one GL context)
    width, height = 320, 240
    times = rnd.snapshot_times(ctx.duration, snapshots)
    views = [rnd.VIEWS["front"], rnd.VIEWS["side"]]
    jobs: dict[str, tuple[list[str], list[np.ndarray]]] = {}
    if not blocked("fig7_snapshots.png"):
        jobs["fig7_snapshots.png"] = (["generation 1", f"generation {last_gen}"], [q_first, q_last])
    if not blocked("fig9_snapshots.png"):
        jobs["fig9_snapshots.png"] = (["interpolation", "optimisation"], [q_interp, q_opt])
    catch: Any = None
    if animation and not blocked("catch.gif"):
        say("planning and generating a catch (JAX compile) ...")
        catch = catch_animation(data, ctx, gif_frames, rep.notes)
    elif not animation:
        rep.skipped["catch.gif"] = "--no-animation"
    batches, layout = [], []
    motions = [q for _, qs in jobs.values() for q in qs]
    if catch is not None:
        motions.append(catch[0])
    if not motions:
        return
    floor = rnd.floor_height(robot, motions)
    ball_target = np.tile(ctx.target, (snapshots, 1))
    for name, (labels, qs) in jobs.items():
        frames_q = [rnd.resample(q, times, ctx.duration) for q in qs]
        for view in views:
            cam = rnd.fit_camera(robot, frames_q, view, ctx.target[None])
            for label, fq in zip(labels, frames_q):
                batches.append(_Batch(fq, [cam], ball_target))
                layout.append((name, f"{label}\n{view.name}"))
    if catch is not None:
        q_gif, balls, _ = catch
        batches.append(_Batch(q_gif, [catch_camera(robot, q_gif, balls)], balls))
        layout.append(("catch.gif", ""))
    say(f"rendering {sum(len(b.q) for b in batches)} frames ...")
    try:
        images, used = _render_batches(robot, batches, renderer, width, height, floor)
    except rnd.RenderUnavailable as e:  # only with --renderer mujoco
        raise UserError(f"--renderer mujoco: {e}") from None
    rep.renderer = used
    if used.startswith("stick") and used != "stick figure":
        say(f"warning: {used}")
    by_name: dict[str, tuple[list[str], list[np.ndarray]]] = {}
    for (name, label), im in zip(layout, images):
        by_name.setdefault(name, ([], []))
        by_name[name][0].append(label)
        by_name[name][1].append(im)
    titles = {
        "fig7_snapshots.png": f"condition {ctx.condition}: generation 1 vs {last_gen} (Fig. 7)",
        "fig9_snapshots.png": f"condition {ctx.condition}: interpolation vs optimisation (Fig. 9)",
    }
    for name, (labels, ims) in by_name.items():
        path = out / name
        if name == "catch.gif":
            wrote(name, rnd.save_gif(ims[0], path, fps=catch[2] * GIF_SPEED))
            continue
        wrote(name, snapshot_figure(np.stack(ims), labels, times, path, titles[name], used))


# ------------------------------------------------------------------------------------ HTML


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
    from evojax_motion.run.checkpoint import atomic_write_text

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
    parts.append("</body></html>\n")
    return atomic_write_text(rep.out_dir / HTML_FILE, "\n".join(parts))


# ------------------------------------------------------------------------------------- CLI


def add_report_parser(subparsers) -> None:
    """Add ``report`` to the ``evojax-motion`` subcommands (``cli.entry.build_parser``)."""
    p = subparsers.add_parser(
        "report",
        help="the paper's figures and an HTML page from a run directory",
        description="Write the figures of a training run (paper Fig. 4, 5, 7-10, a cost vs "
        "human-likeness plot and a catch animation) and one self-contained report.html. "
        "Exit status: 0 all written; 1 run files missing (the other figures are written); "
        "2 no run in RUN_DIR.",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of `evojax-motion train`")
    p.add_argument("--out", default=None, help="output folder (default: RUN_DIR/report)")
    p.add_argument(
        "--condition",
        type=int,
        default=None,
        help="condition index (default: the config's train.plot_condition)",
    )
    p.add_argument("--joint", default=None, help="joint of Fig. 4 (default: the most varied)")
    p.add_argument(
        "--renderer",
        choices=("auto", "mujoco", "stick"),
        default="auto",
        help="snapshots: MuJoCo if a GL backend works (auto), MuJoCo only, or "
        "matplotlib stick figures",
    )
    p.add_argument("--snapshots", type=int, default=5, help="snapshots per motion (default 5)")
    p.add_argument("--gif-frames", type=int, default=36, help="frames of the catch animation")
    p.add_argument("--no-animation", action="store_true", help="skip catch.gif")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_report)


def run_report(args) -> int:
    """The ``report`` subcommand: 0 complete, 1 incomplete run folder (figures still written)."""
    from evojax_motion.run.cache import enable_compile_cache

    enable_compile_cache()  # a second report of a run skips most of the XLA compile time
    rep = make_report(
        args.run_dir,
        args.out,
        condition=args.condition,
        joint=args.joint,
        renderer=args.renderer,
        snapshots=args.snapshots,
        gif_frames=args.gif_frames,
        animation=not args.no_animation,
        quiet=args.quiet,
    )
    print(rep.html)
    if rep.problems:
        names = ", ".join(rep.problems)
        print(
            f"error: incomplete run folder ({names}); the other figures were written",
            file=sys.stderr,
        )
        return 1
    return 0
