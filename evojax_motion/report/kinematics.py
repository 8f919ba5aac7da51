"""What a picture of a motion shows, from forward kinematics (C MuJoCo's ``mj_kinematics``, no
GL): geoms as segments, the end-effector site, cameras fitted to a motion, the pinhole projection
of MuJoCo's free camera, and the frames' times and postures.

Cameras are MuJoCo free cameras: the camera looks along ``(cos az cos el, sin az cos el, sin el)``
(degrees) at ``lookat`` from ``distance``. World frame of the shipped robots: x forward, y left,
z up; so `VIEWS` ``front`` (azimuth 180) faces the robot and ``side`` (azimuth 90) looks at its
right side, where the catching arm is. `report.render` draws the pictures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.model.robot import Robot, robot_from_mjcf_text

BALL_RGBA = (1.0, 0.55, 0.0, 1.0)


class View(NamedTuple):
    """A viewing direction: MuJoCo free-camera ``azimuth`` and ``elevation`` [deg]."""

    name: str
    azimuth: float
    elevation: float


VIEWS = {
    "front": View("front", 180.0, -8.0),
    "side": View("side", 90.0, -8.0),
    "three_quarter": View("three_quarter", 145.0, -18.0),
    "catch": View("catch", 105.0, -5.0),  # from the right, a little ahead: the ball's arc
}


class Camera(NamedTuple):
    """A MuJoCo free camera: ``lookat (3,)`` [m], ``distance`` [m], angles [deg]."""

    lookat: tuple[float, float, float]
    distance: float
    azimuth: float
    elevation: float


class Segments(NamedTuple):
    """Geoms of a robot as segments per frame: ``a, b (F, G, 3)`` end points [m] (equal for
    round geoms), ``radius (G,)`` [m], ``rgba (G, 4)``."""

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray
    rgba: np.ndarray


def robot_from_meta(meta, source: str = "") -> Robot:
    """The `Robot` a database belongs to (``DatabaseMeta``: MJCF text, joints, site)."""
    return robot_from_mjcf_text(
        meta.robot_name, meta.mjcf, meta.joint_names, meta.site_name, source=source
    )


def full_qpos(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Full ``qpos (F, nq)``: controlled joints from ``q (F, J)``, the others at ``qpos0``."""
    m = robot.mj_model
    qpos = np.tile(m.qpos0, (q.shape[0], 1))
    qpos[:, robot.qpos_adr] = q
    return qpos


