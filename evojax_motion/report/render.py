"""Pictures of motions: MuJoCo offscreen snapshots and animations (the paper's Fig. 7 and 9), with a
matplotlib stick-figure fallback where no OpenGL backend exists.

MuJoCo's ``mujoco.Renderer`` needs an OpenGL context. Headless machines get one from EGL
(``MUJOCO_GL=egl``: ``libegl1`` plus Mesa's ``libegl-mesa0``/``libgl1-mesa-dri``, or an NVIDIA
driver) or OSMesa (``MUJOCO_GL=osmesa``: ``libosmesa6``). MuJoCo binds its GL backend once, when
``mujoco`` is first imported, and every module of this package imports it early; so rendering runs
in a child process (``python -m evojax_motion.report.render JOB OUT``) started with
``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM``) set. `gl_status` probes the backends once per process:
the user's ``MUJOCO_GL`` first, then `GL_BACKENDS`; a crash of a GL driver then cannot take the
caller down.

Without a backend, `render_motion` draws the same frames from forward kinematics (C MuJoCo's
``mj_kinematics``, no GL): every capsule/cylinder geom as a thick segment between its end points,
spheres as dots, boxes along their longest axis, from the same camera; frames carry the label
`STICK_LABEL`. Either way the result is ``(F, H, W, 3) uint8`` images.

Cameras are MuJoCo free cameras: the camera looks along ``(cos az cos el, sin az cos el, sin el)``
(degrees) at ``lookat`` from ``distance``. World frame of the shipped robots: x forward, y left,
z up; so `VIEWS` ``front`` (azimuth 180) faces the robot and ``side`` (azimuth 90) looks at its
right side, where the catching arm is.

Example::

    frames = render_motion(robot, q, [fit_camera(robot, [q], VIEWS["front"])], balls=ball_xyz)
    frames.images      # (F, H, W, 3) uint8
    save_gif(frames.images, "catch.gif", fps=20)
"""

from __future__ import annotations

import functools
import io
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.model.robot import Robot, robot_from_mjcf_text
from evojax_motion.settings.online import BALL_RADIUS

GL_BACKENDS = ("egl", "osmesa")
STICK_LABEL = "stick figure (fallback: no OpenGL)"
WORKER_TIMEOUT_S = 600.0
PROBE_TIMEOUT_S = 120.0
BALL_RGBA = (1.0, 0.55, 0.0, 1.0)
_DISABLED = ("disable", "disabled", "off", "false", "0")


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


class GLStatus(NamedTuple):
    """Which OpenGL backend MuJoCo's offscreen renderer can use: ``backend`` (None: none) and a
    one-line ``message`` saying what was tried."""

    backend: str | None
    message: str

    @property
    def available(self) -> bool:
        return self.backend is not None


class Frames(NamedTuple):
    """Rendered frames ``images (F, H, W, 3) uint8`` and which ``renderer`` made them."""

    images: np.ndarray
    renderer: str

    @property
    def fallback(self) -> bool:
        return self.renderer.startswith("stick")


class RenderUnavailable(RuntimeError):
    """MuJoCo's offscreen renderer could not run (no GL backend, or the backend failed)."""


# ------------------------------------------------------------------------------- kinematics


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


