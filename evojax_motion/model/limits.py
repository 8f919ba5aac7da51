"""Velocity and torque limits read from a compiled model, and velocity limits written into MJCF.

Velocity limits live in the model's ``<custom><numeric name="velocity_limit">`` (`VELOCITY_NUMERIC`:
one value per joint of the model, in model order); a config's ``robot.velocity_limits`` is
written there (`with_velocity_limits`). Torque limits come from a joint's ``actuatorfrcrange`` or
from the force ranges of the actuators that drive it (`torque_limits`; docs/robot_models.md).
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from xml.etree import ElementTree

import mujoco
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.model.mjcf import format_numbers, object_names

_ACTUATED_JOINT = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))
VELOCITY_NUMERIC = "velocity_limit"  # <custom><numeric> holding one velocity limit per joint


def velocity_limits(
    m: mujoco.MjModel, joint_names: tuple[str, ...], joint_ids: np.ndarray, where: str
) -> np.ndarray:
    """(J,) float64 [rad/s or m/s] of the joints ``joint_ids`` from the velocity-limit numeric;
    inf where the model has none (`Robot.velocity_limit`)."""
    data = _velocity_numeric(m, where)
    if data is None:
        return np.full(len(joint_names), np.inf)
    limit = data[joint_ids]
    bad = [n for n, v in zip(joint_names, limit) if not v > 0]
    if bad:
        raise UserError(
            f"{where}: custom numeric 'velocity_limit': expected values > 0, got "
            f"{limit.tolist()} for joints {bad}"
        )
    return limit


def torque_limits(
    m: mujoco.MjModel, joint_names: tuple[str, ...], joint_ids: np.ndarray, where: str
) -> tuple[np.ndarray, tuple[str, ...]]:
    """(J,) float64 torque limits [N m or N] of the joints ``joint_ids`` and where each comes
    from, in words (`Robot.torque_limit`, `Robot.torque_limit_source`)."""
    limit = np.full(len(joint_names), np.inf)
    sources = []
    for k, (name, j) in enumerate(zip(joint_names, joint_ids)):
        if m.jnt_actfrclimited[j]:
            limit[k] = _symmetric_bound(
                m.jnt_actfrcrange[j], f"{where}: joint {name!r}: actuatorfrcrange"
            )
            sources.append("joint actuatorfrcrange")
            continue
        acts = [
            a
            for a in range(m.nu)
            if int(m.actuator_trntype[a]) in _ACTUATED_JOINT and m.actuator_trnid[a, 0] == j
        ]
        act_names = object_names(m, mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu)
        unlimited = [act_names[a] for a in acts if not m.actuator_forcelimited[a]]
        if not acts:
            sources.append("none")
        elif unlimited:
            sources.append(f"none (actuator {unlimited[0]!r} has no forcerange)")
        else:
            limit[k] = sum(
                _symmetric_bound(
                    m.actuator_forcerange[a],
                    f"{where}: actuator {act_names[a]!r}: forcerange",
                )
                * abs(float(m.actuator_gear[a, 0]))
                for a in acts
            )
            quoted = ", ".join(repr(act_names[a]) for a in acts)
            sources.append(f"actuator {quoted} forcerange x |gear|")
    return limit, tuple(sources)


def _symmetric_bound(lo_hi, what: str) -> float:
    """The magnitude a range ``[lo, hi]`` with ``lo < 0 < hi`` allows both ways."""
    lo, hi = (float(x) for x in lo_hi)
    if not lo < 0 < hi:
        raise UserError(f"{what}: expected lower < 0 < upper, got [{lo:g}, {hi:g}]")
    return min(-lo, hi)


def _velocity_numeric(m: mujoco.MjModel, where: str) -> np.ndarray | None:
    """(njnt,) float64 values of the model's velocity-limit numeric, or None without one."""
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, VELOCITY_NUMERIC)
    if k < 0:
        return None
    adr, size = int(m.numeric_adr[k]), int(m.numeric_size[k])
    if size != m.njnt:
        raise UserError(
            f"{where}: custom numeric 'velocity_limit': expected {m.njnt} values (one "
            f"per joint of the model, in model order), got {size}"
        )
    return np.asarray(m.numeric_data[adr : adr + size], dtype=np.float64)


def with_velocity_limits(
    xml: str, m: mujoco.MjModel, joints: tuple[str, ...], limits, where: str
) -> str:
    """``xml`` with its velocity-limit numeric holding ``limits`` (a mapping joint -> rad/s or
    m/s, or one value per controlled joint) over the model's own values."""
    key = f"{where}: velocity_limits"
    if isinstance(limits, Mapping):
        given = dict(limits)
        unknown = [n for n in given if n not in joints]
        if unknown:
            raise UserError(
                f"{key}: {unknown[0]!r} is not a controlled joint; expected some of {list(joints)}"
            )
    elif isinstance(limits, (Sequence, np.ndarray)) and not isinstance(limits, str):
        if len(limits) != len(joints):
            raise UserError(
                f"{key}: expected {len(joints)} values (one per controlled joint {list(joints)}) "
                f"or a mapping joint: limit, got {len(limits)}"
            )
        given = dict(zip(joints, limits))
    else:
        raise UserError(
            f"{key}: expected a list of numbers or a mapping joint: limit, got {limits!r}"
        )
    values = _velocity_numeric(m, where)
    values = np.full(m.njnt, np.inf) if values is None else values.copy()
    for name, value in given.items():
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value) > 0
        if not ok:  # (NaN > 0 is false)
            raise UserError(f"{key}: {name}: expected a number > 0 [rad/s or m/s], got {value!r}")
        values[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)] = float(value)
    root = ElementTree.fromstring(xml)
    for custom in root.iter("custom"):
        for numeric in list(custom):
            if numeric.tag == "numeric" and numeric.get("name") == VELOCITY_NUMERIC:
                custom.remove(numeric)
    found = root.find("custom")
    custom = ElementTree.SubElement(root, "custom") if found is None else found
    attrs = {"name": VELOCITY_NUMERIC, "data": format_numbers(values)}
    ElementTree.SubElement(custom, "numeric", attrs)
    return ElementTree.tostring(root, encoding="unicode")