def kinematics_frames(robot: Robot, q):
    """``(f, data)`` for each frame f of ``q (F, J)`` [rad]: one ``MjData`` after
    ``mj_kinematics`` at that frame's full ``qpos`` (`full_qpos`), reused from frame to frame
    (read what a frame needs before the next)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    for f, qpos in enumerate(full_qpos(robot, np.atleast_2d(np.asarray(q, np.float64)))):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        yield f, d


# Geom groups MuJoCo's viewer shows by default (``mjVisual``'s geomgroup 0-2); published models
# keep their collision geoms in group 3, duplicates of the visual ones.
SHOWN_GROUPS = 3


def segments(robot: Robot, q) -> Segments:
    """Forward kinematics (``mj_kinematics``, no GL) of ``q (F, J)`` [rad] as geom segments.

    Capsules and cylinders: their axis; boxes and ellipsoids: their longest axis; spheres: a
    point; meshes (published models are made of them): the longest axis of their bounding box
    (``geom_aabb``), as a box. Only geoms of the groups MuJoCo shows by default
    (`SHOWN_GROUPS`); planes and height fields are left out (a stick figure has no use for them).
    A model without any such geom is drawn as its bodies' chain (`body_chain`).
    """
    q = np.atleast_2d(np.asarray(q, np.float64))
    m = robot.mj_model
    g = mujoco.mjtGeom
    kept: list[int] = []
    axis: list[int] = []
    half: list[float] = []
    radius: list[float] = []
    centre: list[np.ndarray] = []  # [m] in the geom's frame: a mesh's box is off its origin
    for i in range(m.ngeom):
        t, size = int(m.geom_type[i]), m.geom_size[i]
        offset = np.zeros(3)
        if m.geom_group[i] >= SHOWN_GROUPS:
            continue
        if t in (int(g.mjGEOM_CAPSULE), int(g.mjGEOM_CYLINDER)):
            k, length, r = 2, float(size[1]), float(size[0])
        elif t in (int(g.mjGEOM_BOX), int(g.mjGEOM_ELLIPSOID)):
            k = int(np.argmax(size))
            length = float(size[k])
            r = float(min(size)) if t == int(g.mjGEOM_BOX) else float(size[0])
        elif t == int(g.mjGEOM_SPHERE):
            k, length, r = 2, 0.0, float(size[0])
        elif t == int(g.mjGEOM_MESH):
            offset, box = np.asarray(m.geom_aabb[i][:3]), np.asarray(m.geom_aabb[i][3:])
            k = int(np.argmax(box))
            length, r = float(box[k]), float(min(box))
        else:
            continue
        kept.append(i)
        axis.append(k)
        half.append(length)
        radius.append(r)
        centre.append(offset)
    if not kept:
        return body_chain(robot, q)
    idx = np.asarray(kept, int)
    a = np.zeros((q.shape[0], idx.size, 3))
    b = np.zeros_like(a)
    local = np.asarray(centre).reshape(-1, 3)
    for f, d in kinematics_frames(robot, q):
        mat = d.geom_xmat[idx].reshape(-1, 3, 3)
        pos = d.geom_xpos[idx] + np.einsum("gij,gj->gi", mat, local)
        direction = mat[np.arange(idx.size), :, np.asarray(axis, int)] * np.asarray(half)[:, None]
        a[f], b[f] = pos - direction, pos + direction
    return Segments(
        a=a, b=b, radius=np.asarray(radius, float), rgba=np.asarray(m.geom_rgba[idx], float)
    )


CHAIN_RADIUS = 0.02  # [m] of `body_chain`'s segments
CHAIN_RGBA = (0.6, 0.6, 0.65, 1.0)


def body_chain(robot: Robot, q) -> Segments:
    """A model's bodies as a stick figure for ``q (F, J)``: a segment from each body's parent's
    origin to its own, and one from the end effector's body to its site; `CHAIN_RADIUS`."""
    q = np.atleast_2d(np.asarray(q, np.float64))
    m = robot.mj_model
    child = np.arange(1, m.nbody)
    parent = m.body_parentid[child]
    site_body = int(m.site_bodyid[robot.site_id])
    a = np.zeros((q.shape[0], child.size + 1, 3))
    b = np.zeros_like(a)
    for f, d in kinematics_frames(robot, q):
        a[f, :-1], b[f, :-1] = d.xpos[parent], d.xpos[child]
        a[f, -1], b[f, -1] = d.xpos[site_body], d.site_xpos[robot.site_id]
    n = child.size + 1
    return Segments(a=a, b=b, radius=np.full(n, CHAIN_RADIUS), rgba=np.tile(CHAIN_RGBA, (n, 1)))


def site_positions(robot: Robot, q) -> np.ndarray:
    """World position of the robot's end-effector site for ``q (F, J)``: ``(F, 3)`` [m]."""
    q = np.atleast_2d(np.asarray(q, np.float64))
    out = np.zeros((q.shape[0], 3))
    for f, d in kinematics_frames(robot, q):
        out[f] = d.site_xpos[robot.site_id]
    return out


def camera_axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MuJoCo free camera's ``forward, right, up`` unit vectors for angles in degrees."""
    az, el = math.radians(azimuth), math.radians(elevation)
    forward = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def geom_points(robot: Robot, motions: Sequence[np.ndarray]) -> np.ndarray:
    """End points of every geom segment of every motion ``(F, J)``, grown by the radius along
    each axis: ``(P, 3)`` [m] (what a camera must keep in view)."""
    pts = []
    for q in motions:
        s = segments(robot, q)
        for ends in (s.a, s.b):
            for k in range(3):
                step = np.zeros(3)
                step[k] = 1.0
                r = s.radius[None, :, None] * step
                pts += [(ends - r).reshape(-1, 3), (ends + r).reshape(-1, 3)]
    return np.concatenate(pts)


