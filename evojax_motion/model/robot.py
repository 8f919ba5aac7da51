"""The robot: an MJCF model, its controlled joints and its end effector (DESIGN 1).

Park et al. (2008, sec. 4) drive the waist and right arm of the humanoid Mahru I, a 7-DOF serial
chain, and score a movement by the torques of its inverse dynamics (eq. 4-5). Here a robot is
any MuJoCo model plus the names of the joints that move (hinge or slide) and of the site whose
position is the task condition (the hand's catch point). `Robot` reads from the compiled model
everything the rest of the pipeline needs as plain numpy arrays: joint limits (infinite for a
continuous joint), velocity and torque limits, a rest posture, and the addresses that map the
controlled joints into ``qpos``/``qvel``. Joints of the model that are not controlled are held at
``qpos0`` by the dynamics backends.

A model file is loaded the way MuJoCo loads it (`model.mjcf.read_mjcf`: ``<include>``, meshes
and textures beside the file). The `Robot` keeps one self-contained MJCF text (``Robot.mjcf``),
which a database or run folder embeds and `robot_from_mjcf_text` compiles again anywhere: a file
without includes or asset files verbatim, any other one expanded by ``MjSpec.to_xml`` with its
meshes written into the text (docs/robot_models.md). An end effector given as a body, or with an
offset, becomes a site of that text (`END_EFFECTOR_SITE`); velocity limits given in a config
become its ``velocity_limit`` numeric. The velocity and torque limits are read by `model.limits`.

Shipped models (`SHIPPED_ROBOTS`, files in ``evojax_motion/models``; docs/robot_models.md):
  - ``mahru_arm``: waist yaw + right arm with de Leva (1996) adult male segment inertias;
  - ``arm6``: a 6-DOF industrial-style arm, so that nothing assumes mahru_arm's layout.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple
from xml.etree import ElementTree

import mujoco
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.model.limits import torque_limits, velocity_limits, with_velocity_limits
from evojax_motion.model.mjcf import compile_mjcf, format_numbers, object_names, read_mjcf

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_JOINT_TYPE_NAMES = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}
# A keyframe written with 6 decimals may sit this far outside a limit written the same way.
_REST_TOL = 1e-6
REST_MARGIN = 0.05  # the rest posture keeps this fraction of a joint's range from either limit
REST_KEYFRAMES = ("rest", "home")  # keyframes taken as the rest posture, in this order
CONTINUOUS_HALF_SPAN = math.pi  # [rad] postures of a continuous hinge are drawn from rest +- this
UNLIMITED_SLIDE_HALF_SPAN = 1.0  # [m] and those of a slide joint without a range from rest +- this
END_EFFECTOR_SITE = "end_effector"  # the site added for a body end effector or an offset


class ShippedRobot(NamedTuple):
    """A robot that comes with the package: its MJCF file (in MODELS_DIR) and defaults."""

    file: str
    joints: tuple[str, ...]
    site: str


SHIPPED_ROBOTS: dict[str, ShippedRobot] = {
    "mahru_arm": ShippedRobot(
        "mahru_arm.xml",
        (
            "waist_yaw",
            "shoulder_pitch",
            "shoulder_roll",
            "shoulder_yaw",
            "elbow",
            "wrist_pitch",
            "wrist_yaw",
        ),
        "hand",
    ),
    "arm6": ShippedRobot(
        "arm6.xml",
        ("base_yaw", "shoulder_lift", "elbow_lift", "forearm_roll", "wrist_bend", "flange_roll"),
        "tool",
    ),
}


def _joint_tuple(joints: Sequence[str], where: str) -> tuple[str, ...]:
    if isinstance(joints, str):  # tuple("elbow") would be five one-letter joints
        raise UserError(
            f"{where}: joints: expected a list of joint names, got the string {joints!r}"
        )
    return tuple(joints)


def _read_only(a: np.ndarray) -> np.ndarray:
    """Cached arrays are shared by every caller: make accidental in-place edits fail loudly."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)  # eq=False: hashed by identity, usable as a jit static arg
