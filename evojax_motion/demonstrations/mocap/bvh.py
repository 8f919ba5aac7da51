"""Reader of BVH (Biovision hierarchy) files: a skeleton plus per-frame joint rotations.

The file's HIERARCHY gives each joint an OFFSET from its parent and CHANNELS (positions and/or
rotations, in degrees, in the order listed); MOTION gives one row of channel values per frame.
Forward kinematics turns every frame into world positions of the joints, so the rest of the
import sees named points like markers: a joint's point is its origin; an ``End Site`` is named
``<joint>_end``. Rotations compose in channel order as intrinsic rotations,
``R_local = R_c1 @ R_c2 @ R_c3`` (the BVH convention); ``R = R_parent @ R_local`` and
``p = p_parent + R_parent @ (offset + translation)``. BVH is y-up; lengths are in the file's unit,
scaled to metres by ``unit_scale`` (default 0.01: centimetres, as in the CMU conversions).
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError

_AXES = {"x": 0, "y": 1, "z": 2}


def axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(F, 3, 3)`` about coordinate ``axis`` (0, 1, 2) by ``angle (F,)`` rad."""
    c, s = np.cos(angle), np.sin(angle)
    r = np.zeros((*np.shape(angle), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[..., axis, axis] = 1.0
    r[..., i, i] = c
    r[..., j, j] = c
    r[..., i, j] = -s
    r[..., j, i] = s
    return r


class _Joint(NamedTuple):
    name: str
    parent: int
    offset: np.ndarray
    channels: tuple[str, ...]
    first_channel: int


class _Tokens:
    def __init__(self, text: str):
        self.tok = text.split()
        self.i = 0

    def next(self, what: str) -> str:
        if self.i >= len(self.tok):
            raise TrialError(f"truncated: expected {what}, got the end of the file")
        self.i += 1
        return self.tok[self.i - 1]

    def expect(self, word: str) -> None:
        got = self.next(repr(word))
        if got.upper() != word.upper():
            raise TrialError(f"expected {word!r}, got {got!r}")

    def number(self, what: str) -> float:
        t = self.next(what)
        try:
            return float(t)
        except ValueError:
            raise TrialError(f"expected a number for {what}, got {t!r}") from None


def _parse_joint(
    tk: _Tokens, name: str, parent: int, joints: list, n_channels: list, end_site: bool = False
) -> None:
    """Parse one ``{ OFFSET CHANNELS children }`` block (recursively) into ``joints``."""
    tk.expect("{")
    tk.expect("OFFSET")
    offset = np.array([tk.number(f"{name} OFFSET") for _ in range(3)])
    channels: tuple[str, ...] = ()
    me = len(joints)
    if end_site:
        joints.append(_Joint(name, parent, offset, (), n_channels[0]))
        tk.expect("}")
        return
    tk.expect("CHANNELS")
    count = int(tk.number(f"{name} CHANNELS"))
    channels = tuple(tk.next(f"{name} channel").lower() for _ in range(count))
    for ch in channels:
        if ch not in ("xposition", "yposition", "zposition", "xrotation", "yrotation", "zrotation"):
            raise TrialError(f"joint {name}: unknown channel {ch!r}")
    joints.append(_Joint(name, parent, offset, channels, n_channels[0]))
    n_channels[0] += count
    while True:
        word = tk.next(f"JOINT, End Site or '}}' in {name}")
        if word == "}":
            return
        if word.upper() == "JOINT":
            _parse_joint(tk, tk.next("joint name"), me, joints, n_channels)
        elif word.upper() == "END":
            tk.expect("Site")
            _parse_joint(tk, f"{name}_end", me, joints, n_channels, end_site=True)
        else:
            raise TrialError(f"joint {name}: unexpected {word!r}")


def read_bvh(path: str | os.PathLike, unit_scale: float = 0.01) -> MarkerData:
    """Joint (and end-site) positions of every frame of a BVH file, in metres, y up."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="strict") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as e:
        raise TrialError(f"cannot read the file: {e}") from None
    head, sep, motion = text.partition("MOTION")
    if not sep:
        raise TrialError("not a BVH file or truncated: no MOTION section")
    tk = _Tokens(head)
    tk.expect("HIERARCHY")
    tk.expect("ROOT")
    joints: list[_Joint] = []
    n_channels = [0]
    _parse_joint(tk, tk.next("root name"), -1, joints, n_channels)
    mt = _Tokens(motion)
    mt.expect("Frames:")
    n_frames = int(mt.number("Frames"))
    mt.expect("Frame")
    mt.expect("Time:")
    dt = mt.number("Frame Time")
    if n_frames < 1 or not dt > 0:
        raise TrialError(f"expected Frames >= 1 and Frame Time > 0, got {n_frames}, {dt}")
    values = mt.tok[mt.i :]
    need = n_frames * n_channels[0]
    if len(values) < need:
        raise TrialError(f"truncated: {len(values)} of {need} motion values")
    try:
        motion_arr = np.asarray(values[:need], np.float64).reshape(n_frames, n_channels[0])
    except ValueError:
        raise TrialError("MOTION: expected numbers") from None
    pos = _forward_kinematics(joints, motion_arr) * unit_scale
    names = tuple(j.name for j in joints)
    return MarkerData(names, pos, 1.0 / dt, path, np.array([0.0, 1.0, 0.0]))


def _forward_kinematics(joints: list[_Joint], motion: np.ndarray) -> np.ndarray:
    """World positions ``(F, n_joints, 3)`` of every joint in the file's units."""
    f = motion.shape[0]
    rots, pos = [], []
    for j in joints:
        trans = np.broadcast_to(j.offset, (f, 3)).copy()
        rot = np.broadcast_to(np.eye(3), (f, 3, 3)).copy()
        for k, ch in enumerate(j.channels):
            v = motion[:, j.first_channel + k]
            axis = _AXES[ch[0]]
            if ch.endswith("position"):
                trans[:, axis] += v
            else:
                rot = rot @ axis_rotation(axis, np.deg2rad(v))
        if j.parent < 0:
            pos.append(trans)
            rots.append(rot)
        else:
            rp, pp = rots[j.parent], pos[j.parent]
            pos.append(pp + np.einsum("fij,fj->fi", rp, trans))
            rots.append(rp @ rot)
    return np.stack(pos, axis=1)
