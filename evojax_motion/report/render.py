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

Without a backend, `render_motion` draws the same frames from forward kinematics, no GL
(`report.sticks.render_sticks`, labelled `report.sticks.STICK_LABEL`, or `ASKED_LABEL` where
``renderer`` asked for them). Either way the result is
``(F, H, W, 3) uint8`` images. Cameras (`report.kinematics.Camera`, `VIEWS`, `fit_camera`) are
MuJoCo free cameras.

Example::

    from evojax_motion.report.kinematics import VIEWS, fit_camera

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
from evojax_motion.report.kinematics import BALL_RGBA, Camera, full_qpos
from evojax_motion.report.sticks import ASKED_LABEL, STICK_LABEL, render_sticks
from evojax_motion.settings.online import BALL_RADIUS

GL_BACKENDS = ("egl", "osmesa")
WORKER_TIMEOUT_S = 600.0
PROBE_TIMEOUT_S = 120.0
_DISABLED = ("disable", "disabled", "off", "false", "0")


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
    qpos = full_qpos(robot, job["q"])
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
    label = ASKED_LABEL if renderer == "stick" else STICK_LABEL
    return Frames(render_sticks(robot, q, cameras, balls, width, height, floor, label), used)


def save_gif(images: np.ndarray, path: str | os.PathLike, fps: float = 20.0) -> Path:
    """Write ``images (F, H, W, 3) uint8`` as a looping GIF (Pillow), atomically."""
    from PIL import Image

    from evojax_motion.run.atomic import atomic_write_bytes

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