class Robot:
    """An MJCF model with J controlled joints and an end-effector site.

    name: a shipped robot's name or the MJCF file's stem.
    mjcf: the MJCF XML text, self-contained: the model is compiled from this string alone.
    joint_names: (J,) controlled joints, in the order of every ``q (..., J)`` array.
    site_name: the end-effector site (the hand's grasp point for the catch conditions).
    source: where the MJCF came from (a file path), used to name it in error messages.
    files: the files read to make ``mjcf`` (the model file, its includes, meshes and textures);
        empty for a robot rebuilt from stored text.

    Derived, cached on first use (all numpy, read-only): ``mj_model``, ``joint_ids (J,)``,
    ``qpos_adr (J,)``, ``dof_adr (J,)``, ``continuous (J,)``, ``lower (J,)``, ``upper (J,)``
    [rad or m; -inf/+inf for a continuous joint], ``velocity_limit (J,)``, ``torque_limit (J,)``
    (inf where the model gives none) with ``torque_limit_source``, ``rest (J,)`` with
    ``rest_source``, ``site_id``, ``n_joints``. Construction validates everything and raises
    `UserError`.
    """

    name: str
    mjcf: str = field(repr=False)
    joint_names: tuple[str, ...]
    site_name: str
    source: str = field(default="", repr=False)
    files: tuple[str, ...] = field(default=(), repr=False)

    def __post_init__(self):
        object.__setattr__(self, "joint_names", _joint_tuple(self.joint_names, self._where))
        object.__setattr__(self, "files", tuple(self.files))
        # Validate now, so that a bad model fails where it is loaded, not deep inside a jit.
        for attr in ("joint_ids", "lower", "velocity_limit", "torque_limit", "rest", "site_id"):
            getattr(self, attr)

    def __getstate__(self) -> dict:
        # Pickle the definition only: the compiled model and arrays are rebuilt (and checked).
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __setstate__(self, state: dict) -> None:
        object.__setattr__(self, "files", ())  # pickles of older versions lack it
        for key, value in state.items():
            object.__setattr__(self, key, value)
        self.__post_init__()

    @property
    def _where(self) -> str:
        return self.source or f"robot {self.name!r}"

    @functools.cached_property
    def mj_model(self) -> mujoco.MjModel:
        """The compiled model, with constraints and contacts switched off.

        The project's torques are rigid-body inverse dynamics of free-space motions (eq. 4);
        joint limits are enforced by the compilers, not by constraint forces, so both dynamics
        backends must see a model without constraints whatever the MJCF's <option> says.
        """
        return compile_mjcf(self.mjcf, self._where)

    @functools.cached_property
    def joint_ids(self) -> np.ndarray:
        """(J,) int: MuJoCo joint ids of the controlled joints."""
        m = self.mj_model
        if not self.joint_names:
            raise UserError(f"{self._where}: joints: expected at least one controlled joint")
        available = object_names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt)
        ids: list[int] = []
        for k, name in enumerate(self.joint_names):
            if name in self.joint_names[:k]:
                raise UserError(f"{self._where}: joints: {name!r} is listed twice")
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j < 0:
                raise UserError(
                    f"{self._where}: joints: no joint named {name!r}; the model's joints are "
                    f"{available}"
                )
            if int(m.jnt_type[j]) not in (_HINGE, _SLIDE):
                kind = _JOINT_TYPE_NAMES.get(int(m.jnt_type[j]), str(m.jnt_type[j]))
                raise UserError(
                    f"{self._where}: joints: {name!r} is a {kind} joint; expected hinge or slide"
                )
            lo, hi = m.jnt_range[j]
            if m.jnt_limited[j] and not lo < hi:
                raise UserError(
                    f"{self._where}: joint {name!r}: range: expected lower < upper, got "
                    f"[{lo:g}, {hi:g}]"
                )
            ids.append(j)
        return _read_only(np.asarray(ids, dtype=np.int64))

    @functools.cached_property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @functools.cached_property
    def qpos_adr(self) -> np.ndarray:
        """(J,) int: where each controlled joint sits in ``qpos``."""
        return _read_only(self.mj_model.jnt_qposadr[self.joint_ids].astype(np.int64))

    @functools.cached_property
    def dof_adr(self) -> np.ndarray:
        """(J,) int: where each controlled joint sits in ``qvel``/``qacc``/``qfrc_inverse``."""
        return _read_only(self.mj_model.jnt_dofadr[self.joint_ids].astype(np.int64))

    @functools.cached_property
    def continuous(self) -> np.ndarray:
        """(J,) bool: joints without a range (no ``range``, or ``limited="false"``): a
        continuous hinge, or a slide without limits. Their `lower`/`upper` are -inf/+inf."""
        return _read_only(~self.mj_model.jnt_limited[self.joint_ids].astype(bool))

    @functools.cached_property
    def lower(self) -> np.ndarray:
        """(J,) float64: lower joint limits from ``jnt_range`` [rad or m]; -inf if continuous."""
        lo = self.mj_model.jnt_range[self.joint_ids, 0].astype(np.float64)
        return _read_only(np.where(self.continuous, -np.inf, lo))

    @functools.cached_property
    def upper(self) -> np.ndarray:
        """(J,) float64: upper joint limits from ``jnt_range`` [rad or m]; +inf if continuous."""
        hi = self.mj_model.jnt_range[self.joint_ids, 1].astype(np.float64)
        return _read_only(np.where(self.continuous, np.inf, hi))

    def posture_box(self, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)``, each (J,) and finite: where postures may be drawn from.

        A joint with limits: ``[lower + margin, upper - margin]`` [rad or m]; a continuous hinge:
        ``rest -+ CONTINUOUS_HALF_SPAN`` (one turn); a slide without limits: ``rest -+
        UNLIMITED_SLIDE_HALF_SPAN``.
        """
        hinge = self.mj_model.jnt_type[self.joint_ids] == _HINGE
        half = np.where(hinge, CONTINUOUS_HALF_SPAN, UNLIMITED_SLIDE_HALF_SPAN)
        lo = np.where(self.continuous, self.rest - half, self.lower + margin)
        hi = np.where(self.continuous, self.rest + half, self.upper - margin)
        if np.any(lo > hi):
            narrow = [n for n, a, b in zip(self.joint_names, lo, hi) if a > b]
            raise ValueError(
                f"posture_box: margin {margin} is wider than half the range of {narrow}"
            )
        return lo, hi

    def sample_postures(self, rng: np.random.Generator, n: int, margin: float = 0.0):
        """``(n, J)`` float64 postures drawn uniformly from `posture_box` (``margin``)."""
        lo, hi = self.posture_box(margin)
        return rng.uniform(lo, hi, (n, self.n_joints))

    @functools.cached_property
    def velocity_limit(self) -> np.ndarray:
        """(J,) float64 [rad/s or m/s] from <custom><numeric name="velocity_limit">; inf if absent.

        The numeric holds one value per joint of the model, in model order, so that it does not
        depend on which joints a user chooses to control; ``inf`` is no limit. A config's
        ``robot.velocity_limits`` is written into this numeric when the robot is loaded.
        """
        return _read_only(
            velocity_limits(self.mj_model, self.joint_names, self.joint_ids, self._where)
        )

    @functools.cached_property
    def _torque_limits(self) -> tuple[np.ndarray, tuple[str, ...]]:
        limit, sources = torque_limits(self.mj_model, self.joint_names, self.joint_ids, self._where)
        return _read_only(limit), sources

    @property
    def torque_limit(self) -> np.ndarray:
        """(J,) float64 [N m or N]: the largest joint torque the model allows, both ways.

        From the joint's ``actuatorfrcrange`` when ``actuatorfrclimited``; else from the
        actuators that drive the joint directly (``joint=``): the sum of their ``forcerange``
        bounds times ``|gear|``, when every one of them is ``forcelimited``; else inf (no limit).
        An asymmetric range gives its smaller magnitude (a bound that holds both ways).
        """
        return self._torque_limits[0]

    @property
    def torque_limit_source(self) -> tuple[str, ...]:
        """(J,) where each `torque_limit` comes from, in words."""
        return self._torque_limits[1]

    @functools.cached_property
    def _rest(self) -> tuple[np.ndarray, str]:
        m = self.mj_model
        key, label = _rest_keyframe(m)
        if key >= 0:
            values = np.asarray(m.key_qpos[key][self.qpos_adr], dtype=np.float64)
            source = f"keyframe {label!r}"
            outside = (values < self.lower - _REST_TOL) | (values > self.upper + _REST_TOL)
            if np.any(outside):
                bad = {n: float(v) for n, v, o in zip(self.joint_names, values, outside) if o}
                raise UserError(
                    f"{self._where}: keyframe {label!r}: expected joint values inside their "
                    f"ranges, got {bad}"
                )
        else:
            values = np.asarray(m.qpos0[self.qpos_adr], dtype=np.float64)
            source = "qpos0 (the model has no keyframe)"
        span = np.where(self.continuous, 0.0, self.upper - self.lower)
        inner_lo = np.where(self.continuous, -np.inf, self.lower + REST_MARGIN * span)
        inner_hi = np.where(self.continuous, np.inf, self.upper - REST_MARGIN * span)
        moved = (values < inner_lo) | (values > inner_hi)
        if np.any(moved):
            names = [n for n, mv in zip(self.joint_names, moved) if mv]
            source += f", moved {REST_MARGIN:.0%} of the range off the limits for {names}"
        return _read_only(np.clip(values, inner_lo, inner_hi)), source

    @property
    def rest(self) -> np.ndarray:
        """(J,) float64: the rest posture, never on a limit.

        The keyframe named ``rest``, else ``home``, else the model's first keyframe, else
        ``qpos0`` (0 unless a joint has a ``ref``); a value closer than `REST_MARGIN` of its
        joint's range to a limit is moved to that distance. A keyframe outside the limits is a
        `UserError`. `rest_source` says which was used.
        """
        return self._rest[0]

    @property
    def rest_source(self) -> str:
        """Where `rest` comes from, in words (a keyframe's name, or qpos0)."""
        return self._rest[1]

    @functools.cached_property
    def site_id(self) -> int:
        m = self.mj_model
        s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, self.site_name)
        if s < 0:
            sites = object_names(m, mujoco.mjtObj.mjOBJ_SITE, m.nsite)
            have = f"the model's sites are {sites}" if sites else "the model has no sites"
            raise UserError(f"{self._where}: site: no site named {self.site_name!r}; {have}")
        return int(s)


