"""The robot: an MJCF model, its controlled joints and its end-effector site (DESIGN 1).

Park et al. (2008, sec. 4) drive the waist and right arm of the humanoid Mahru I, a 7-DOF serial
chain, and score a movement by the torques of its inverse dynamics (eq. 4-5). Here a robot is
any MuJoCo model plus the names of the joints that move (hinge or slide, each with a range) and
of the site whose position is the task condition (the hand's catch point). `Robot` reads from
the compiled model everything the rest of the pipeline needs as plain numpy arrays: joint
limits, velocity and torque limits, a rest posture, and the addresses that map the controlled
joints into ``qpos``/``qvel``. Joints of the model that are not controlled are held at
``qpos0`` by the dynamics backends.

Shipped models (`SHIPPED_ROBOTS`, files in ``evojax_motion/models``; docs/robot_models.md):
  - ``mahru_arm``: waist yaw + right arm with de Leva (1996) adult male segment inertias;
  - ``arm6``: a 6-DOF industrial-style arm, so that nothing assumes mahru_arm's layout.

The MJCF text is kept in the `Robot` so that a database or run directory can embed it and rebuild
the same robot later (`robot_from_mjcf_text`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.errors import UserError

MODELS_DIR = Path(__file__).resolve().parent / "models"

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_JOINT_TYPE_NAMES = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}
# A keyframe written with 6 decimals may sit this far outside a limit written the same way.
_REST_TOL = 1e-6


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


def _names(m: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(m, obj, i) or f"#{i}" for i in range(count)]


def _compile(xml: str, where: str) -> mujoco.MjModel:
    """Compile MJCF text, with constraints and contacts switched off (see `Robot.mj_model`)."""
    try:
        m = mujoco.MjModel.from_xml_string(xml)
    except Exception as err:  # mujoco raises ValueError; its first line says what is wrong
        lines = str(err).strip().splitlines()
        raise UserError(
            f"{where}: MJCF does not compile: {lines[0] if lines else type(err).__name__}"
        ) from None
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT) | int(
        mujoco.mjtDisableBit.mjDSBL_CONTACT
    )
    return m


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
    mjcf: the MJCF XML text (self-contained: the model is compiled from this string).
    joint_names: (J,) controlled joints, in the order of every ``q (..., J)`` array.
    site_name: the end-effector site (the hand's grasp point for the catch conditions).
    source: where the MJCF came from (a file path), used to name it in error messages.

    Derived, cached on first use (all numpy, read-only): ``mj_model``, ``joint_ids (J,)``,
    ``qpos_adr (J,)``, ``dof_adr (J,)``, ``lower (J,)``, ``upper (J,)`` [rad or m],
    ``velocity_limit (J,)``, ``torque_limit (J,)`` (inf where the model gives none), ``rest (J,)``,
    ``site_id``, ``n_joints``. Construction validates everything and raises `UserError`.
    """

    name: str
    mjcf: str = field(repr=False)
    joint_names: tuple[str, ...]
    site_name: str
    source: str = field(default="", repr=False)

    def __post_init__(self):
        object.__setattr__(self, "joint_names", _joint_tuple(self.joint_names, self._where))
        # Validate now, so that a bad model fails where it is loaded, not deep inside a jit.
        for attr in ("joint_ids", "lower", "velocity_limit", "torque_limit", "rest", "site_id"):
            getattr(self, attr)

    def __getstate__(self) -> dict:
        # Pickle the definition only: the compiled model and arrays are rebuilt (and checked).
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __setstate__(self, state: dict) -> None:
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
        return _compile(self.mjcf, self._where)

    @functools.cached_property
    def joint_ids(self) -> np.ndarray:
        """(J,) int: MuJoCo joint ids of the controlled joints."""
        m = self.mj_model
        if not self.joint_names:
            raise UserError(f"{self._where}: joints: expected at least one controlled joint")
        available = _names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt)
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
            if not m.jnt_limited[j]:
                raise UserError(
                    f"{self._where}: joint {name!r} has no range (limited=false); expected "
                    'range="lower upper" on the joint'
                )
            lo, hi = m.jnt_range[j]
            if not lo < hi:
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
    def lower(self) -> np.ndarray:
        """(J,) float64: lower joint limits from ``jnt_range`` [rad or m]."""
        return _read_only(self.mj_model.jnt_range[self.joint_ids, 0].astype(np.float64))

    @functools.cached_property
    def upper(self) -> np.ndarray:
        """(J,) float64: upper joint limits from ``jnt_range`` [rad or m]."""
        return _read_only(self.mj_model.jnt_range[self.joint_ids, 1].astype(np.float64))

    @functools.cached_property
    def velocity_limit(self) -> np.ndarray:
        """(J,) float64 [rad/s or m/s] from <custom><numeric name="velocity_limit">; inf if absent.

        The numeric holds one value per joint of the model, in model order, so that it does not
        depend on which joints a user chooses to control.
        """
        m = self.mj_model
        k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, "velocity_limit")
        if k < 0:
            return _read_only(np.full(self.n_joints, np.inf))
        adr, size = int(m.numeric_adr[k]), int(m.numeric_size[k])
        data = np.asarray(m.numeric_data[adr : adr + size], dtype=np.float64)
        if size != m.njnt:
            raise UserError(
                f"{self._where}: custom numeric 'velocity_limit': expected {m.njnt} values (one "
                f"per joint of the model, in model order), got {size}"
            )
        limit = data[self.joint_ids]
        bad = [n for n, v in zip(self.joint_names, limit) if not v > 0]
        if bad:
            raise UserError(
                f"{self._where}: custom numeric 'velocity_limit': expected values > 0, got "
                f"{limit.tolist()} for joints {bad}"
            )
        return _read_only(limit)

    @functools.cached_property
    def torque_limit(self) -> np.ndarray:
        """(J,) float64 [N m or N]: joint ``actuatorfrcrange`` magnitude; inf where unlimited.

        An asymmetric range gives its smaller magnitude (a bound that holds both ways).
        """
        m = self.mj_model
        limit = np.full(self.n_joints, np.inf)
        for k, (name, j) in enumerate(zip(self.joint_names, self.joint_ids)):
            if not m.jnt_actfrclimited[j]:
                continue
            lo, hi = m.jnt_actfrcrange[j]
            if not lo < 0 < hi:
                raise UserError(
                    f"{self._where}: joint {name!r}: actuatorfrcrange: expected lower < 0 < "
                    f"upper, got [{lo:g}, {hi:g}]"
                )
            limit[k] = min(-lo, hi)
        return _read_only(limit)

    @functools.cached_property
    def rest(self) -> np.ndarray:
        """(J,) float64: keyframe "rest" if the model has one, else ``qpos0`` clipped to limits."""
        m = self.mj_model
        k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "rest")
        if k < 0:
            return _read_only(np.clip(m.qpos0[self.qpos_adr], self.lower, self.upper))
        rest = np.asarray(m.key_qpos[k][self.qpos_adr], dtype=np.float64)
        outside = (rest < self.lower - _REST_TOL) | (rest > self.upper + _REST_TOL)
        if np.any(outside):
            bad = {n: float(v) for n, v, o in zip(self.joint_names, rest, outside) if o}
            raise UserError(
                f"{self._where}: keyframe 'rest': expected joint values inside their ranges, "
                f"got {bad}"
            )
        return _read_only(np.clip(rest, self.lower, self.upper))

    @functools.cached_property
    def site_id(self) -> int:
        m = self.mj_model
        s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, self.site_name)
        if s < 0:
            sites = _names(m, mujoco.mjtObj.mjOBJ_SITE, m.nsite)
            have = f"the model's sites are {sites}" if sites else "the model has no sites"
            raise UserError(f"{self._where}: site: no site named {self.site_name!r}; {have}")
        return int(s)


