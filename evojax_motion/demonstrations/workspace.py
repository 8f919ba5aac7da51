"""Robot-specific defaults of the synthetic demonstrations (`demonstrations.synthetic`).

The catch region and the preferred posture depend on the robot: the shipped robots have presets
(`ROBOT_PRESETS`); for any other arm they are derived from its model (`derive_defaults`): the
catch region from the reachable workspace (`sample_workspace`, `derive_region`), the comfortable
posture and its per-trial noise from the joint ranges (`derive_comfort`, `derive_posture_std`).
`resolve_settings` fills the robot-specific fields of a `DemoSettings` left unset and checks them
against the robot.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import mujoco
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.model.robot import Robot
from evojax_motion.settings.demonstrations import CatchRegion, DemoSettings

LIMIT_TOUCH_TOL = 1e-4  # [rad] a joint this close to the shrunk limits was clamped by the IK


class RobotPreset(NamedTuple):
    """Per-robot defaults of the robot-specific `DemoSettings` fields (used where they are None)."""

    region: CatchRegion
    comfort_deg: dict  # joint name -> preferred final angle [deg]; other joints: rest
    posture_std_deg: dict  # joint name -> std of the per-trial preference noise [deg]
    posture_weight: dict  # joint name -> null-space weight of the preference (IK ``w_pref``)


ROBOT_PRESETS: dict[str, RobotPreset] = {
    # Shoulder joint centre at (0, -0.19, 1.40), hand reach ~0.61 m. The sector (52-85 % of the
    # reach, in front of and a little across the right shoulder) spans about the box that
    # docs/robot_models.md verifies as reachable with margins (x 0.2-0.5, y -0.5-0.1, z 1.1-1.7 m).
    "mahru_arm": RobotPreset(
        region=CatchRegion("upper_arm", (0.32, 0.52), (-45.0, 15.0), (-30.0, 30.0)),
        comfort_deg={
            "shoulder_pitch": 45.0,
            "shoulder_roll": 10.0,
            "shoulder_yaw": 10.0,
            "elbow": 60.0,
        },
        posture_std_deg={
            "waist_yaw": 3.0,
            "shoulder_pitch": 5.0,
            "shoulder_roll": 8.0,
            "shoulder_yaw": 12.0,
            "elbow": 5.0,
            "wrist_pitch": 5.0,
            "wrist_yaw": 3.0,
        },
        # Within reach, people recruit the trunk little (Kaminski, Bock & Gentile 1995): the
        # waist is held toward its preference 4 times as hard as the arm joints.
        posture_weight={"waist_yaw": 1.0},
    ),
    # Shoulder (upper_link origin) at (0.05, 0, 0.78), reach ~0.91 m; its slow joints stretch
    # most durations beyond Fitts' law (max_speed_fraction).
    "arm6": RobotPreset(
        region=CatchRegion("upper_link", (0.40, 0.70), (-40.0, 40.0), (-30.0, 20.0)),
        comfort_deg={},
        posture_std_deg={},
        posture_weight={},
    ),
}
DEFAULT_POSTURE_STD_DEG = 5.0  # for joints a preset does not name
DEFAULT_POSTURE_WEIGHT = 0.25

# Defaults for a robot without a preset, derived from its model (`derive_region`,
# `derive_comfort`, `derive_posture_std`).
WORKSPACE_SAMPLES = 4096  # postures drawn within the joint limits for the reachable workspace
WORKSPACE_SEED = 0  # their draw: the derived region is a property of the robot, not of demos.seed
SHOULDER_SPREAD = 0.1  # the shoulder: the deepest body that moves less than this x hand extent
REGION_RADIUS_FRACTION = (0.5, 0.75)  # catch radii as fractions of the reach from the shoulder
REGION_AZIMUTH_HALF_DEG = 40.0  # the sector spans +-this about the front
REGION_ELEVATION_DEG = (-20.0, 30.0)
FRONT_MIN_FRACTION = 0.1  # a rest hand this far (x reach) out horizontally defines the front
COMFORT_CENTRAL_FRACTION = 0.5  # the comfortable posture lies in this central part of a range
POSTURE_STD_FRACTION = 0.04  # per-trial preference noise: this fraction of a joint's range...
POSTURE_STD_MAX_DEG = 8.0  # ...at most this; a continuous joint gets the most
MIN_WORKSPACE_EXTENT = 1e-3  # [m] an end effector that moves less has an empty workspace


class Resolved(NamedTuple):
    """Robot-specific settings resolved against the robot (numpy, float64)."""

    region: CatchRegion
    centre: np.ndarray  # (3,) region centre [m]
    comfort: np.ndarray  # (J,) preferred final posture [rad]
    posture_std: np.ndarray  # (J,) [rad]
    posture_weight: np.ndarray  # (J,) IK w_pref
    source: str  # where the robot-specific defaults came from (a preset, or derived)


class Workspace(NamedTuple):
    """The end effector's reachable workspace, sampled (`sample_workspace`); n postures."""

    hand: np.ndarray  # (n, 3) end-effector site positions [m]
    chain: tuple[str, ...]  # named bodies from the world to the site's body, world first
    body_pos: np.ndarray  # (n, len(chain), 3) their origins [m]
    rest_hand: np.ndarray  # (3,) the site at the rest posture [m]
    rest_body: np.ndarray  # (len(chain), 3) the bodies' origins at the rest posture [m]

    @property
    def extent(self) -> float:
        """[m] the farthest sampled hand position from their mean."""
        return float(np.linalg.norm(self.hand - self.hand.mean(axis=0), axis=1).max())


