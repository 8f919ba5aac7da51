"""The report of a training run: the paper's figures from a run folder, and one self-contained HTML
page (``evojax-motion report RUN_DIR [--out DIR]``).

`make_report` writes them: the run folder is read by `report.run_folder`, the condition's motions
come from `report.condition`, the figures from `report.figures` and `report.plots`, the page from
`report.html`; the command's parser is `cli.report`.

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
The catch animation throws a ball through the condition's catch point
(`report.condition.catch_animation`).

Snapshots come from MuJoCo's offscreen renderer when an OpenGL backend works
(`report.render.gl_status`),
else from the matplotlib stick-figure fallback, labelled as such; the plots never need GL.

Exit status of the command: 0 every figure written; 1 some run file missing or unreadable (each
named on stderr and in the page) and only the figures that do not need it written; 2 ``RUN_DIR``
does not exist or holds no run (no ``config.yaml``, ``metrics.jsonl`` or database), or a bad
option.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evojax_motion.console import log
from evojax_motion.errors import UserError
from evojax_motion.report.condition import (
    catch_animation,
    catch_camera,
    condition_context,
    interpolate,
    motion_cost,
    optimise,
)
from evojax_motion.report.figures import (
    CATCH_FIGURE,
    FIGURES,
    plot_basis,
    plot_catch_success,
    plot_tradeoff,
    snapshot_figure,
)
from evojax_motion.report.html import write_html
from evojax_motion.report.run_folder import CATCH_FILE, RUN_FILES, load_run

REPORT_DIR = "report"
GIF_SPEED = 0.5  # playback speed of catch.gif (half speed)


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
    if data.catch is not None:
        wrote(CATCH_FIGURE, plot_catch_success(data.catch, out / CATCH_FIGURE))
    elif CATCH_FILE not in rep.problems:
        rep.notes.append(
            f"no {CATCH_FILE}: `python benchmarks/catch_success.py --train-dir "
            f"{data.run_dir}` adds catches in physics per database"
        )

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
    from evojax_motion.report import kinematics as kin
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
    times = kin.snapshot_times(ctx.duration, snapshots)
    views = [kin.VIEWS["front"], kin.VIEWS["side"]]
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
    floor = kin.floor_height(robot, motions)
    ball_target = np.tile(ctx.target, (snapshots, 1))
    for name, (labels, qs) in jobs.items():
        frames_q = [kin.resample(q, times, ctx.duration) for q in qs]
        for view in views:
            cam = kin.fit_camera(robot, frames_q, view, ctx.target[None])
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
    asked = renderer == "stick"  # stick figures asked for, not a fallback
    for name, (labels, ims) in by_name.items():
        path = out / name
        if name == "catch.gif":
            wrote(name, rnd.save_gif(ims[0], path, fps=catch[2] * GIF_SPEED))
            continue
        figure = snapshot_figure(np.stack(ims), labels, times, path, titles[name], used, asked)
        wrote(name, figure)