def _default_joints(m: mujoco.MjModel) -> tuple[str, ...]:
    """All hinge and slide joints of a model, in model order."""
    return tuple(
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
        for j in range(m.njnt)
        if int(m.jnt_type[j]) in (_HINGE, _SLIDE)
    )


def robot_from_mjcf_text(
    name: str,
    xml: str,
    joints: Sequence[str] | None = None,
    site: str | None = None,
    source: str = "",
) -> Robot:
    """Build and validate a `Robot` from MJCF text (a file's content, or one embedded in a run).

    joints: controlled joints; None: every hinge/slide joint of the model, in model order.
    site: end-effector site; None: the model's only site (an error if it has several).
    source: a file path or label naming the model in error messages.
    """
    where = source or f"robot {name!r}"
    if joints is None or site is None:
        model = _compile(xml, where)  # the defaults are read from the model
        if joints is None:
            joints = _default_joints(model)
        if site is None:
            sites = _names(model, mujoco.mjtObj.mjOBJ_SITE, model.nsite)
            if len(sites) != 1:
                have = f"the model's sites are {sites}" if sites else "the model has no sites"
                raise UserError(f"{where}: site: expected the end-effector site's name; {have}")
            site = sites[0]
    names = _joint_tuple(joints, where)
    return Robot(name=name, mjcf=xml, joint_names=names, site_name=site, source=source)


def load_robot(
    spec: str | os.PathLike = "mahru_arm",
    joints: Sequence[str] | None = None,
    site: str | None = None,
) -> Robot:
    """A shipped robot by name (`SHIPPED_ROBOTS`), or an MJCF file by path.

    joints, site: override the shipped defaults; for a file, None means every hinge/slide joint
    and the model's only site (see `robot_from_mjcf_text`).
    """
    if isinstance(spec, str) and spec in SHIPPED_ROBOTS:
        entry = SHIPPED_ROBOTS[spec]
        path, name = MODELS_DIR / entry.file, spec
        joints = entry.joints if joints is None else joints
        site = entry.site if site is None else site
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
        if not path.is_file():
            raise UserError(f"{path}: MJCF file not found")
        name = path.stem
    try:
        xml = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: cannot read the MJCF file: {err}") from None
    return robot_from_mjcf_text(name, xml, joints, site, source=str(path))


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
