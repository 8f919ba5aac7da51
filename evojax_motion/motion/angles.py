"""Joint angles of continuous joints kept on one 2 pi branch (DESIGN, conventions).

A continuous hinge (no range) reaches the same pose at ``q`` and ``q + 2 pi k``. Averages,
distances and interpolations over joint angles are meaningful only when every trajectory of a
database lies on one branch: each trajectory is unwrapped along time (no jump of more than pi
between samples) and then shifted by a whole number of turns so that its mean lies within pi of
the robot's rest posture. Joints that are not continuous are returned unchanged.
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_difference(delta: np.ndarray, continuous: np.ndarray) -> np.ndarray:
    """Joint-angle differences with continuous joints wrapped into [-pi, pi).

    delta: (..., J) differences of joint values; continuous: (J,) bool.
    """
    delta = np.asarray(delta)
    wrapped = (delta + np.pi) % TWO_PI - np.pi
    return np.where(np.asarray(continuous, bool), wrapped, delta)


def on_rest_branch(q: np.ndarray, rest: np.ndarray, continuous: np.ndarray) -> np.ndarray:
    """Trajectories unwrapped along time and shifted to the branch nearest ``rest``.

    q: (..., T, J) joint trajectories; rest: (J,); continuous: (J,) bool. Returns (..., T, J), the
    same poses: continuous joints differ from ``q`` by whole turns only, and the mean over T of each
    of them lies in [rest - pi, rest + pi).
    """
    q = np.asarray(q)
    cont = np.asarray(continuous, bool)
    if not cont.any():
        return q
    unwrapped = np.unwrap(q, axis=-2)
    mean = unwrapped.mean(axis=-2, keepdims=True)
    turns = np.floor((mean - rest + np.pi) / TWO_PI)
    shifted = unwrapped - TWO_PI * turns
    return np.where(cont, shifted, q).astype(q.dtype, copy=False)


def posture_on_rest_branch(q: np.ndarray, rest: np.ndarray, continuous: np.ndarray) -> np.ndarray:
    """Postures (..., J) with continuous joints moved by whole turns to within pi of ``rest``."""
    q = np.asarray(q)
    return (rest + wrap_difference(q - rest, continuous)).astype(q.dtype, copy=False)