def _qpos(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Full ``qpos (F, nq)``: controlled joints from ``q (F, J)``, the others at ``qpos0``."""
    m = robot.mj_model
    qpos = np.tile(m.qpos0, (q.shape[0], 1))
    qpos[:, robot.qpos_adr] = q
    return qpos


def segments(robot: Robot, q) -> Segments:
    """Forward kinematics (``mj_kinematics``, no GL) of ``q (F, J)`` [rad] as geom segments.

    Capsules and cylinders: their axis; boxes and ellipsoids: their longest axis; spheres: a
    point. Planes, meshes and height fields are left out (a stick figure has no use for them).
    """
    q = np.atleast_2d(np.asarray(q, np.float64))
    m = robot.mj_model
    d = mujoco.MjData(m)
    g = mujoco.mjtGeom
    kept: list[int] = []
    axis: list[int] = []
    half: list[float] = []
    for i in range(m.ngeom):
        t, size = int(m.geom_type[i]), m.geom_size[i]
        if t in (int(g.mjGEOM_CAPSULE), int(g.mjGEOM_CYLINDER)):
            k, length = 2, float(size[1])
        elif t in (int(g.mjGEOM_BOX), int(g.mjGEOM_ELLIPSOID)):
            k = int(np.argmax(size))
            length = float(size[k])
        elif t == int(g.mjGEOM_SPHERE):
            k, length = 2, 0.0
        else:
            continue
        kept.append(i)
        axis.append(k)
        half.append(length)
    idx = np.asarray(kept, int)
    radius = np.array(
        [
            m.geom_size[i][0] if int(m.geom_type[i]) != int(g.mjGEOM_BOX) else min(m.geom_size[i])
            for i in kept
        ]
    )
    a = np.zeros((q.shape[0], idx.size, 3))
    b = np.zeros_like(a)
    for f, qpos in enumerate(_qpos(robot, q)):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        pos = d.geom_xpos[idx]
        mat = d.geom_xmat[idx].reshape(-1, 3, 3)
        direction = mat[np.arange(idx.size), :, np.asarray(axis, int)] * np.asarray(half)[:, None]
        a[f], b[f] = pos - direction, pos + direction
    return Segments(a=a, b=b, radius=radius, rgba=np.asarray(m.geom_rgba[idx], float))


def site_positions(robot: Robot, q) -> np.ndarray:
    """World position of the robot's end-effector site for ``q (F, J)``: ``(F, 3)`` [m]."""
    q = np.atleast_2d(np.asarray(q, np.float64))
    m = robot.mj_model
    d = mujoco.MjData(m)
    out = np.zeros((q.shape[0], 3))
    for f, qpos in enumerate(_qpos(robot, q)):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        out[f] = d.site_xpos[robot.site_id]
    return out


def _camera_axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    forward, right, up = _camera_axes(view.azimuth, view.elevation)
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


# ------------------------------------------------------------------------------- GL (MuJoCo)


def _job_arrays(robot, q, cameras, balls, width, height, floor, sky=True) -> dict:
    q = np.atleast_2d(np.asarray(q, np.float64))
    f = q.shape[0]
    if len(cameras) not in (1, f):
        raise ValueError(f"cameras: expected 1 or {f} (one per frame), got {len(cameras)}")
    cams = list(cameras) * (f if len(cameras) == 1 else 1)
    balls = np.full((f, 3), np.nan) if balls is None else np.asarray(balls, float).reshape(f, 3)
    return {
        "mjcf": np.asarray(robot.mjcf),
        "name": np.asarray(robot.name),
        "joints": np.asarray(robot.joint_names, dtype=str),
        "site": np.asarray(robot.site_name),
        "q": q,
        "balls": balls,
        "lookat": np.asarray([c.lookat for c in cams], float),
        "distance": np.asarray([c.distance for c in cams], float),
        "azimuth": np.asarray([c.azimuth for c in cams], float),
        "elevation": np.asarray([c.elevation for c in cams], float),
        "size": np.asarray([height, width]),
        "floor": np.asarray(np.nan if floor is None else floor, float),
        "sky": np.asarray(bool(sky)),
    }


def _add_geom(scene, gtype, size, pos, rgba, emission: float = 0.0) -> None:
    """Append a decoration geom (not part of the model) to a ``mjvScene``."""
    if scene.ngeom >= scene.maxgeom:
        return
    mujoco.mjv_initGeom(
        scene.geoms[scene.ngeom],
        int(gtype),
        np.asarray(size, np.float64),
        np.asarray(pos, np.float64),
        np.eye(3).reshape(-1),
        np.asarray(rgba, np.float32),
    )
    scene.geoms[scene.ngeom].emission = emission
    scene.ngeom += 1


def scene_model(mjcf: str, floor: float | None, sky: bool = True) -> mujoco.MjModel:
    """The robot's model dressed for pictures: a gradient sky (else black), a checker floor at
    z = ``floor`` (None: none) and a brighter headlight. Bodies and joints are untouched (same
    ``qpos``)."""
    spec = mujoco.MjSpec.from_string(mjcf)
    tex, builtin = mujoco.mjtTexture, mujoco.mjtBuiltin
    if sky:
        spec.add_texture(
            name="evojax_sky",
            type=tex.mjTEXTURE_SKYBOX,
            builtin=builtin.mjBUILTIN_GRADIENT,
            rgb1=[0.93, 0.95, 0.98],
            rgb2=[0.62, 0.68, 0.77],
            width=64,
            height=384,
        )
    if floor is not None and math.isfinite(floor):
        spec.add_texture(
            name="evojax_grid",
            type=tex.mjTEXTURE_2D,
            builtin=builtin.mjBUILTIN_CHECKER,
            rgb1=[0.78, 0.79, 0.81],
            rgb2=[0.68, 0.70, 0.73],
            width=64,
            height=64,
        )
        mat = spec.add_material(name="evojax_grid", texrepeat=[10, 10], reflectance=0.05)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "evojax_grid"
        spec.worldbody.add_geom(
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[4, 4, 0.05],
            pos=[0, 0, floor],
            material="evojax_grid",
            contype=0,
            conaffinity=0,
        )
    m = spec.compile()
    m.vis.headlight.ambient[:] = 0.35
    m.vis.headlight.diffuse[:] = 0.55
    return m


def render_in_process(job: dict) -> np.ndarray:
    """Render a job (`_job_arrays`) with ``mujoco.Renderer`` in this process: ``(F, H, W, 3)``.

    Needs ``MUJOCO_GL`` set to a working backend before ``mujoco`` was first imported (the worker
    process does that); elsewhere use `render_mujoco`.
    """
    robot = robot_from_mjcf_text(
        str(job["name"]), str(job["mjcf"]), tuple(job["joints"].tolist()), str(job["site"])
    )
    floor = float(job["floor"])
    m = scene_model(robot.mjcf, floor if math.isfinite(floor) else None, bool(job["sky"]))
    height, width = (int(x) for x in job["size"])
    m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), width)
    m.vis.global_.offheight = max(int(m.vis.global_.offheight), height)
    d = mujoco.MjData(m)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    qpos = _qpos(robot, job["q"])
    out = np.zeros((qpos.shape[0], height, width, 3), np.uint8)
    with mujoco.Renderer(m, height, width) as renderer:
        for f in range(qpos.shape[0]):
            d.qpos[:] = qpos[f]
            mujoco.mj_forward(m, d)  # kinematics plus the lights' and cameras' poses
            cam.lookat[:] = job["lookat"][f]
            cam.distance = float(job["distance"][f])
            cam.azimuth = float(job["azimuth"][f])
            cam.elevation = float(job["elevation"][f])
            renderer.update_scene(d, camera=cam)
            ball = job["balls"][f]
            if np.isfinite(ball).all():
                _add_geom(
                    renderer.scene,
                    mujoco.mjtGeom.mjGEOM_SPHERE,
                    (BALL_RADIUS, 0, 0),
                    ball,
                    BALL_RGBA,
                    emission=0.4,  # bright from any side
                )
            out[f] = renderer.render()
    return out