def _rest_keyframe(m: mujoco.MjModel) -> tuple[int, str]:
    """(keyframe id, its name) of the rest posture's keyframe (`REST_KEYFRAMES`, else the first);
    (-1, "") when the model has none."""
    for name in REST_KEYFRAMES:
        k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, name)
        if k >= 0:
            return int(k), name
    if m.nkey:
        return 0, mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, 0) or "#0"
    return -1, ""


# -- building a robot ----------------------------------------------------------------------------


def _path_joints(m: mujoco.MjModel, body: int) -> tuple[str, ...]:
    """The hinge and slide joints on the kinematic path from the root to ``body``, root first."""
    chain = []
    while body > 0:
        chain.append(body)
        body = int(m.body_parentid[body])
    return tuple(
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
        for b in reversed(chain)
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
        if int(m.jnt_type[j]) in (_HINGE, _SLIDE)
    )


def _offset(value, where: str) -> np.ndarray | None:
    if value is None:
        return None
    try:
        offset = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        offset = np.zeros(0)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise UserError(
            f"{where}: end_effector_offset: expected 3 finite numbers [m], got {value!r}"
        )
    return offset


def _add_site(xml: str, m: mujoco.MjModel, body: int, pos, quat, where: str) -> tuple[str, str]:
    """``xml`` with a new site on ``body`` at ``pos``/``quat`` (body frame); ``(xml, name)``."""
    taken = set(object_names(m, mujoco.mjtObj.mjOBJ_SITE, m.nsite))
    name, k = END_EFFECTOR_SITE, 1
    while name in taken:
        name, k = f"{END_EFFECTOR_SITE}_{k}", k + 1
    root = ElementTree.fromstring(xml)
    body_name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body) or ""
    if body == 0:
        parent = root.find("worldbody")
    else:
        parent = next((b for b in root.iter("body") if b.get("name") == body_name), None)
    if parent is None:
        raise UserError(
            f"{where}: end_effector: body {body_name or f'#{body}'!r} is not a named <body> "
            "element of the file (made by <replicate> or <attach>?); add a site to it and name "
            "that site"
        )
    attrs = {"name": name, "pos": format_numbers(pos), "quat": format_numbers(quat)}
    ElementTree.SubElement(parent, "site", attrs)
    return ElementTree.tostring(root, encoding="unicode"), name


