"""Settings of the evolution (config section ``evolution``; `evolution.step`,
`evolution.conditions`) and of its spread over devices (section ``parallel``;
`evolution.sharding`)."""

from __future__ import annotations

from dataclasses import dataclass

from evojax_motion.errors import check_setting


@dataclass(frozen=True)
class EvolutionSettings:
    """The evolution's settings; defaults are the paper's (sec. 4.2-4.4).

    - ``conditions``: size m of the fixed condition set (paper: 300).
    - ``generations``: generations to run (paper: 10).
    - ``region_margin`` [m]: targets are drawn uniformly from the bounding box of the
      demonstrations' hand positions grown by this margin on every side (negative shrinks it) ...
    - ``min_neighbours``: ... and kept only where at least this many demonstrations lie within
      ``basis.radius`` (so each condition has a basis: where the robot will work).
    - ``candidates_per_condition``: oversampling factor of that rejection sampling.
    - ``ik_tolerance`` [m]: a target whose human-like IK posture misses it by more is rejected.
    - ``duration`` [s]: duration of every condition's motion; ``null`` = its neighbours' mean.
    - ``fit_speed``: with ``duration: null``, each neighbour counts with its duration slowed
      uniformly until its joints keep within the robot's velocity limits less
      ``compiler.limit_headroom`` (`motion.feasibility.slowed_to_velocity_limits`); people
      move faster than many arms allow, and a condition at a human's duration leaves the
      optimiser no motion the robot can execute (default true; false: recorded durations).
    - ``bc_tolerance`` [rad], ``bc_velocity_tolerance`` [rad/s]: offspring whose start/end joint
      angles (velocities) miss the boundary conditions by more are discarded. Velocities get a
      looser bound: the demonstrations start and end at rest, so the velocity rows of the BC
      system are numerically degenerate (``compile_interp``) and are met only to the finite
      difference accuracy of the time grid (a few 1e-2 rad/s at T = 32).
    """

    conditions: int = 300
    generations: int = 10
    region_margin: float = 0.0
    min_neighbours: int = 5
    candidates_per_condition: int = 8
    ik_tolerance: float = 0.005
    duration: float | None = None
    fit_speed: bool = True
    bc_tolerance: float = 1e-3
    bc_velocity_tolerance: float = 0.1

    def __post_init__(self):
        check_setting(self.conditions >= 1, "conditions", "an integer >= 1", self.conditions)
        check_setting(self.generations >= 1, "generations", "an integer >= 1", self.generations)
        check_setting(
            abs(self.region_margin) < 10.0, "region_margin", "|margin| < 10 m", self.region_margin
        )
        check_setting(
            self.min_neighbours >= 1, "min_neighbours", "an integer >= 1", self.min_neighbours
        )
        check_setting(
            self.candidates_per_condition >= 1,
            "candidates_per_condition",
            "an integer >= 1",
            self.candidates_per_condition,
        )
        check_setting(self.ik_tolerance > 0, "ik_tolerance", "a number > 0 [m]", self.ik_tolerance)
        check_setting(
            self.duration is None or self.duration > 0,
            "duration",
            "null or a number > 0 [s]",
            self.duration,
        )
        check_setting(
            isinstance(self.fit_speed, bool), "fit_speed", "true or false", self.fit_speed
        )
        check_setting(
            self.bc_tolerance > 0, "bc_tolerance", "a number > 0 [rad]", self.bc_tolerance
        )
        check_setting(
            self.bc_velocity_tolerance > 0,
            "bc_velocity_tolerance",
            "a number > 0 [rad/s]",
            self.bc_velocity_tolerance,
        )


@dataclass(frozen=True)
class ParallelSettings:
    """How a generation's conditions are spread over devices (config section ``parallel``).

    - ``devices``: shard the conditions over the first ``devices`` of ``jax.devices()`` (the
      devices of all hosts after ``jax.distributed.initialize``); ``null`` = all of them. With one
      device the plain generation step runs on it.

    Padding rule (fixed): with d devices the m conditions are padded to ``d * ceil(m / d)`` with
    copies of the last condition marked as padding (NaN target). They never change the results of
    the real conditions and are dropped before the step returns (`evolution.sharding`).
    """

    devices: int | None = None

    def __post_init__(self):
        d = self.devices
        check_setting(
            d is None or (isinstance(d, int) and not isinstance(d, bool) and d >= 1),
            "devices",
            "null (all) or an integer >= 1",
            d,
        )