def _worker_env(backend: str) -> dict:
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    env["PYOPENGL_PLATFORM"] = backend  # mujoco.egl / mujoco.osmesa refuse a mismatch
    env.setdefault("JAX_PLATFORMS", "cpu")  # the worker never needs an accelerator
    # The child imports this package the way the parent found it, installed or not.
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env


def _run_worker(job: dict, backend: str, timeout: float) -> np.ndarray:
    """Render ``job`` in a child process with ``MUJOCO_GL=backend``; raise `RenderUnavailable`."""
    with tempfile.TemporaryDirectory(prefix="evojax_render_") as tmp:
        job_path, out_path = Path(tmp) / "job.npz", Path(tmp) / "out.npz"
        np.savez(job_path, **job)
        cmd = [sys.executable, "-m", "evojax_motion.report.render", str(job_path), str(out_path)]
        try:
            proc = subprocess.run(
                cmd, env=_worker_env(backend), capture_output=True, text=True, timeout=timeout
            )
        except subprocess.TimeoutExpired:
            raise RenderUnavailable(f"{backend}: renderer timed out after {timeout:g} s") from None
        if proc.returncode != 0 or not out_path.is_file():
            lines = [x for x in (proc.stderr or "").strip().splitlines() if x.strip()]
            why = lines[-1] if lines else f"exit status {proc.returncode}"
            raise RenderUnavailable(f"{backend}: {why}")
        with np.load(out_path) as f:
            return f["images"]