def fit_camera(
    robot: Robot,
    motions: Sequence[np.ndarray],
    view: View,
    extra_points=None,
    aspect: float = 4.0 / 3.0,
    margin: float = 1.06,
) -> Camera:
    """A camera of ``view`` that keeps every geom of every motion ``(F, J)`` (and the finite rows
    of ``extra_points (P, 3)``, e.g. the catch point) in a picture of width/height ``aspect``.

    The look-at point centres the points' extent across the view; the distance is the smallest at
    which every point lies inside the perspective frustum (MuJoCo's vertical ``fovy``), times
    ``margin``.
    """
    pts = geom_points(robot, motions)
    if extra_points is not None:
        extra = np.asarray(extra_points, float).reshape(-1, 3)
        pts = np.concatenate([pts, extra[np.isfinite(extra).all(axis=1)]])
    forward, right, up = camera_axes(view.azimuth, view.elevation)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    x, y = (pts - centre) @ right, (pts - centre) @ up
    centre = centre + right * 0.5 * (x.max() + x.min()) + up * 0.5 * (y.max() + y.min())
    rel = pts - centre
    x, y, z = rel @ right, rel @ up, rel @ forward
    tan_y = math.tan(0.5 * math.radians(float(robot.mj_model.vis.global_.fovy)))
    tan_x = tan_y * aspect
    # a point at depth z (along the view) is inside when |x| <= (distance + z) tan_x, same for y
    distance = float(np.max(np.maximum(np.abs(x) / tan_x, np.abs(y) / tan_y) - z))
    lookat = (float(centre[0]), float(centre[1]), float(centre[2]))
    return Camera(lookat, margin * distance, view.azimuth, view.elevation)


def floor_height(robot: Robot, motions: Sequence[np.ndarray]) -> float:
    """z [m] of the lowest geom surface over the motions (where a floor is drawn)."""
    lows = []
    for q in motions:
        s = segments(robot, q)
        lows.append(min(s.a[..., 2].min(), s.b[..., 2].min()) - s.radius.max(initial=0.0))
    return float(min(lows))


def catch_frames(robot: Robot, t_motion, q, ball_times, ball, catch_time: float, times):
    """Arm and ball of a catch at ``times (F,)`` [s after the ball's release].

    ``t_motion (T,)``: the motion's uniform time grid [s after release], ``q (T, J)``: the arm
    rests at ``q[0]`` before it and holds ``q[-1]`` after; ``ball_times (S,)``, ``ball (S, 3)``:
    the flight, linearly interpolated until ``catch_time``; from then on the ball sits at the
    hand (the end-effector site). Returns ``q (F, J)``, ``ball (F, 3)``.
    """
    times = np.asarray(times, float)
    t_motion = np.asarray(t_motion, float)
    q_f = resample(q, times - t_motion[0], t_motion[-1] - t_motion[0])
    ball = np.asarray(ball, float)
    ball_f = np.stack([np.interp(times, ball_times, ball[:, k]) for k in range(3)], axis=1)
    caught = times >= catch_time
    if caught.any():
        ball_f[caught] = site_positions(robot, q_f[caught])
    return q_f, ball_f


def project(points, camera: Camera, fovy_deg: float, width: int, height: int):
    """Pinhole projection of ``points (..., 3)`` [m] as MuJoCo's free camera sees them.

    Returns pixel coordinates ``u, v (...)`` (origin top left) and ``depth (...)`` [m] along the
    view (<= 0: behind the camera) and the focal length [px].
    """
    forward, right, up = camera_axes(camera.azimuth, camera.elevation)
    eye = np.asarray(camera.lookat) - camera.distance * forward
    rel = np.asarray(points, float) - eye
    depth = rel @ forward
    focal = 0.5 * height / math.tan(0.5 * math.radians(fovy_deg))
    safe = np.where(depth > 1e-6, depth, np.nan)
    return (
        0.5 * width + focal * (rel @ right) / safe,
        0.5 * height - focal * (rel @ up) / safe,
        depth,
        focal,
    )


def snapshot_times(duration: float, count: int) -> np.ndarray:
    """``count`` evenly spaced times over ``[0, duration]`` [s], both ends included."""
    return np.linspace(0.0, float(duration), count)


def resample(q, times, duration: float) -> np.ndarray:
    """``q (T, J)`` on the uniform grid over ``[0, duration]``, linearly interpolated at
    ``times (F,)`` [s]: ``(F, J)``."""
    q = np.asarray(q, np.float64)
    s = np.linspace(0.0, float(duration), q.shape[0])
    return np.stack([np.interp(times, s, q[:, j]) for j in range(q.shape[1])], axis=1)
