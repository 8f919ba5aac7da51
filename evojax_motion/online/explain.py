"""What a user is told about the limits of a generated motion (a numpy `generation.OnlineResult`):
why it is not usable, with the figures of the binding velocity or torque limit
(`explain_unusable`), its time scaling and margins as summary rows (`describe_limits`) and as a
trajectory file's meta (`limit_meta`).
"""

from __future__ import annotations

import numpy as np

from evojax_motion.model.robot import Robot
from evojax_motion.online.generation import OnlineResult
from evojax_motion.online.limits import VELOCITY
from evojax_motion.settings.online import OnlineSettings


def _limit_figure(robot: Robot, motion: OnlineResult, i: int, settings: OnlineSettings) -> str:
    """'joint 'elbow' needs 7.2 rad/s at t = 0.31 s into the motion; its limit is 6 rad/s (5.7
    usable with 5 % headroom)' for motion ``i`` (numpy) at its duration."""
    j, kind = int(motion.worst_joint[i]), int(motion.worst_kind[i])
    name = robot.joint_names[j]
    if kind == VELOCITY:
        what, unit, limit = "speed", "rad/s", float(robot.velocity_limit[j])
    else:
        what, unit, limit = "torque", "N m", float(robot.torque_limit[j])
    usable = (1.0 - settings.limit_headroom) * limit
    return (
        f"joint {name!r} needs {float(motion.worst_value[i]):.4g} {unit} of {what} at t = "
        f"{float(motion.worst_time[i]):.3f} s into the motion against a limit of {limit:.4g} "
        f"{unit} ({usable:.4g} usable with {settings.limit_headroom:.0%} headroom)"
    )


def explain_unusable(
    robot: Robot, motion: OnlineResult, i: int, settings: OnlineSettings, window: str = ""
) -> str:
    """Why motion ``i`` of a numpy `OnlineResult` is not usable, in one line (with the figures
    of the binding velocity or torque limit). ``window``: what bounds its duration, e.g.
    "between the reaction time and the ball's arrival" (default: `MAX_DURATION`)."""
    if bool(motion.ok[i]) or not bool(motion.reachable[i]):
        return "the motion is usable" if bool(motion.ok[i]) else "the target is not reachable"
    needed, dur = float(motion.duration_needed[i]), float(motion.duration[i])
    within = (
        motion.torque_margin[i] >= 0 and motion.velocity_margin[i] >= 0 and motion.within_time[i]
    )
    if within or not np.isfinite(motion.worst_value[i]):
        return "the generated motion is not usable (non-finite or outside the joint limits)"
    figure = _limit_figure(robot, motion, i, settings)
    if not np.isfinite(needed):
        return (
            f"no motion within the velocity and torque limits: even in {dur:.3f} s (the longest "
            f"allowed{', ' + window if window else ''}) {figure}"
        )
    return (
        f"the motion needs {needed:.3f} s to stay within the velocity and torque limits but only "
        f"{dur:.3f} s are available{' ' + window if window else ''}: in {dur:.3f} s {figure}"
    )


def describe_limits(robot: Robot, motion: OnlineResult, i: int) -> dict[str, str]:
    """Summary rows of motion ``i`` (numpy): its time scaling and its limit margins."""
    asked, dur = float(motion.duration_asked[i]), float(motion.duration[i])
    rows = {}
    if dur > asked:
        j, kind = int(motion.worst_joint[i]), int(motion.worst_kind[i])
        which = "speed" if kind == VELOCITY else "torque"
        rows["time scaling"] = (
            f"stretched from {asked:.3f} s to {dur:.3f} s ({which} limit of joint "
            f"{robot.joint_names[j]!r})"
        )
    room = float(motion.joint_margin[i])
    rows["limit margins"] = (
        f"torque {float(motion.torque_margin[i]):.3f}, speed "
        f"{float(motion.velocity_margin[i]):.3f} (1 - peak/limit), joint range "
        + (f"{room:.3f} rad" if np.isfinite(room) else "unlimited")
    )
    return rows


def limit_meta(motion: OnlineResult, i: int) -> dict:
    """The margins and the time scaling of motion ``i`` (numpy) for a trajectory file's meta."""
    room = float(motion.joint_margin[i])
    return {
        "duration_asked": float(motion.duration_asked[i]),
        "time_scaled": bool(float(motion.duration[i]) > float(motion.duration_asked[i])),
        "torque_margin": float(motion.torque_margin[i]),
        "velocity_margin": float(motion.velocity_margin[i]),
        "joint_limit_margin": room if np.isfinite(room) else None,
    }
