"""``evojax-motion robot MODEL``: what the project reads from a robot model, and a config for it.

The first step of bringing your own arm (docs/robot_models.md): load an MJCF file as training
will (`model.robot.load_robot`) and print the files read, the controlled joints with their ranges
(continuous ones marked), torque limits and where they come from, velocity limits, the end
effector, the rest posture and where it comes from, the reach and the default region of the
synthetic demonstrations (`demonstrations.workspace`), and a YAML ``robot:`` section to start a
config from.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np

from evojax_motion.errors import UserError


def add_robot_parser(subparsers) -> None:
    """Add ``robot`` to the ``evojax-motion`` subcommands (``cli.entry.build_parser``)."""
    p = subparsers.add_parser(
        "robot",
        help="what is read from a robot model (joints, limits, end effector, rest), and a "
        "config section for it",
        description="Load an MJCF model as training does and print the files read, the "
        "controlled joints with their ranges, torque and velocity limits (and where they come "
        "from), the end effector, the rest posture, and a YAML robot: section for a config.",
    )
    p.add_argument("model", metavar="MODEL", help="MJCF file (or a shipped robot's name)")
    p.add_argument(
        "--joints",
        nargs="+",
        default=None,
        metavar="JOINT",
        help="controlled joints, in order (default: the hinge and slide joints from the root "
        "to the end effector)",
    )
    p.add_argument(
        "--end-effector",
        default=None,
        metavar="NAME",
        help="end-effector site or body (default: the model's only site)",
    )
    p.add_argument(
        "--end-effector-offset",
        nargs=3,
        type=float,
        default=None,
        metavar=("X", "Y", "Z"),
        help="[m] offset of the end effector in its site's or body's frame",
    )
    p.set_defaults(func=run_robot)


def run_robot(args: argparse.Namespace) -> int:
    """The ``robot`` subcommand: print `describe_robot` of the loaded model."""
    from evojax_motion.model.robot import load_robot

    joints = None
    if args.joints is not None:  # "a b", "a,b" and "a, b" all name two joints
        joints = [n for arg in args.joints for n in arg.replace(",", " ").split()]
        if not joints:
            raise UserError("--joints: expected joint names")
    offset = args.end_effector_offset
    if offset is not None and not all(math.isfinite(x) for x in offset):
        raise UserError(f"--end-effector-offset: expected 3 finite numbers [m], got {offset}")
    robot = load_robot(
        args.model, joints=joints, end_effector=args.end_effector, end_effector_offset=offset
    )
    print(describe_robot(robot, args.model, joints, args.end_effector, offset))
    return 0


def _number(x: float) -> str:
    return "none" if not math.isfinite(x) else f"{x:.6g}"


def _table(rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def _workspace_lines(robot) -> list[str]:
    """The reach (`demonstrations.workspace.sample_workspace` within the limits less the demos'
    default margin) and the default region of ``demos`` (a shipped robot's preset, else derived:
    `derive_region`); an empty workspace is said, not raised, so the rest of the report stays."""
    from evojax_motion.demonstrations.workspace import (
        ROBOT_PRESETS,
        WORKSPACE_SAMPLES,
        derive_region,
        sample_workspace,
        workspace_shoulder,
    )
    from evojax_motion.settings.demonstrations import DemoSettings

    margin = DemoSettings().limit_margin_deg
    workspace = sample_workspace(robot, math.radians(margin))
    shoulder, centre, reach = workspace_shoulder(workspace)
    at = np.array2string(centre, precision=4, separator=", ")
    lines = [
        f"reach: {reach:.3f} m from body {workspace.chain[shoulder]!r} at {at} m (the deepest "
        f"body that stays put; the end effector over {WORKSPACE_SAMPLES} postures within the "
        f"limits less {margin:g} deg)"
    ]
    if robot.name in ROBOT_PRESETS:
        region, source = ROBOT_PRESETS[robot.name].region, "the shipped robot's preset"
    else:
        try:
            region, source = derive_region(robot, workspace), "derived from the reach"
        except UserError as e:
            return [*lines, f"demos region: none: {e}"]
    lines.append(
        f"demos region ({source}): about body {region.frame!r}, radius {region.radius[0]:g} .. "
        f"{region.radius[1]:g} m, azimuth {region.azimuth_deg[0]:g} .. {region.azimuth_deg[1]:g} "
        f"deg, elevation {region.elevation_deg[0]:g} .. {region.elevation_deg[1]:g} deg"
    )
    return lines


OTHER_JOINTS_SHOWN = 8  # uncontrolled joints named by `_other_joints_lines`, then a count


def _other_joints_lines(robot) -> list[str]:
    """A line naming the model's joints that are not controlled (held at ``qpos0``, at rest, in
    every motion and its dynamics), with a note where one is a free joint; none if there are
    none."""
    import mujoco

    m = robot.mj_model
    kinds = {
        int(v): v.name.removeprefix("mjJNT_").lower() for v in mujoco.mjtJoint.__members__.values()
    }
    controlled = {int(j) for j in robot.joint_ids}
    others = [j for j in range(m.njnt) if j not in controlled]
    if not others:
        return []

    def named(j: int) -> str:
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
        return f"{name} ({kinds[int(m.jnt_type[j])]})"

    names = [named(j) for j in others]
    shown = ", ".join(names[:OTHER_JOINTS_SHOWN])
    more = f", ... ({len(names)} in all)" if len(names) > OTHER_JOINTS_SHOWN else ""
    lines = [f"other joints, held at the model's qpos0 in every motion: {shown}{more}"]
    if any(int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE) for j in others):
        lines.append(
            "  (a free joint among them: the chain's base is held fixed, as a bolted arm's)"
        )
    return lines


def describe_robot(
    robot,
    model: str,
    joints: list[str] | None = None,
    end_effector: str | None = None,
    offset=None,
) -> str:
    """The ``robot`` subcommand's report of ``robot`` (loaded from ``model`` with ``joints``,
    ``end_effector`` and ``offset`` as given, None where left to the defaults)."""
    import mujoco
    import yaml

    from evojax_motion.model.robot import SHIPPED_ROBOTS

    m = robot.mj_model
    lines = []
    files = [Path(f) for f in robot.files]
    if files:
        base = files[0].parent
        shown = [os.path.relpath(f, base) for f in files]
        lines.append(f"files read ({len(files)}, in {base}): {', '.join(shown)}")
    size = len(robot.mjcf.encode("utf-8")) / 1e3
    how = "the file's text" if len(files) <= 1 else "one expanded text, meshes included"
    amount = f"{size:.3g} kB" if size < 1e3 else f"{size / 1e3:.3g} MB"
    lines.append(f"stored with databases and runs: {how} ({amount} of MJCF)")

    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    rows = [["joint", "type", "range", "torque limit", "torque limit from", "velocity limit"]]
    for k, name in enumerate(robot.joint_names):
        is_hinge = int(m.jnt_type[robot.joint_ids[k]]) == hinge
        unit, force, speed = ("rad", "N m", "rad/s") if is_hinge else ("m", "N", "m/s")
        if robot.continuous[k]:
            span = "continuous" if is_hinge else "unlimited"
        else:
            span = f"{robot.lower[k]:.6g} .. {robot.upper[k]:.6g} {unit}"
        tau, vel = robot.torque_limit[k], robot.velocity_limit[k]
        rows.append(
            [
                name,
                "hinge" if is_hinge else "slide",
                span,
                _number(tau) + (f" {force}" if math.isfinite(tau) else ""),
                robot.torque_limit_source[k],
                _number(vel) + (f" {speed}" if math.isfinite(vel) else ""),
            ]
        )
    chosen = "as given" if joints is not None else "those from the root to the end effector"
    lines.append(f"joints ({robot.n_joints}, {chosen}):")
    lines += _table(rows)
    lines += _other_joints_lines(robot)

    body = int(m.site_bodyid[robot.site_id])
    body_name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body) or f"#{body}"
    d = mujoco.MjData(m)
    d.qpos[robot.qpos_adr] = robot.rest
    mujoco.mj_kinematics(m, d)
    at = np.array2string(d.site_xpos[robot.site_id], precision=4, separator=", ")
    if end_effector is None or end_effector == robot.site_name:
        what = f"site {robot.site_name!r} on body {body_name!r}"
    else:
        what = f"{end_effector!r} (site {robot.site_name!r} added to body {body_name!r})"
    if offset is not None:
        what += f", offset {list(offset)} m"
    lines.append(f"end effector: {what}; at the rest posture {at} m (world)")
    rest = np.array2string(robot.rest, precision=4, separator=", ")
    lines.append(f"rest posture: {robot.rest_source}: {rest}")
    lines += _workspace_lines(robot)

    section: dict = {}
    if model in SHIPPED_ROBOTS:
        section["name"] = model
    else:
        section["mjcf"] = model
    section["joints"] = list(robot.joint_names)
    section["end_effector"] = end_effector if end_effector is not None else robot.site_name
    if offset is not None:
        section["end_effector_offset"] = [float(x) for x in offset]
    text = yaml.safe_dump({"robot": section}, sort_keys=False, default_flow_style=None)
    lines += ["", "# a config's robot section (evojax-motion train CONFIG):", text.rstrip()]
    unknown = [n for n, v in zip(robot.joint_names, robot.velocity_limit) if not math.isfinite(v)]
    if unknown:
        example = ", ".join(f"{n}: 2.0" for n in unknown[:2])
        lines.append(
            f"  # velocity_limits: {{{example}}}   # [rad/s], from the datasheet; the model "
            f"gives none for {len(unknown)} joint(s)"
        )
    return "\n".join(lines)