def sample_workspace(
    robot: Robot, margin: float = 0.0, n: int = WORKSPACE_SAMPLES, seed: int = WORKSPACE_SEED
) -> Workspace:
    """Forward kinematics (C MuJoCo, float64) of ``n`` postures drawn uniformly within the joint
    limits shrunk by ``margin`` [rad] (`Robot.sample_postures`: continuous joints one turn about
    rest; other joints of the model at ``qpos0``), from a fixed ``seed``."""
    m = robot.mj_model
    chain, b = [], int(m.site_bodyid[robot.site_id])
    while True:
        if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b):
            chain.append(b)
        if b == 0:
            break
        b = int(m.body_parentid[b])
    chain.reverse()
    postures = robot.sample_postures(np.random.default_rng(seed), n, margin)
    data = mujoco.MjData(m)

    def fk(q):
        data.qpos[:] = m.qpos0
        data.qpos[robot.qpos_adr] = q
        mujoco.mj_kinematics(m, data)
        return data.site_xpos[robot.site_id].copy(), data.xpos[chain].copy()

    hand, body = np.empty((n, 3)), np.empty((n, len(chain), 3))
    for i, q in enumerate(postures):
        hand[i], body[i] = fk(q)
    rest_hand, rest_body = fk(robot.rest)
    names = tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, c) for c in chain)
    return Workspace(hand, names, body, rest_hand, rest_body)


def workspace_shoulder(workspace: Workspace) -> tuple[int, np.ndarray, float]:
    """``(index, centre, reach)``: the shoulder, the deepest body of ``workspace.chain`` that
    moves less than `SHOULDER_SPREAD` x the hand's extent (the world when none does), its origin
    at the rest posture (3,) [m], and the reach [m], the farthest sampled hand position from it."""
    spread = np.linalg.norm(workspace.body_pos - workspace.rest_body, axis=-1).max(axis=0)
    shoulder = int(np.flatnonzero(spread <= SHOULDER_SPREAD * workspace.extent)[-1])
    centre = workspace.rest_body[shoulder]
    return shoulder, centre, float(np.linalg.norm(workspace.hand - centre, axis=1).max())


def derive_region(robot: Robot, workspace: Workspace) -> CatchRegion:
    """The catch region of a robot without a preset, from its sampled workspace (`DemoSettings`
    ``region`` says how). Raises `UserError` when the end effector does not move."""
    extent = workspace.extent
    if not extent > MIN_WORKSPACE_EXTENT:
        raise UserError(
            f"robot {robot.name!r}: the end effector {robot.site_name!r} stays within "
            f"{extent:.2g} m over {len(workspace.hand)} postures drawn within the joint limits: "
            "an empty workspace; expected joints that move it (robot.joints, robot.end_effector)"
        )
    shoulder, centre, reach = workspace_shoulder(workspace)
    ahead = workspace.rest_hand[:2] - centre[:2]
    front = 0.0
    if np.linalg.norm(ahead) >= FRONT_MIN_FRACTION * reach:
        front = round(math.degrees(math.atan2(ahead[1], ahead[0])), 1)
    return CatchRegion(
        frame=workspace.chain[shoulder],
        radius=tuple(round(f * reach, 3) for f in REGION_RADIUS_FRACTION),
        azimuth_deg=(front - REGION_AZIMUTH_HALF_DEG, front + REGION_AZIMUTH_HALF_DEG),
        elevation_deg=REGION_ELEVATION_DEG,
    )


def derive_comfort(robot: Robot) -> np.ndarray:
    """``(J,)`` [rad] the comfortable final posture of a robot without a preset: the rest
    posture moved into the central `COMFORT_CENTRAL_FRACTION` of each joint's range (away from
    the limits, Liegeois 1977); a continuous joint at rest."""
    lower = np.where(robot.continuous, robot.rest, robot.lower)  # finite: no inf - inf
    upper = np.where(robot.continuous, robot.rest, robot.upper)
    cut = 0.5 * (1.0 - COMFORT_CENTRAL_FRACTION) * (upper - lower)
    return np.clip(robot.rest, lower + cut, upper - cut)