def _end_effector_site(
    m: mujoco.MjModel, xml: str, target: str | None, offset, where: str
) -> tuple[str, str, int]:
    """``(xml, site name, body id)`` of the end effector ``target`` (a site or body name; None:
    the model's only site), with a site added where it is a body or has an offset."""
    offset = _offset(offset, where)
    sites = object_names(m, mujoco.mjtObj.mjOBJ_SITE, m.nsite)
    if target is None:
        if len(sites) != 1:
            have = f"the model's sites are {sites}" if sites else "the model has no sites"
            raise UserError(
                f"{where}: end_effector: expected the name of the end-effector site or body; {have}"
            )
        target = sites[0]
    s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, target)
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, target)
    if s >= 0:
        body = int(m.site_bodyid[s])
        if offset is None or not np.any(offset):
            return xml, target, body
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.site_quat[s])
        pos = m.site_pos[s] + rot.reshape(3, 3) @ offset
        xml, name = _add_site(xml, m, body, pos, m.site_quat[s], where)
        return xml, name, body
    if b > 0:
        pos = np.zeros(3) if offset is None else offset
        xml, name = _add_site(xml, m, b, pos, (1.0, 0.0, 0.0, 0.0), where)
        return xml, name, b
    have = f"the model's sites are {sites}" if sites else "the model has no sites"
    bodies = object_names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)[1:]
    raise UserError(
        f"{where}: end_effector: no site or body named {target!r}; {have}, its bodies {bodies}"
    )