def _candidates() -> list[str]:
    user = os.environ.get("MUJOCO_GL", "").strip().lower()
    if user in _DISABLED:
        return []
    first = [user] if user in GL_BACKENDS else []
    return first + [b for b in GL_BACKENDS if b not in first]


_PROBE_MJCF = """<mujoco><worldbody><body><joint name="j" type="hinge" range="-1 1"/>
<geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.05"/><site name="s"/></body></worldbody>
</mujoco>"""


@functools.cache
def gl_status() -> GLStatus:
    """Find an OpenGL backend for ``mujoco.Renderer`` (once per process; see the module doc).

    Tries ``MUJOCO_GL`` when it names one of `GL_BACKENDS`, then the others; ``MUJOCO_GL=disable``
    skips them all.
    """
    candidates = _candidates()
    if not candidates:
        return GLStatus(None, "MUJOCO_GL is set to disable rendering")
    robot = robot_from_mjcf_text("probe", _PROBE_MJCF, ("j",), "s")
    cam = Camera((0.0, 0.0, 0.15), 1.0, 90.0, -10.0)
    job = _job_arrays(robot, np.zeros((1, 1)), [cam], None, 32, 24, None)
    tried = []
    for backend in candidates:
        try:
            img = _run_worker(job, backend, PROBE_TIMEOUT_S)
        except RenderUnavailable as e:
            tried.append(str(e))
            continue
        if img.std() > 0:  # a context that renders nothing is no backend either
            return GLStatus(backend, f"MuJoCo offscreen rendering with MUJOCO_GL={backend}")
        tried.append(f"{backend}: rendered a blank image")
    return GLStatus(
        None, "no OpenGL backend for MuJoCo's offscreen renderer (" + "; ".join(tried) + ")"
    )


def render_mujoco(
    robot: Robot,
    q,
    cameras: Sequence[Camera],
    balls=None,
    width: int = 320,
    height: int = 240,
    floor: float | None = None,
    backend: str | None = None,
    sky: bool = True,
) -> np.ndarray:
    """MuJoCo offscreen frames of ``q (F, J)`` [rad]: ``(F, H, W, 3) uint8``.

    ``cameras``: one for all frames or one per frame; ``balls (F, 3)`` [m] draws a ball where
    finite; ``floor``: z [m] of a floor plane (None: none); ``backend``: a GL backend (None:
    `gl_status`'s); ``sky``: a gradient sky, else a black background. Raises
    `RenderUnavailable` when no backend works.
    """
    backend = backend or gl_status().backend
    if backend is None:
        raise RenderUnavailable(gl_status().message)
    job = _job_arrays(robot, q, cameras, balls, width, height, floor, sky)
    return _run_worker(job, backend, WORKER_TIMEOUT_S)


# ------------------------------------------------------------------------ matplotlib fallback


