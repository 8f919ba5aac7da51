"""Settings of the online stage (paper sec. 3.2 and 4): the query within the robot's limits
(`OnlineSettings`, `online.generation`), ball catching (`CatchSettings`, `online.catching`) and the
MuJoCo rollout of a plan (`SimSettings`, `online.simulate`), with the constants they share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from evojax_motion.errors import check_setting

MAX_DURATION = 60.0  # [s] the longest motion a query may ask for or be stretched to
BALL_RADIUS = 0.035  # [m], a tennis ball


@dataclass(frozen=True)
class OnlineSettings:
    """Settings of the online query (static under jit).

    - ``n_components``: principal components of the interpolation (paper eq. 1: 3).
    - ``limit_components``: components whose BC null space the limit projection moves in (>=
      ``n_components``; 4 = the optimisation compiler's eq. 3 basis).
    - ``min_neighbours``: a target is inside the learned region when at least this many valid
      primitives lie within ``BasisSettings.radius`` of it (<= ``BasisSettings.neighbours``).
    - ``prefer_evolved``: take the neighbours among the evolved (robot-optimised) primitives when
      at least ``min_neighbours`` of them lie within the radius, else among all valid ones. The
      human originals stay in the database for the evolution's sake (sec. 4.3); online, a basis
      mixing them in pulls the motion back toward the human's torques (benchmarks/online_quality:
      median eq. 5 cost 9.4 with all entries, 6.1 with evolved ones, paper setting).
    - ``ik_iters``: IK iterations (started from the nearest neighbour's final posture; on the
      paper-setting database 8 already reach the final accuracy, p95 6e-5 m).
    - ``reach_tolerance`` [m]: a target whose IK posture misses it by more is unreachable.
    - ``limit_margin`` [rad]: the limit projection aims this far inside the joint limits.
    - ``projection_iters``: semi-smooth Newton steps of the limit projection.
    - ``penalty``: weight of a limit violation relative to the null-space step (scale-free).
    - ``limit_headroom``: fraction of every velocity and torque limit that time scaling keeps
      free (for a tracking controller's feedback; docs/simulation.md): motions are planned
      within ``(1 - limit_headroom)`` times the limits.
    - ``scaling_scan``, ``scaling_iters``: durations scanned (log-spaced up to `MAX_DURATION`)
      and bisection steps of the time scaling.
    """

    n_components: int = 3
    limit_components: int = 4
    min_neighbours: int = 4
    prefer_evolved: bool = True
    ik_iters: int = 10
    reach_tolerance: float = 1e-3
    limit_margin: float = 2e-3
    projection_iters: int = 8
    penalty: float = 1e4
    limit_headroom: float = 0.05
    scaling_scan: int = 32
    scaling_iters: int = 24

    def __post_init__(self):
        check_setting(self.n_components >= 1, "n_components", "an integer >= 1", self.n_components)
        check_setting(
            self.limit_components >= self.n_components,
            "limit_components",
            f"an integer >= n_components ({self.n_components})",
            self.limit_components,
        )
        check_setting(
            self.min_neighbours >= 1, "min_neighbours", "an integer >= 1", self.min_neighbours
        )
        check_setting(self.ik_iters >= 1, "ik_iters", "an integer >= 1", self.ik_iters)
        check_setting(
            self.reach_tolerance > 0, "reach_tolerance", "a number > 0 [m]", self.reach_tolerance
        )
        check_setting(
            self.limit_margin >= 0, "limit_margin", "a number >= 0 [rad]", self.limit_margin
        )
        check_setting(
            self.projection_iters >= 0, "projection_iters", "an integer >= 0", self.projection_iters
        )
        check_setting(self.penalty > 0, "penalty", "a number > 0", self.penalty)
        check_setting(
            0 <= self.limit_headroom < 1,
            "limit_headroom",
            "a number in [0, 1)",
            self.limit_headroom,
        )
        check_setting(self.scaling_scan >= 2, "scaling_scan", "an integer >= 2", self.scaling_scan)
        check_setting(
            self.scaling_iters >= 0, "scaling_iters", "an integer >= 0", self.scaling_iters
        )


@dataclass(frozen=True)
class CatchSettings:
    """How a catch is planned (static under jit).

    - ``horizon`` [s], ``samples``: the ball's flight examined at ``samples`` instants in
      ``[0, horizon]`` (default every 10 ms for 1.5 s).
    - ``drag`` [1/m]: quadratic drag coefficient k (0: vacuum). ``substeps``: RK4 steps per sample.
    - ``reaction_time`` [s]: from release until the arm may start moving.
    - ``speedup``: the arm may move at most this many times faster than its natural duration.
    - ``time_scale`` [s], ``space_scale`` [m]: weights of the time margin and of the depth inside
      the learned region when choosing the catch point.
    """

    horizon: float = 1.5
    samples: int = 151
    drag: float = 0.0
    substeps: int = 4
    reaction_time: float = 0.1
    speedup: float = 1.5
    time_scale: float = 0.05
    space_scale: float = 0.03

    def __post_init__(self):
        check_setting(0 < self.horizon <= 10, "horizon", "a number in (0, 10] [s]", self.horizon)
        check_setting(self.samples >= 2, "samples", "an integer >= 2", self.samples)
        check_setting(0 <= self.drag < 1, "drag", "a number in [0, 1) [1/m]", self.drag)
        check_setting(self.substeps >= 1, "substeps", "an integer >= 1", self.substeps)
        check_setting(
            self.reaction_time >= 0, "reaction_time", "a number >= 0 [s]", self.reaction_time
        )
        check_setting(self.speedup >= 1, "speedup", "a number >= 1", self.speedup)
        check_setting(self.time_scale > 0, "time_scale", "a number > 0 [s]", self.time_scale)
        check_setting(self.space_scale > 0, "space_scale", "a number > 0 [m]", self.space_scale)


@dataclass(frozen=True)
class SimSettings:
    """How a plan is executed and judged.

    - ``bandwidth`` [Hz], ``damping_ratio``: the PD feedback's closed-loop natural frequency f
      and damping ratio zeta per joint (``kp = (2 pi f)^2``, ``kd = 2 zeta 2 pi f``, times the
      joint-space inertia matrix). 8 Hz is well below the 2 ms step's limit (``2 pi f dt`` =
      0.1) and above the motions' content (a 0.5 s reach is ~2 Hz).
    - ``hold`` [s]: simulated after the motion ends (or the ball arrives, if later).
    - ``ball_radius`` [m], ``ball_mass`` [kg]: a tennis ball (ITF: 3.3-3.4 cm, 56-59.4 g).
    - ``capture_radius`` [m]: the ball's centre within this of the catching point: touching the
      palm (ball radius 3.5 cm plus 2.5 cm, half a palm's width).
    - ``grip_time`` [s]: how long the grip takes to close; the largest relative speed of a catch
      is ``2 capture_radius / grip_time`` (10 m/s by default).
    - ``fps``: frames per second of the animation.
    """

    bandwidth: float = 8.0
    damping_ratio: float = 1.0
    hold: float = 0.3
    ball_radius: float = BALL_RADIUS
    ball_mass: float = 0.057
    capture_radius: float = 0.06
    grip_time: float = 0.012
    fps: float = 25.0

    def __post_init__(self):
        positive = {
            "bandwidth": "Hz",
            "damping_ratio": "",
            "ball_radius": "m",
            "ball_mass": "kg",
            "capture_radius": "m",
            "grip_time": "s",
            "fps": "1/s",
        }
        for name, unit in positive.items():
            value = getattr(self, name)
            check_setting(
                math.isfinite(value) and value > 0, name, f"a number > 0 {unit}".strip(), value
            )
        check_setting(
            math.isfinite(self.hold) and self.hold >= 0, "hold", "a number >= 0 [s]", self.hold
        )

    @property
    def kp(self) -> float:
        """Proportional gain per unit inertia [1/s^2]."""
        return (2.0 * math.pi * self.bandwidth) ** 2

    @property
    def kd(self) -> float:
        """Derivative gain per unit inertia [1/s]."""
        return 2.0 * self.damping_ratio * 2.0 * math.pi * self.bandwidth

    @property
    def max_relative_speed(self) -> float:
        """[m/s] the fastest a ball may move relative to the catching point and be caught."""
        return 2.0 * self.capture_radius / self.grip_time
