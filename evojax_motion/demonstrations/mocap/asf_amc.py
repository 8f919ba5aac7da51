"""Reader of Acclaim ASF/AMC files (CMU Graphics Lab and HDM05 motion-capture databases).

The ASF file is the skeleton: per bone a unit ``direction`` and a ``length`` in the global frame of
the zero pose, a local frame given by ``axis ax ay az ORDER`` (degrees) and its rotational ``dof``;
``:hierarchy`` gives the parents. The AMC file holds, per frame, the root's translation and
rotation and each bone's dof values. Forward kinematics (Acclaim's definition):

    C = axis rotation of the bone, M = dof rotation (Rz Ry Rx of the rx, ry, rz values)
    R_bone = R_parent @ C @ M @ C^-1,     end_bone = end_parent + R_bone @ (direction * length)

Rotations given by an order string ``XYZ`` are applied about fixed axes in that order
(``R = Rz @ Ry @ Rx``), as in the CMU reference viewer. The root's point is its translation; a
bone's point is its distal end (so ``rclavicle`` names the shoulder, ``rhumerus`` the elbow). ASF is
y-up; lengths are in ``1/length`` inches (``:units length 0.45`` in CMU files), returned in metres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from evojax_motion.demonstrations.mocap.bvh import axis_rotation
from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError

INCH = 0.0254  # [m]
DEFAULT_RATE = 120.0  # [Hz] CMU and HDM05 record at 120 Hz; AMC files do not say


@dataclass(frozen=True)
class Bone:
    name: str
    direction: np.ndarray  # (3,) unit, global zero pose
    length: float  # file units
    axis: np.ndarray  # (3,) degrees
    axis_order: str  # e.g. "XYZ"
    dof: tuple[str, ...]  # subset of rx ry rz, in AMC column order


@dataclass(frozen=True)
class Skeleton:
    bones: dict[str, Bone]
    parent: dict[str, str]  # bone -> parent bone or "root"
    order: tuple[str, ...]  # bones, parents before children
    root_order: tuple[str, ...]  # AMC root columns, e.g. TX TY TZ RX RY RZ
    root_axis: np.ndarray  # (3,) degrees
    root_axis_order: str
    length_to_m: float
    degrees: bool
    source: str


def euler(angles_deg: np.ndarray, order: str) -> np.ndarray:
    """``(..., 3)`` x/y/z angles [deg] -> ``(..., 3, 3)`` rotation, applied about fixed axes in
    ``order`` (``"XYZ"``: x first, so ``R = Rz @ Ry @ Rx``)."""
    a = np.deg2rad(np.asarray(angles_deg, np.float64))
    r = np.broadcast_to(np.eye(3), (*a.shape[:-1], 3, 3)).copy()
    for ch in order.upper():
        k = "XYZ".index(ch)
        r = axis_rotation(k, a[..., k]) @ r
    return r


def _floats(parts: list[str], n: int, where: str) -> np.ndarray:
    try:
        vals = [float(p.strip("()")) for p in parts[:n]]
    except ValueError:
        raise TrialError(f"{where}: expected {n} numbers, got {parts[:n]}") from None
    if len(vals) != n:
        raise TrialError(f"{where}: expected {n} numbers, got {parts}")
    return np.asarray(vals)


def read_asf(path: str | os.PathLike, unit_scale: float | None = None) -> Skeleton:
    """Parse an ASF skeleton. ``unit_scale``: metres per file unit (default: from ``:units``)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = [ln.split("#")[0].strip() for ln in f]
    except OSError as e:
        raise TrialError(f"cannot read the skeleton: {e}") from None
    lines = [ln for ln in lines if ln]
    section, bones, parent = "", {}, {}
    length_unit, degrees = 1.0, True
    root_order: tuple[str, ...] = ("TX", "TY", "TZ", "RX", "RY", "RZ")
    root_axis, root_axis_order = np.zeros(3), "XYZ"
    cur: dict | None = None
    for ln in lines:
        parts = ln.split()
        if ln.startswith(":"):
            section = parts[0][1:].lower()
            continue
        key = parts[0].lower()
        if section == "units":
            if key == "length":
                length_unit = float(parts[1])
            elif key == "angle":
                degrees = parts[1].lower().startswith("deg")
        elif section == "root":
            if key == "order":
                root_order = tuple(p.upper() for p in parts[1:])
            elif key == "axis":
                root_axis_order = parts[1].upper()
            elif key == "orientation":
                root_axis = _floats(parts[1:], 3, f"{path}: root orientation")
        elif section == "bonedata":
            if key == "begin":
                cur = {"dof": ()}
            elif key == "end":
                if cur is None or not {"name", "direction", "length"} <= set(cur):
                    raise TrialError(f"{path}: a bone lacks name, direction or length")
                cur.setdefault("axis", (np.zeros(3), "XYZ"))
                d = cur["direction"]
                n = np.linalg.norm(d)
                bones[cur["name"]] = Bone(
                    cur["name"],
                    d / n if n > 0 else d,
                    cur["length"],
                    cur["axis"][0],
                    cur["axis"][1],
                    cur["dof"],
                )
                cur = None
            elif cur is not None:
                if key == "name":
                    cur["name"] = parts[1]
                elif key == "direction":
                    cur["direction"] = _floats(parts[1:], 3, f"{path}: direction")
                elif key == "length":
                    cur["length"] = float(parts[1])
                elif key == "axis":
                    cur["axis"] = (_floats(parts[1:], 3, f"{path}: axis"), parts[4].upper())
                elif key == "dof":
                    dof = tuple(p.lower() for p in parts[1:])
                    bad = [d for d in dof if d not in ("rx", "ry", "rz")]
                    if bad:
                        raise TrialError(f"{path}: bone {cur.get('name')}: dof {bad} unsupported")
                    cur["dof"] = dof
        elif section == "hierarchy" and key not in ("begin", "end"):
            for child in parts[1:]:
                parent[child] = parts[0]
    if not bones:
        raise TrialError(f"{path}: no :bonedata (not an ASF skeleton, or truncated)")
    missing = [b for b in bones if b not in parent]
    if missing:
        raise TrialError(f"{path}: bones {missing[:3]} have no parent in :hierarchy")
    order: list[str] = []
    placed = {"root"}
    while len(order) < len(bones):
        ready = [b for b in bones if b not in placed and parent[b] in placed]
        if not ready:
            raise TrialError(f"{path}: :hierarchy has a cycle or names an unknown bone")
        order.extend(ready)
        placed.update(ready)
    scale = INCH / length_unit if unit_scale is None else unit_scale
    return Skeleton(
        bones, parent, tuple(order), root_order, root_axis, root_axis_order, scale, degrees, path
    )