def project(points, camera: Camera, fovy_deg: float, width: int, height: int):
    """Pinhole projection of ``points (..., 3)`` [m] as MuJoCo's free camera sees them.

    Returns pixel coordinates ``u, v (...)`` (origin top left) and ``depth (...)`` [m] along the
    view (<= 0: behind the camera) and the focal length [px].
    """
    forward, right, up = _camera_axes(camera.azimuth, camera.elevation)
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
    """The frames of `render_mujoco`, drawn with matplotlib from forward kinematics (no GL).

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


def render_motion(
    robot: Robot,
    q,
    cameras: Sequence[Camera],
    balls=None,
    width: int = 320,
    height: int = 240,
    floor: float | None = None,
    renderer: str = "auto",
) -> Frames:
    """Frames of ``q (F, J)``: MuJoCo when a GL backend works, else the stick-figure fallback.

    ``renderer``: ``"auto"``, ``"mujoco"`` (raise `RenderUnavailable` without GL) or ``"stick"``.
    ``Frames.renderer`` says which drew them, and why the fallback was needed when MuJoCo failed.
    """
    if renderer not in ("auto", "mujoco", "stick"):
        raise ValueError(f"renderer: expected auto, mujoco or stick, got {renderer!r}")
    used = "stick figure"
    if renderer != "stick":
        status = gl_status()
        if status.available:
            try:
                images = render_mujoco(robot, q, cameras, balls, width, height, floor)
                return Frames(images, f"mujoco ({status.backend})")
            except RenderUnavailable as e:
                if renderer == "mujoco":
                    raise
                used = f"stick figure (MuJoCo rendering failed: {e})"
        elif renderer == "mujoco":
            raise RenderUnavailable(status.message)
    return Frames(render_sticks(robot, q, cameras, balls, width, height, floor), used)


def snapshot_times(duration: float, count: int) -> np.ndarray:
    """``count`` evenly spaced times over ``[0, duration]`` [s], both ends included."""
    return np.linspace(0.0, float(duration), count)


def resample(q, times, duration: float) -> np.ndarray:
    """``q (T, J)`` on the uniform grid over ``[0, duration]``, linearly interpolated at
    ``times (F,)`` [s]: ``(F, J)``."""
    q = np.asarray(q, np.float64)
    s = np.linspace(0.0, float(duration), q.shape[0])
    return np.stack([np.interp(times, s, q[:, j]) for j in range(q.shape[1])], axis=1)


def save_gif(images: np.ndarray, path: str | os.PathLike, fps: float = 20.0) -> Path:
    """Write ``images (F, H, W, 3) uint8`` as a looping GIF (Pillow), atomically."""
    from PIL import Image

    from evojax_motion.run.checkpoint import atomic_write_bytes

    # An adaptive palette per frame (octree keeps small saturated areas such as the ball).
    frames = [
        Image.fromarray(np.asarray(im, np.uint8)).quantize(256, Image.Quantize.FASTOCTREE)
        for im in images
    ]
    buf = io.BytesIO()
    frames[0].save(
        buf,
        format="GIF",
        save_all=True,
        append_images=frames[1:],
        duration=round(1000.0 / fps),
        loop=0,
        optimize=False,
    )
    return atomic_write_bytes(path, buf.getvalue())


def _worker_main(argv: list[str]) -> int:
    """``python -m evojax_motion.report.render JOB.npz OUT.npz``: render JOB into OUT
    (``images``)."""
    if len(argv) != 2:
        print("usage: python -m evojax_motion.report.render JOB.npz OUT.npz", file=sys.stderr)
        return 2
    with np.load(argv[0], allow_pickle=False) as f:
        job = {k: f[k] for k in f.files}
    try:
        images = render_in_process(job)
    except Exception as e:  # any GL failure: report one line, the parent decides
        msg = str(e).strip().splitlines()
        print(f"{type(e).__name__}: {msg[0] if msg else ''}", file=sys.stderr)
        return 3
    np.savez(argv[1], images=images)
    return 0


if __name__ == "__main__":
    sys.exit(_worker_main(sys.argv[1:]))