def robot_from_mjcf_text(
    name: str,
    xml: str,
    joints: Sequence[str] | None = None,
    site: str | None = None,
    source: str = "",
    *,
    end_effector: str | None = None,
    end_effector_offset: Sequence[float] | None = None,
    velocity_limits: Mapping[str, float] | Sequence[float] | None = None,
    files: Sequence[str] = (),
) -> Robot:
    """Build and validate a `Robot` from MJCF text (`read_mjcf`'s, or one embedded in a run).

    joints: controlled joints; None: the hinge and slide joints on the kinematic path from the
      root to the end effector, root first.
    end_effector: a site or body name (``site`` is the older name of the same argument; None: the
      model's only site). end_effector_offset: ``(3,)`` [m] in the end effector's frame. A body,
      or an offset, adds a site named `END_EFFECTOR_SITE` to the text (``Robot.site_name``).
    velocity_limits: [rad/s or m/s] a mapping joint -> limit, or one limit per controlled joint;
      written into the text's ``velocity_limit`` numeric (joints left out keep the model's).
    source: a file path or label naming the model in error messages. files: see `Robot`.
    """
    where = source or f"robot {name!r}"
    if site is not None and end_effector is not None and site != end_effector:
        raise UserError(
            f"{where}: end_effector {end_effector!r} and site {site!r}: expected one of them "
            "(site is the older name of end_effector)"
        )
    target = end_effector if end_effector is not None else site
    if (
        joints is not None
        and site is not None
        and end_effector is None
        and end_effector_offset is None
        and velocity_limits is None
    ):  # a stored robot: nothing to read from the model first
        return Robot(name, xml, _joint_tuple(joints, where), site, source, tuple(files))
    model = compile_mjcf(xml, where)  # the defaults are read from the model
    xml, site_name, body = _end_effector_site(model, xml, target, end_effector_offset, where)
    if joints is None:
        joints = _path_joints(model, body)
        if not joints:
            raise UserError(
                f"{where}: joints: no hinge or slide joint between the root and the end effector "
                f"{target or site_name!r}; expected robot.joints"
            )
    names = _joint_tuple(joints, where)
    if velocity_limits is not None:
        xml = with_velocity_limits(xml, model, names, velocity_limits, where)
    return Robot(name, xml, names, site_name, source, tuple(files))


