"""Settings of the demonstrations stage: `DemoSettings` (the config's ``demos`` section) with its
`CatchRegion`, and `IKSettings` of the motion-capture import's key-point IK.

The models these settings drive are described in `demonstrations.synthetic` (synthetic
catching demonstrations) and `demonstrations.mocap.retarget` (retargeting by key-point IK).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from evojax_motion.errors import UserError, check_setting

MAX_ASYMMETRY = 0.5  # |a| of the time warp; |a| < 1 keeps it monotone


@dataclass(frozen=True)
class CatchRegion:
    """Where the catch points lie: a spherical-shell sector around a body of the robot.

    frame: body whose origin, at the rest posture, is the centre (e.g. the shoulder); axes are the
      world axes (x forward, y left, z up for the shipped robots).
    radius: (min, max) distance from the centre [m].
    azimuth_deg: (min, max) angle about +z from +x [deg]; positive toward +y (left); within
      [-360, 360] and at most one turn wide (a sector may cross +-180).
    elevation_deg: (min, max) angle above the horizontal plane [deg].
    """

    frame: str = "upper_arm"
    radius: tuple[float, ...] = (0.32, 0.52)
    azimuth_deg: tuple[float, ...] = (-45.0, 15.0)
    elevation_deg: tuple[float, ...] = (-30.0, 30.0)

    def __post_init__(self):
        _check_range("radius", self.radius, 0.0, math.inf, open_low=True)
        _check_range("azimuth_deg", self.azimuth_deg, -360.0, 360.0, max_width=360.0)
        _check_range("elevation_deg", self.elevation_deg, -90.0, 90.0)
        check_setting(
            isinstance(self.frame, str) and bool(self.frame), "frame", "a body name", self.frame
        )


def _check_range(name, value, lo, hi, open_low=False, max_width=math.inf):
    ok = (
        isinstance(value, tuple)
        and len(value) == 2
        and all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)
        and (value[0] > lo if open_low else value[0] >= lo)
        and value[0] < value[1] <= hi
        and value[1] - value[0] <= max_width
    )
    width = f" and max - min <= {max_width:g}" if math.isfinite(max_width) else ""
    expected = f"[min, max] with {lo:g} {'<' if open_low else '<='} min < max <= {hi:g}{width}"
    check_setting(ok, name, expected, value)


# Numeric fields of DemoSettings: (lowest, highest) allowed, both inclusive.
_NUMBER_RANGES = {
    "fitts_a": (1e-3, 10.0),
    "fitts_b": (1e-3, 10.0),
    "target_width": (1e-3, 10.0),
    "duration_noise": (0.0, 0.5),
    "asymmetry_mean": (-MAX_ASYMMETRY, MAX_ASYMMETRY),
    "asymmetry_std": (0.0, 0.2),
    "curvature_std": (0.0, 0.1),
    "arc_blend": (0.0, 1.0),
    "max_speed_fraction": (0.05, 1.0),
    "limit_margin_deg": (0.0, 20.0),
    "catch_tolerance": (1e-6, 0.1),
    "oversample": (1.0, 100.0),
}
_INT_MINIMA = {"count": 1, "samples": 8, "ik_iters": 1, "max_rounds": 1}


@dataclass(frozen=True)
class DemoSettings:
    """How the synthetic demonstrations are drawn (the config's ``demos`` section; the models in
    the docstring of `demonstrations.synthetic`). Every key has a default that works for any arm:
    the four robot-specific ones (``region``, ``comfort_joints``/``comfort_deg``,
    ``posture_std_deg``, ``posture_weight``) come from the robot's preset for the shipped robots
    (`ROBOT_PRESETS`: mahru_arm, arm6) and are derived from the model for any other
    (`derive_defaults`). The presets, the ``derive_*`` functions and the upper-case constants
    named below are in `demonstrations.workspace`.

    - ``count``: demonstrations in the database (default 311, the paper's sec. 4.1).
    - ``samples``: T, samples per trajectory on normalised time (default 100).
    - ``seed``: the PRNG key the CLI builds (``generate_demonstrations`` takes the key itself;
      default 0). Same key, same settings -> bit-identical database.
    - ``region``: where the catch points lie, a `CatchRegion` ``{frame, radius [m],
      azimuth_deg, elevation_deg}``: a spherical-shell sector around the origin of body
      ``frame`` at the rest posture, world axes. Default (null): the preset's; else derived
      from the reachable workspace (`derive_region`): the hand over `WORKSPACE_SAMPLES`
      postures drawn uniformly within the joint limits (continuous joints: one turn about
      rest); ``frame`` = the shoulder, the deepest body of the arm's chain that moves less than
      `SHOULDER_SPREAD` of the hand's extent; ``radius`` = `REGION_RADIUS_FRACTION` (0.5-0.75)
      of the largest sampled distance of the hand from it (comfortable reach, away from the
      base); ``azimuth_deg`` = +-`REGION_AZIMUTH_HALF_DEG` (40) about the front (the rest
      hand's horizontal direction from the shoulder, else +x); ``elevation_deg`` =
      `REGION_ELEVATION_DEG` (-20..30).
    - ``fitts_a`` [s], ``fitts_b`` [s/bit], ``target_width`` [m]: Fitts' law ``D = a + b
      log2(2 d / W)`` for a hand travel d (defaults 0.25 s, 0.10 s/bit, 0.08 m).
    - ``duration_noise``: std of log(D) around Fitts' law (default 0.08).
    - ``asymmetry_mean``, ``asymmetry_std``: time-warp parameter a, speed peak earlier for
      a > 0 (defaults 0.10, 0.05).
    - ``curvature_std``: std of the random bend's largest deviation, a fraction of the path
      length (default 0.03).
    - ``arc_blend``: hand path = (1 - arc_blend) straight line + arc_blend shoulder-centred arc
      (default 0.8).
    - ``max_speed_fraction``: durations are stretched where a joint would exceed this fraction
      of its velocity limit (default 0.9; joints without a limit never stretch).
    - ``comfort_joints``, ``comfort_deg``: preferred final angles [deg] of the named joints, the
      other joints at rest (set both or neither). Default (null): the preset's; else derived
      (`derive_comfort`): the rest posture moved into the central half
      (`COMFORT_CENTRAL_FRACTION`) of each joint's range; continuous joints at rest.
    - ``posture_std_deg``: std [deg] of the per-trial Gaussian noise on the preferred final
      posture, one value for all joints or one per joint. Default (null): the preset's (5 deg
      for joints it does not name); else derived (`derive_posture_std`):
      `POSTURE_STD_FRACTION` (4 %) of each joint's range, at most `POSTURE_STD_MAX_DEG` (8 deg;
      a continuous joint gets 8).
    - ``posture_weight``: null-space weights in (0, 1] of the preference (IK ``w_pref``), one
      value or one per joint; a heavier joint stays nearer its preferred angle. Default (null):
      the preset's; else `DEFAULT_POSTURE_WEIGHT` (0.25) for every joint.
    - ``limit_margin_deg`` [deg]: the IK keeps every joint this far inside its limits; a trial
      that comes closer is rejected (default 2). The rest posture must keep it too.
    - ``catch_tolerance`` [m]: largest hand error along the path and at the catch point
      (default 0.005).
    - ``ik_iters``: IK iterations per path node (default 8).
    - ``oversample``: candidates per round / count (default 1.2).
    - ``max_rounds``: candidate rounds before giving up (default 8); the error then counts the
      candidates by cause (limits, misses with figures, catch points beyond the sampled reach).
    """

    count: int = 311
    samples: int = 100
    seed: int = 0
    region: CatchRegion | None = None
    fitts_a: float = 0.25
    fitts_b: float = 0.10
    target_width: float = 0.08
    duration_noise: float = 0.08
    asymmetry_mean: float = 0.10
    asymmetry_std: float = 0.05
    curvature_std: float = 0.03
    arc_blend: float = 0.8
    max_speed_fraction: float = 0.9
    comfort_joints: tuple[str, ...] | None = None
    comfort_deg: tuple[float, ...] | None = None
    posture_std_deg: tuple[float, ...] | None = None
    posture_weight: tuple[float, ...] | None = None
    limit_margin_deg: float = 2.0
    catch_tolerance: float = 0.005
    ik_iters: int = 8
    oversample: float = 1.2
    max_rounds: int = 8

    def __post_init__(self):
        for name, low in _INT_MINIMA.items():
            v = getattr(self, name)
            ok = not isinstance(v, bool) and isinstance(v, int) and v >= low
            check_setting(ok, name, f"an integer >= {low}", v)
        ok = not isinstance(self.seed, bool) and isinstance(self.seed, int)
        check_setting(ok, "seed", "an integer", self.seed)
        for name, (lo, hi) in _NUMBER_RANGES.items():
            v = getattr(self, name)
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and lo <= v <= hi
            check_setting(ok, name, f"a number in [{lo:g}, {hi:g}]", v)
        check_setting(
            self.region is None or isinstance(self.region, CatchRegion),
            "region",
            "a catch region (frame, radius, azimuth_deg, elevation_deg) or null",
            self.region,
        )
        check_setting(
            self.comfort_joints is None or all(isinstance(n, str) for n in self.comfort_joints),
            "comfort_joints",
            "a list of joint names or null",
            self.comfort_joints,
        )
        check_setting(
            (self.comfort_joints is None) == (self.comfort_deg is None)
            and (
                self.comfort_deg is None
                or (
                    len(self.comfort_deg) == len(self.comfort_joints or ())
                    and all(_finite(v) for v in self.comfort_deg)
                )
            ),
            "comfort_deg",
            "one angle per entry of comfort_joints (set both or neither)",
            self.comfort_deg,
        )
        check_setting(
            self.posture_std_deg is None
            or (
                len(self.posture_std_deg) >= 1
                and all(_finite(v) and v >= 0 for v in self.posture_std_deg)
            ),
            "posture_std_deg",
            "a list of numbers >= 0 (one, or one per joint) or null",
            self.posture_std_deg,
        )
        check_setting(
            self.posture_weight is None
            or (
                len(self.posture_weight) >= 1
                and all(_finite(v) and 0 < v <= 1 for v in self.posture_weight)
            ),
            "posture_weight",
            "a list of numbers in (0, 1] (one, or one per joint) or null",
            self.posture_weight,
        )


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class IKSettings:
    """Regularisation and iteration counts of the key-point IK (static under jit).

    smooth: s [m^2/rad^2], pull toward the previous frame's posture (temporal smoothness).
    posture: r [m^2/rad^2], pull toward the rest posture (resolves redundancy).
    iters: LM iterations per frame. warmup: the first frame is solved ``warmup`` times in a row
      before the trial starts (``warmup * iters`` iterations from the rest posture).
    """

    smooth: float = 1e-3
    posture: float = 1e-5
    iters: int = 4
    warmup: int = 12

    def __post_init__(self):
        if self.smooth < 0 or self.posture < 0:
            raise UserError("smooth and posture weights must be >= 0")
        if self.iters < 1 or self.warmup < 1:
            raise UserError("iteration counts must be >= 1")