def derive_posture_std(robot: Robot) -> np.ndarray:
    """``(J,)`` [rad] per-trial preference noise of a robot without a preset: a fraction
    `POSTURE_STD_FRACTION` of each joint's range, at most `POSTURE_STD_MAX_DEG`."""
    span = np.where(robot.continuous, np.inf, robot.upper - robot.lower)
    return np.minimum(POSTURE_STD_FRACTION * span, math.radians(POSTURE_STD_MAX_DEG))


def derive_defaults(robot: Robot, limit_margin_deg: float = 2.0) -> RobotPreset:
    """The robot-specific defaults of a robot without a preset, as a `RobotPreset` (angles in
    degrees; `derive_region` on the workspace within the limits shrunk by ``limit_margin_deg``,
    `derive_comfort`, `derive_posture_std`, `DEFAULT_POSTURE_WEIGHT`)."""
    names = robot.joint_names
    workspace = sample_workspace(robot, math.radians(limit_margin_deg))
    return RobotPreset(
        region=derive_region(robot, workspace),
        comfort_deg=dict(zip(names, np.rad2deg(derive_comfort(robot)).tolist())),
        posture_std_deg=dict(zip(names, np.rad2deg(derive_posture_std(robot)).tolist())),
        posture_weight={},
    )


def resolve_settings(robot: Robot, settings: DemoSettings) -> Resolved:
    """Fill the robot-specific settings from the robot's preset, or derive them from the robot
    (`derive_defaults`), and check them against it."""
    _check_rest(robot, settings)  # first: a range narrower than the margin fails here
    names = list(robot.joint_names)
    preset = ROBOT_PRESETS.get(robot.name)
    derived: list[RobotPreset] = []

    def default(field):
        if preset is not None:
            return getattr(preset, field)
        if not derived:
            derived.append(derive_defaults(robot, settings.limit_margin_deg))
        return getattr(derived[0], field)

    def per_joint(field, fallback):  # one value or one per joint in settings; a dict in presets
        value = getattr(settings, field)
        if value is None:
            table = default(field)
            return np.array([table.get(n, fallback) for n in names], np.float64)
        if len(value) not in (1, len(names)):
            raise UserError(
                f"demos.{field}: expected 1 or {len(names)} values (one per joint), got "
                f"{len(value)}"
            )
        return np.broadcast_to(np.asarray(value, np.float64), (len(names),)).copy()

    region = settings.region if settings.region is not None else default("region")
    m = robot.mj_model
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, region.frame)
    if body < 0:
        bodies = [m.body(i).name for i in range(m.nbody)]
        raise UserError(
            f"demos.region.frame: no body named {region.frame!r} in robot {robot.name!r}; "
            f"bodies: {bodies}"
        )
    data = mujoco.MjData(m)
    data.qpos[robot.qpos_adr] = robot.rest
    mujoco.mj_kinematics(m, data)

    if settings.comfort_joints is None:
        comfort_deg = default("comfort_deg")
    else:
        comfort_deg = dict(zip(settings.comfort_joints, settings.comfort_deg or ()))
    comfort = np.array(robot.rest, np.float64)
    for name, deg in comfort_deg.items():
        if name not in names:
            raise UserError(f"demos.comfort_joints: no controlled joint {name!r}; joints: {names}")
        k = names.index(name)
        comfort[k] = np.deg2rad(deg)
        if not robot.lower[k] <= comfort[k] <= robot.upper[k]:
            raise UserError(
                f"demos.comfort_deg: joint {name!r} at {deg:g} deg is outside its limits "
                f"[{math.degrees(robot.lower[k]):.4g}, {math.degrees(robot.upper[k]):.4g}] deg"
            )
    posture_std = np.deg2rad(per_joint("posture_std_deg", DEFAULT_POSTURE_STD_DEG))
    posture_weight = per_joint("posture_weight", DEFAULT_POSTURE_WEIGHT)
    if preset is not None:
        source = f"the preset of {robot.name!r}"
    else:
        source = "derived from the robot" if derived else "the settings"
    return Resolved(region, data.xpos[body].copy(), comfort, posture_std, posture_weight, source)


def _check_rest(robot: Robot, settings: DemoSettings) -> None:
    """Every demonstration starts at rest: a rest posture within ``limit_margin_deg`` of a limit
    would fail every trial's limit check. Raises `UserError` naming the joint."""
    margin = np.minimum(robot.rest - robot.lower, robot.upper - robot.rest)
    need = math.radians(settings.limit_margin_deg) + LIMIT_TOUCH_TOL
    if np.any(margin <= need):
        k = int(np.argmin(margin - need))
        raise UserError(
            f"demos.limit_margin_deg: the rest posture ({robot.rest_source}) has joint "
            f"{robot.joint_names[k]!r} at {robot.rest[k]:.4g} rad, {math.degrees(margin[k]):.3g} "
            f"deg from its limit, within the {settings.limit_margin_deg:g} deg every "
            "demonstration keeps (they start at rest); expected a smaller demos.limit_margin_deg "
            "or a rest keyframe inside the limits"
        )