def read_amc(path: str | os.PathLike, skeleton: Skeleton, rate: float = DEFAULT_RATE) -> MarkerData:
    """Bone end positions of every frame of an AMC motion, in metres, y up."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = [ln.strip() for ln in f]
    except OSError as e:
        raise TrialError(f"cannot read the file: {e}") from None
    degrees = skeleton.degrees
    frames: list[dict[str, list[float]]] = []
    for k, ln in enumerate(lines):
        if not ln or ln.startswith("#"):
            continue
        if ln.startswith(":"):
            if ln.upper().startswith(":RADIANS"):
                degrees = False
            continue
        parts = ln.split()
        if len(parts) == 1 and parts[0].isdigit():
            frames.append({})
            continue
        if not frames:
            raise TrialError(f"line {k + 1}: data before the first frame number")
        try:
            frames[-1][parts[0]] = [float(v) for v in parts[1:]]
        except ValueError:
            raise TrialError(f"line {k + 1}: expected numbers, got {parts[1:]}") from None
    if not frames:
        raise TrialError("no frames in the AMC file")
    expected = {"root": len(skeleton.root_order)}
    expected.update({b: len(skeleton.bones[b].dof) for b in skeleton.order})
    for i, fr in enumerate(frames):
        lacking = [b for b, n in expected.items() if n > 0 and len(fr.get(b, ())) != n]
        if lacking:
            what = "truncated: last frame" if i == len(frames) - 1 else f"frame {i + 1}"
            raise TrialError(f"{what} lacks values for {lacking[:3]}")
    values = {b: np.asarray([fr.get(b, []) for fr in frames]) for b in expected}
    conv = 1.0 if degrees else 180.0 / np.pi
    return _forward_kinematics(skeleton, values, conv, path, rate)


def _forward_kinematics(sk: Skeleton, values: dict, conv: float, path: str, rate: float):
    f = values["root"].shape[0]
    root = values["root"]
    t = np.zeros((f, 3))
    rot_xyz = np.zeros((f, 3))
    order = ""
    for c, name in enumerate(sk.root_order):
        axis = "XYZ".index(name[1])
        if name.startswith("T"):
            t[:, axis] = root[:, c]
        else:
            rot_xyz[:, axis] = root[:, c] * conv
            order += name[1]
    c_root = euler(sk.root_axis, sk.root_axis_order)
    r_root = c_root @ euler(rot_xyz, order or "XYZ") @ c_root.T
    rots, ends = {"root": r_root}, {"root": t}
    for b in sk.order:
        bone = sk.bones[b]
        m = np.zeros((f, 3))
        for c, d in enumerate(bone.dof):
            m[:, "xyz".index(d[1])] = values[b][:, c] * conv
        c_b = euler(bone.axis, bone.axis_order)
        r = rots[sk.parent[b]] @ c_b @ euler(m, "XYZ") @ c_b.T
        rots[b] = r
        ends[b] = ends[sk.parent[b]] + np.einsum("fij,j->fi", r, bone.direction * bone.length)
    names = ("root", *sk.order)
    pos = np.stack([ends[n] for n in names], axis=1) * sk.length_to_m
    return MarkerData(names, pos, rate, path, np.array([0.0, 1.0, 0.0]))


def read_asf_amc(
    amc: str | os.PathLike,
    asf: str | os.PathLike,
    rate: float = DEFAULT_RATE,
    unit_scale: float | None = None,
) -> MarkerData:
    """Convenience: `read_asf` then `read_amc`."""
    return read_amc(amc, read_asf(asf, unit_scale), rate)
