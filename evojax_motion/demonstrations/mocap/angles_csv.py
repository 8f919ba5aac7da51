"""Reader of plain joint-angle CSV files: a header row of column names, one row per frame.

    time,waist_yaw,shoulder_pitch,...      <- a time column [s] is optional (else: ``rate``)
    0.00,0.0,12.5,...

Angles are in degrees unless ``degrees=False``. Columns are matched to a robot's joints by name,
or by an `AngleMap` (``joint: column``, with an optional sign/scale and offset in degrees) for files
whose columns are anatomical angles, e.g. the UE ADL ``*angles.csv`` files.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from evojax_motion.demonstrations.mocap.markers import AngleData, TrialError
from evojax_motion.errors import UserError

TIME_COLUMNS = ("time", "t", "time_s", "time [s]", "time (s)")


def read_angles_csv(
    path: str | os.PathLike, rate: float | None = None, degrees: bool = True
) -> AngleData:
    """Read a joint-angle CSV. ``rate`` [Hz] is needed when the file has no time column."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise TrialError(f"cannot read the file: {e}") from None
    if len(rows) < 3:
        raise TrialError("expected a header row and at least two rows of angles")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header) or any(not h for h in header):
        raise TrialError("the header must name every column once")
    ncol = len(header)
    values = []
    for k, r in enumerate(rows[1:], start=2):
        if len(r) < ncol:
            raise TrialError(f"truncated: line {k} has {len(r)} of {ncol} fields")
        try:
            values.append([float(c) for c in r[:ncol]])
        except ValueError:
            raise TrialError(f"line {k}: expected numbers, got {r[:4]!r}") from None
    arr = np.asarray(values)
    if not np.isfinite(arr).all():
        raise TrialError("angles must be finite numbers (no gaps)")
    tcol = [i for i, h in enumerate(header) if h.lower() in TIME_COLUMNS]
    if tcol:
        t = arr[:, tcol[0]]
        dt = np.diff(t)
        if not (dt > 0).all():
            raise TrialError(f"column {header[tcol[0]]!r}: times must increase")
        if np.ptp(dt) > 1e-3 * dt.mean():
            raise TrialError(f"column {header[tcol[0]]!r}: samples must be evenly spaced")
        file_rate = 1.0 / dt.mean()
        if rate is not None and abs(file_rate - rate) > 1e-3 * rate:
            raise TrialError(f"time column says {file_rate:.4g} Hz but --rate is {rate:g} Hz")
        rate = file_rate
        keep = [i for i in range(ncol) if i != tcol[0]]
    else:
        if rate is None:
            raise TrialError("no time column: give the sampling rate (--rate HZ)")
        keep = list(range(ncol))
    angles = arr[:, keep]
    if degrees:
        angles = np.deg2rad(angles)
    return AngleData(tuple(header[i] for i in keep), angles, float(rate), path)


class AngleSource(NamedTuple):
    """A robot joint's angle = ``scale * column + offset`` [rad]."""

    column: str
    scale: float = 1.0
    offset: float = 0.0  # [rad]


AngleMap = Mapping[str, AngleSource]


def load_angle_map(path: str | os.PathLike) -> dict[str, AngleSource]:
    """Read a YAML angle map: ``robot_joint: column`` or ``{column, scale, offset_deg}``."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise UserError(f"{path}: cannot read the angle map: {e}") from None
    if not isinstance(data, Mapping) or not data:
        raise UserError(f"{path}: expected a mapping robot_joint -> column")
    out = {}
    for joint, spec in data.items():
        if isinstance(spec, str):
            spec = {"column": spec}
        if not isinstance(spec, Mapping) or "column" not in spec:
            raise UserError(
                f"{path}: {joint}: expected a column name or {{column, scale, offset_deg}}}}"
            )
        extra = set(spec) - {"column", "scale", "offset_deg"}
        if extra:
            raise UserError(f"{path}: {joint}: unknown keys {sorted(extra)}")
        try:
            out[str(joint)] = AngleSource(
                str(spec["column"]),
                float(spec.get("scale", 1.0)),
                float(np.deg2rad(float(spec.get("offset_deg", 0.0)))),
            )
        except (TypeError, ValueError):
            raise UserError(f"{path}: {joint}: scale and offset_deg must be numbers") from None
    return out


def angles_to_robot(
    data: AngleData,
    joint_names: tuple[str, ...],
    rest: np.ndarray,
    angle_map: AngleMap | None = None,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """``q (F, J)`` [rad] for the robot's joints; joints that no column gives stay at ``rest``.

    Without ``angle_map`` columns are matched by joint name. Raises `TrialError` when no joint is
    matched or a mapped column is missing. Returns ``(q, unmatched joint names)``.
    """
    if angle_map is None:
        angle_map = {j: AngleSource(j) for j in joint_names if j in data.names}
        if not angle_map:
            raise TrialError(
                f"no column is named after a robot joint {list(joint_names)}; columns: "
                f"{list(data.names)[:8]} (give --angle-map)"
            )
    q = np.tile(np.asarray(rest, np.float64), (data.angles.shape[0], 1))
    for joint, src in angle_map.items():
        if joint not in joint_names:
            raise TrialError(f"angle map: {joint!r} is not a robot joint {list(joint_names)}")
        if src.column not in data.names:
            raise TrialError(f"column {src.column!r} missing (mapped to {joint})")
        q[:, joint_names.index(joint)] = (
            src.scale * data.angles[:, data.names.index(src.column)] + src.offset
        )
    unmatched = tuple(j for j in joint_names if j not in angle_map)
    return q, unmatched