def load_robot(
    spec: str | os.PathLike = "mahru_arm",
    joints: Sequence[str] | None = None,
    site: str | None = None,
    *,
    end_effector: str | None = None,
    end_effector_offset: Sequence[float] | None = None,
    velocity_limits: Mapping[str, float] | Sequence[float] | None = None,
) -> Robot:
    """A shipped robot by name (`SHIPPED_ROBOTS`), or an MJCF file by path (`read_mjcf`).

    joints, site / end_effector, end_effector_offset, velocity_limits: see
    `robot_from_mjcf_text`; for a shipped robot None keeps its joints and site.
    """
    if isinstance(spec, str) and spec in SHIPPED_ROBOTS:
        entry = SHIPPED_ROBOTS[spec]
        path, name = MODELS_DIR / entry.file, spec
        joints = entry.joints if joints is None else joints
        if site is None and end_effector is None:
            site = entry.site
    else:
        text = os.fspath(spec)
        looks_like_path = (
            not isinstance(spec, str)
            or Path(text).suffix != ""
            or "/" in text
            or os.sep in text
            or os.path.exists(text)
        )
        if not looks_like_path:
            raise UserError(
                f"robot: unknown robot {text!r}; expected one of {sorted(SHIPPED_ROBOTS)} or a "
                "path to an MJCF .xml file"
            )
        path = Path(text)
        name = path.stem
    model = read_mjcf(path)
    return robot_from_mjcf_text(
        name,
        model.xml,
        joints,
        site,
        source=str(path),
        end_effector=end_effector,
        end_effector_offset=end_effector_offset,
        velocity_limits=velocity_limits,
        files=model.files,
    )


def robot_from_config(settings: Any) -> Robot:
    """The robot of a config's ``robot`` section (`settings.RobotConfig`): ``mjcf`` if set, else the
    shipped ``name``, with its ``joints``, ``site``/``end_effector``, ``end_effector_offset`` and
    ``velocity_limits``."""
    spec = settings.mjcf if settings.mjcf is not None else settings.name
    return load_robot(
        spec,
        joints=settings.joints,
        site=settings.site,
        end_effector=getattr(settings, "end_effector", None),
        end_effector_offset=getattr(settings, "end_effector_offset", None),
        velocity_limits=getattr(settings, "velocity_limits", None),
    )


def mj_inverse_torques(robot: Robot, q, qd, qdd, data=None) -> np.ndarray:
    """C MuJoCo ``mj_inverse`` (float64) of the controlled joints: the reference for every backend.

    ``q, qd, qdd: (T, J)`` -> ``tau (T, J)``; uncontrolled joints are held at ``qpos0``, at rest.
    ``data``: an ``MjData`` of ``robot.mj_model`` to reuse (one is made otherwise).
    """
    m = robot.mj_model
    d = mujoco.MjData(m) if data is None else data
    q, qd, qdd = (np.atleast_2d(np.asarray(a, np.float64)) for a in (q, qd, qdd))
    out = np.empty_like(q)
    for i in range(q.shape[0]):
        d.qpos[:] = m.qpos0
        d.qvel[:] = 0.0
        d.qacc[:] = 0.0
        d.qpos[robot.qpos_adr] = q[i]
        d.qvel[robot.dof_adr] = qd[i]
        d.qacc[robot.dof_adr] = qdd[i]
        mujoco.mj_inverse(m, d)
        out[i] = d.qfrc_inverse[robot.dof_adr]
    return out
