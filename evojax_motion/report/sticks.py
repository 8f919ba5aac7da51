"""The stick-figure fallback of `report.render`: the frames of MuJoCo's renderer drawn with
matplotlib from forward kinematics, where no OpenGL backend exists.

Every capsule/cylinder geom is a thick segment between its end points, spheres are dots, boxes lie
along their longest axis (`report.kinematics.segments`), seen from the same camera; frames carry
the label `STICK_LABEL`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from evojax_motion.model.robot import Robot
from evojax_motion.report.kinematics import BALL_RGBA, Camera, project, segments
from evojax_motion.settings.online import BALL_RADIUS

STICK_LABEL = "stick figure (fallback: no OpenGL)"
ASKED_LABEL = "stick figure"  # where the stick figures were asked for (``--renderer stick``)


def render_sticks(
    robot: Robot,
    q,
    cameras: Sequence[Camera],
    balls=None,
    width: int = 320,
    height: int = 240,
    floor: float | None = None,
    label: str = STICK_LABEL,
) -> np.ndarray:
    """The frames of `report.render.render_mujoco`, drawn with matplotlib from forward
    kinematics (no GL).

    Every geom is a segment (`segments`) projected through the same pinhole camera as MuJoCo's
    (same look-at, distance, angles, ``fovy``), as thick as its radius at its depth, drawn far to
    near; the ball and a floor square likewise. ``label`` is written in the top left corner.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon

    q = np.atleast_2d(np.asarray(q, np.float64))
    f = q.shape[0]
    cams = list(cameras) * (f if len(cameras) == 1 else 1)
    balls = None if balls is None else np.asarray(balls, float).reshape(f, 3)
    seg = segments(robot, q)
    fill = np.clip(seg.rgba[:, :3] * 0.85, 0, 1)
    edge = np.clip(seg.rgba[:, :3] * 0.45, 0, 1)
    fovy = float(robot.mj_model.vis.global_.fovy)
    dpi = 100.0
    pt = 72.0 / dpi  # points per pixel
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor=(0.95, 0.96, 0.98))
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    out = np.zeros((f, height, width, 3), np.uint8)
    for k in range(f):
        cam = cams[k]
        ax.cla()
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_axis_off()
        ax.set_facecolor((0.95, 0.96, 0.98))
        if floor is not None and math.isfinite(floor):
            c, half = np.asarray(cam.lookat), 0.6 * cam.distance
            corners = np.array(
                [
                    [c[0] + sx * half, c[1] + sy * half, floor]
                    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
                ]
            )
            u, v, depth, _ = project(corners, cam, fovy, width, height)
            if (depth > 0).all():
                ax.add_patch(Polygon(np.stack([u, v], 1), closed=True, fc="0.80", ec="none"))
        pa = project(seg.a[k], cam, fovy, width, height)
        pb = project(seg.b[k], cam, fovy, width, height)
        depth = 0.5 * (pa[2] + pb[2])
        for g in np.argsort(-depth):  # painter's algorithm: far geoms first
            if not (pa[2][g] > 0 and pb[2][g] > 0):
                continue
            px = 2.0 * seg.radius[g] * pa[3] / depth[g]  # diameter [px] at the geom's depth
            xs, ys = [pa[0][g], pb[0][g]], [pa[1][g], pb[1][g]]
            if np.hypot(xs[1] - xs[0], ys[1] - ys[0]) < 0.5:  # a sphere, or seen end-on
                ax.plot(xs[:1], ys[:1], "o", ms=max(px * pt, 1.0), mfc=fill[g], mec=edge[g])
                continue
            ax.plot(xs, ys, "-", lw=(px + 2) * pt, color=edge[g], solid_capstyle="round")
            ax.plot(xs, ys, "-", lw=max(px * pt, 0.5), color=fill[g], solid_capstyle="round")
        if balls is not None and np.isfinite(balls[k]).all():
            u, v, dpt, foc = project(balls[k], cam, fovy, width, height)
            if dpt > 0:
                ax.plot([u], [v], "o", ms=2 * BALL_RADIUS * foc / dpt * pt, color=BALL_RGBA[:3])
        if label:
            ax.text(4, 4, label, fontsize=6, color="0.35", va="top", ha="left")
        canvas.draw()
        out[k] = np.asarray(canvas.buffer_rgba())[:height, :width, :3]
    return out
