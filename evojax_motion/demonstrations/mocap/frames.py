"""Body frames that move with the person: x forward, y left, z up (the robot's world convention).

A frame's origin is the shoulder (or another reference point) in every frame; its heading is that
of the trunk (`heading_direction`: two trunk markers, else the right-left shoulder line), turned
about the vertical (`body_frames`). A person who steps, walks or turns keeps the same arm motion
in it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from evojax_motion.demonstrations.mocap.markers import (
    KEYPOINT_CHAIN,
    LEFT_SHOULDER,
    MarkerData,
    MarkerModel,
    TrialError,
)

MIN_HEADING = 1e-3  # [m] a horizontal heading vector shorter than this tells no direction


def body_frame(
    points: Mapping[str, np.ndarray], up: np.ndarray, forward: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Trunk frame of a trial's first frame: ``(origin (3,), rot (3, 3))``; ``rot @ (p - origin)``
    gives coordinates x forward, y left, z up. Origin: the shoulder (or first key point)."""
    first = next(k for k in KEYPOINT_CHAIN if k in points)
    origin = points[first][0]
    up = up / np.linalg.norm(up)
    if forward is None:
        right = points[first][0] - points[LEFT_SHOULDER][0]
    else:
        right = np.cross(forward, up)
    right = right - up * (right @ up)
    norm = np.linalg.norm(right)
    if not math.isfinite(norm) or norm < 1e-6:
        raise TrialError(
            f"cannot tell left from right: the shoulder line's horizontal part is "
            f"{1e3 * norm:.2f} mm in the first frame"
        )
    right /= norm
    fwd = np.cross(up, right)
    left = -right
    return origin, np.stack([fwd, left, up])


class Heading(NamedTuple):
    """What turns a trial's body frame (`heading_direction`).

    direction: (F, 3) a vector that turns with the trunk, or None (the frame does not turn).
    centre: (F, 3) the mean of the trunk markers it comes from, or None (from the shoulders).
    source: in words, for the report.
    """

    direction: np.ndarray | None
    centre: np.ndarray | None
    source: str


def heading_direction(
    data: MarkerData, points: Mapping[str, np.ndarray], model: MarkerModel
) -> Heading:
    """The trunk's heading: the model's `MarkerModel.heading` markers when the trial has them in
    every frame (gap-filled as the key points' markers are); else the shoulder line (shoulder -
    left shoulder) when the model has a left shoulder; else none (the recording's ``forward``
    axis, fixed).
    """
    if model.heading is not None:
        names = [*model.heading[0], *model.heading[1]]
        if all(n in data.names for n in names):
            a = np.mean([data.get(n) for n in model.heading[0]], axis=0)
            b = np.mean([data.get(n) for n in model.heading[1]], axis=0)
            if np.isfinite(b - a).all():
                centre = np.mean([data.get(n) for n in names], axis=0)
                source = f"markers {'+'.join(model.heading[0])} -> {'+'.join(model.heading[1])}"
                return Heading(b - a, centre, source)
    if model.forward is None and LEFT_SHOULDER in points:
        first = next(k for k in KEYPOINT_CHAIN if k in points)
        return Heading(points[first] - points[LEFT_SHOULDER], None, "shoulder line")
    return Heading(None, None, "fixed")


def heading_turn(direction: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``(F,)`` [rad] how far ``direction (F, 3)`` has turned about ``up`` since frame 0
    (counter-clockwise seen from above positive), unwrapped. Its tilt out of the horizontal does
    not count. Raises `TrialError` when it points (nearly) straight up in some frame."""
    up = up / np.linalg.norm(up)
    flat = direction - np.outer(direction @ up, up)
    norm = np.linalg.norm(flat, axis=-1)
    if not (norm > MIN_HEADING).all():
        frame = int(np.argmin(np.where(np.isfinite(norm), norm, -1.0)))
        raise TrialError(
            f"cannot tell the trunk's heading at frame {frame}: its horizontal part is "
            f"{1e3 * norm[frame]:.1f} mm < {1e3 * MIN_HEADING:.0f} mm"
        )
    d0 = flat[0]
    sin = np.cross(d0, flat) @ up
    cos = flat @ d0
    return np.unwrap(np.arctan2(sin, cos))


def body_frames(
    points: Mapping[str, np.ndarray],
    up: np.ndarray,
    forward: np.ndarray | None,
    origin: np.ndarray | None = None,
    heading: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Body frames of every frame of a trial: ``(origin (F, 3), rot (F, 3, 3))``; ``rot[t] @
    (p[t] - origin[t])`` gives coordinates x forward, y left, z up that move with the person.

    Frame 0 is `body_frame`; frame ``t`` is it turned about ``up`` by `heading_turn` of
    ``heading (F, 3)`` (None: not turned). origin: ``(F, 3)`` the reference point in every frame
    (None: frame 0's shoulder in every frame, a frame fixed in the lab).
    """
    o0, rot0 = body_frame(points, up, forward)
    first = next(iter(points.values()))
    n = first.shape[0]
    origin = np.broadcast_to(o0, (n, 3)) if origin is None else np.asarray(origin)
    if heading is None:
        return origin, np.broadcast_to(rot0, (n, 3, 3))
    turn = heading_turn(heading, up)
    u = up / np.linalg.norm(up)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    s, c = np.sin(turn)[:, None, None], np.cos(turn)[:, None, None]
    turned = np.eye(3) + s * k + (1.0 - c) * (k @ k)  # (F, 3, 3) Rodrigues: turn about up
    return origin, rot0 @ np.swapaxes(turned, -1, -2)
