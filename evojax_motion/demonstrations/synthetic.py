"""Synthetic human-like catching demonstrations: the initial movement primitive database.

Park et al. (2008, sec. 4.1) record one man catching a ball 311 times at "various falling point[s]
of a ball", using only his right arm and waist, and turn the marker trajectories into joint
trajectories with an IK solver (sec. 2). No such recording ships with this project, so
`generate_demonstrations` synthesises a stand-in from models of human reaching:

- catch points: a spherical-shell sector around the shoulder
  (`settings.demonstrations.CatchRegion`, centred on a named body of the robot at its rest
  posture), filled with uniform volume density by a Halton sequence (stratified,
  low-discrepancy) under a random shift drawn from the key. The shipped robots have a preset
  sector (`workspace.ROBOT_PRESETS`); for any other arm it is derived from the reachable
  workspace (`workspace.derive_region`: the hand over `workspace.WORKSPACE_SAMPLES` postures
  drawn within the joint limits);
- hand path, by progress u in [0, 1]: ``(1 - arc_blend)`` straight line (Morasso 1981; Flash &
  Hogan 1985) + ``arc_blend`` shoulder-centred arc (direction slerped, distance interpolated; from
  a hanging arm, straight lines pass close to the shoulder and need a deep, fast elbow flexion and
  trunk twist; measured vertical and 3-D reaches are curved too, Atkeson & Hollerbach 1985), plus a
  random bend ``4 u (1 - u) kappa L n`` that vanishes at both ends (``kappa ~ N(0,
  curvature_std)``, ``n`` a random unit normal of the chord, L its length);
- timing: minimum-jerk progress ``u = 10 w^3 - 15 w^4 + 6 w^5`` (Flash & Hogan 1985) of the warped
  time ``w = s + a s (1 - s)``, ``a ~ N(asymmetry_mean, asymmetry_std)``: a > 0 moves the speed
  peak earlier (a longer deceleration phase, MacKenzie et al. 1987); velocity and acceleration
  stay zero at both ends, so the motion goes from rest to rest;
- duration: Fitts' law ``D = (a + b log2(2 d / W)) exp(duration_noise z)`` (Fitts 1954), d the
  hand's travel, W the target (catch) width; stretched where a joint would exceed
  ``max_speed_fraction`` of its velocity limit;
- posture: a hand position leaves the arm redundant (7 joints, 3 constraints); the IK resolves it
  toward a comfortable final posture (mahru_arm's preset: rest for waist and wrist, shoulder
  forward, elbow moderately flexed; any other arm: its rest posture moved into the central half
  of each joint's range, `workspace.derive_comfort`, after the joint-range criterion of Liegeois
  1977) plus per-trial Gaussian noise, whose null-space part is the trial-to-trial elbow swivel and
  trunk/wrist variability of human reaching (Kang, He & Tillery 2005; Lacquaniti & Soechting
  1982). The preference moves from rest with the hand's progress;
- joint trajectories: `model.ik.solve_ik_trajectory` at T evenly spaced values of u (warm-started
  scan, limits shrunk by ``limit_margin_deg``), then a C2 cubic spline in u evaluated at the
  progress of the T time samples (`shaping`); cost ``0.5 int |tau|^2 dt`` (eq. 5,
  `motion.objective.CostProgram`).

Trials that miss their path or catch point by more than ``catch_tolerance`` or touch the shrunk
limits (a clamped joint has a kink) are rejected. Each round draws ``oversample * count``
candidates in one jit (fixed shapes); further rounds continue the Halton sequence until ``count``
trials pass; when they do not, the error counts the candidates by cause (limits touched, by joint;
catch points missed, with figures and how many lie beyond the sampled reach). Same key ->
bit-identical output. Continuous joints (no range) are stored on the rest branch
(`motion.angles.on_rest_branch`).
"""

from __future__ import annotations

import functools
import math
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import one_shot, one_shot_jit
from evojax_motion.demonstrations.shaping import (
    HALTON_BASES,
    halton,
    region_points,
    shoulder_arc,
    spline_eval,
    spline_matrix,
)
from evojax_motion.demonstrations.workspace import (
    LIMIT_TOUCH_TOL,
    Resolved,
    resolve_settings,
    sample_workspace,
)
from evojax_motion.errors import UserError
from evojax_motion.linalg.precision import exact_matmuls
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.model.ik import solve_ik_trajectory
from evojax_motion.model.robot import Robot
from evojax_motion.motion.angles import on_rest_branch
from evojax_motion.motion.database import Database, human_mask, make_database
from evojax_motion.motion.objective import CostProgram
from evojax_motion.motion.profiles import minimum_jerk
from evojax_motion.motion.timegrid import derivatives, make_time_grid
from evojax_motion.run import cache as compile_cache
from evojax_motion.settings.demonstrations import MAX_ASYMMETRY, DemoSettings

_Array = jax.Array | np.ndarray
CLIP_SIGMAS = 3.0  # every normal draw is clipped at this many standard deviations

CITATIONS = (
    "Park, Ra, Kim & Song (2008), Imitation learning of robot movement using evolutionary "
    "algorithm, IFAC World Congress (311 catching demonstrations, sec. 4.1)",
    "Flash & Hogan (1985), The coordination of arm movements: an experimentally confirmed "
    "mathematical model, J. Neurosci. 5(7):1688-1703 (minimum jerk)",
    "Fitts (1954), The information capacity of the human motor system in controlling the "
    "amplitude of movement, J. Exp. Psychol. 47(6):381-391 (Fitts' law)",
    "Morasso (1981), Spatial control of arm movements, Exp. Brain Res. 42:223-227 "
    "(near-straight hand paths, single-peaked speed)",
    "MacKenzie, Marteniuk, Dugas, Liske & Eickmeier (1987), Three-dimensional movement "
    "trajectories in Fitts' task, Q. J. Exp. Psychol. 39A:629-647 (asymmetric speed profiles)",
    "Kang, He & Tillery (2005), Determining natural arm configuration along a reaching "
    "trajectory, Exp. Brain Res. 167:352-361 (elbow swivel / arm redundancy)",
    "Atkeson & Hollerbach (1985), Kinematic features of unrestrained vertical arm movements, "
    "J. Neurosci. 5(9):2318-2330 (curved vertical paths, invariant bell-shaped speed)",
    "Lacquaniti & Soechting (1982), Coordination of arm and wrist motion during a reaching task, "
    "J. Neurosci. 2(4):399-408 (arm posture in reaching)",
    "Liegeois (1977), Automatic supervisory control of the configuration and behavior of "
    "multibody mechanisms, IEEE Trans. SMC 7(12):868-871 (preferring the middle of joint ranges)",
)


class _Params(NamedTuple):
    """Traced scalar settings of the batched generator (changing them does not recompile)."""

    fitts_a: _Array
    fitts_b: _Array
    target_width: _Array
    duration_noise: _Array
    asymmetry_mean: _Array
    asymmetry_std: _Array
    curvature_std: _Array
    arc_blend: _Array
    max_speed_fraction: _Array
    limit_margin: _Array  # [rad]

    @classmethod
    def of(cls, settings: DemoSettings, dtype) -> _Params:
        values = {f: getattr(settings, f) for f in cls._fields if f != "limit_margin"}
        values["limit_margin"] = math.radians(settings.limit_margin_deg)
        return cls(**{k: np.asarray(v, dtype) for k, v in values.items()})  # no XLA op


class _Trials(NamedTuple):
    """A candidate pool, P trials (jax arrays in the jit, numpy after). Shapes in comments."""

    q: _Array  # (P, T, J)
    duration: _Array  # (P,)
    target: _Array  # (P, 3) catch point
    final_pos: _Array  # (P, 3) hand at the last sample (FK)
    track_error: _Array  # (P,) largest hand error along the path [m]
    margin: _Array  # (P, J) smallest distance to the true limits [rad]
    speed_ratio: _Array  # (P,) largest |qd| / velocity limit
    end_speed: _Array  # (P,) largest |qd| at s = 0 and s = 1 [rad/s]
    asymmetry: _Array  # (P,)
    curvature: _Array  # (P,)
    stretched: _Array  # (P,) duration lengthened beyond Fitts' law for the velocity limits


class _Robot(NamedTuple):
    """The robot's arrays the generator needs, ``(J,)`` each except ``centre (3,)``."""

    centre: _Array  # catch-region centre = shoulder-arc centre [m]
    rest: _Array
    comfort: _Array  # preferred final posture [rad]
    posture_std: _Array  # [rad]
    posture_weight: _Array  # IK w_pref
    lower: _Array
    upper: _Array
    velocity_limit: _Array


def _shift_and_round_keys(key, rounds: int):
    """The Halton shift ``(len(HALTON_BASES),)`` and one key per round ``(rounds,)``, from the
    two halves of ``key`` (one program: op by op, each would compile on its own)."""
    k_shift, k_rounds = jax.random.split(key)
    shift = jax.random.uniform(k_shift, (len(HALTON_BASES),))
    return shift, jax.vmap(functools.partial(jax.random.fold_in, k_rounds))(jnp.arange(rounds))


_shift_and_round_keys_program = one_shot_jit(_shift_and_round_keys, static_argnames="rounds")


@exact_matmuls
def _simulate(
    dyn: Dynamics, samples: int, ik_iters: int, keys, rnd, target, prm: _Params, rob: _Robot
) -> _Trials:
    """Every trial of a candidate pool in one program: round ``rnd`` (int32 scalar) of the
    round keys ``keys (rounds,)``, ``target (P, 3)`` catch points."""
    key = keys[rnd]  # here: indexing a key array outside would compile two programs
    dtype = target.dtype
    p, j = target.shape[0], rob.rest.shape[0]
    grid = make_time_grid(samples, dtype=np.dtype(dtype))
    k_dur, k_asym, k_dir, k_curv, k_post = jax.random.split(key, 5)

    def normal(k, shape=(p,)):
        return jnp.clip(jax.random.normal(k, shape, dtype), -CLIP_SIGMAS, CLIP_SIGMAS)

    p0 = dyn.site_pose(rob.rest)[0]
    travel = target - p0
    length = jnp.linalg.norm(travel, axis=-1)
    bits = jnp.log2(jnp.maximum(2.0 * length / prm.target_width, 1.0))  # Fitts' index
    duration = (prm.fitts_a + prm.fitts_b * bits) * jnp.exp(prm.duration_noise * normal(k_dur))
    asym = jnp.clip(
        prm.asymmetry_mean + prm.asymmetry_std * normal(k_asym), -MAX_ASYMMETRY, MAX_ASYMMETRY
    )
    kappa = prm.curvature_std * normal(k_curv)
    g = jax.random.normal(k_dir, (p, 3), dtype)
    axis = travel / length[:, None]
    g = g - jnp.sum(g * axis, -1, keepdims=True) * axis  # normal to the straight line
    bend = (kappa * length)[:, None, None] * (g / jnp.linalg.norm(g, axis=-1, keepdims=True))[
        :, None
    ]

    def hand_path(u):  # progress u (P, K, 1) -> hand positions (P, K, 3)
        line = p0 + u * travel[:, None]
        arc = shoulder_arc(rob.centre, p0, target, u)
        return (1.0 - prm.arc_blend) * line + prm.arc_blend * arc + 4.0 * u * (1.0 - u) * bend

    lo_ik, hi_ik = rob.lower + prm.limit_margin, rob.upper - prm.limit_margin
    pref_final = jnp.clip(rob.comfort + rob.posture_std * normal(k_post, (p, j)), lo_ik, hi_ik)

    # IK at K = T evenly spaced values of the progress u, not at the time samples: those crowd
    # near the ends, where float32 IK noise between nearly equal targets would read as velocity.
    nodes = jnp.broadcast_to(jnp.linspace(0.0, 1.0, samples, dtype=dtype)[:, None], (p, samples, 1))
    pref = rob.rest + nodes * (pref_final - rob.rest)[:, None]  # (P, K, J): rest -> preference
    q_start = jnp.broadcast_to(rob.rest, (p, j))
    ik = solve_ik_trajectory(
        dyn,
        hand_path(nodes),
        q_start,
        lo_ik,
        hi_ik,
        q_pref=pref,
        w_pref=rob.posture_weight,
        iters=ik_iters,
    )
    q_nodes = ik.q.at[:, 0].set(rob.rest)  # node 0 is the rest posture (zero IK error)

    # Time: minimum-jerk progress on the warped time, through a C2 spline of the nodes in u.
    s64 = np.linspace(0.0, 1.0, samples)
    s, s_rest = jnp.asarray(s64, dtype)[None], jnp.asarray(1.0 - s64, dtype)[None]
    w, w_rest = s + asym[:, None] * s * s_rest, s_rest * (1.0 - asym[:, None] * s)  # w, 1 - w
    u, u_rest = minimum_jerk(w), minimum_jerk(w_rest)  # 1 - mj(w) = mj(1 - w), accurate near 1
    spline = functools.partial(spline_eval, spline_matrix(samples, dtype))
    q = jax.vmap(spline)(q_nodes, u, u_rest)
    hand = jax.vmap(jax.vmap(lambda qq: dyn.site_pose(qq)[0]))(q)
    track_error = jnp.max(jnp.linalg.norm(hand - hand_path(u[..., None]), axis=-1), axis=1)

    # A human-paced motion the robot cannot follow is slowed down, not dropped (dropping would
    # thin out the catch points that need fast joints): D >= max |dq/ds| / (fraction * limit).
    dq_ds, _ = derivatives(grid, q, jnp.ones((), dtype))
    needed = jnp.max(jnp.abs(dq_ds) / (prm.max_speed_fraction * rob.velocity_limit), axis=(1, 2))
    stretched = needed > duration
    duration = jnp.maximum(duration, needed)
    qd, _ = derivatives(grid, q, duration)
    return _Trials(
        q=q,
        duration=duration,
        target=target,
        final_pos=hand[:, -1],
        track_error=track_error,
        margin=jnp.minimum(jnp.min(q - rob.lower, axis=1), jnp.min(rob.upper - q, axis=1)),
        speed_ratio=jnp.max(jnp.abs(qd) / rob.velocity_limit, axis=(1, 2)),
        end_speed=jnp.max(jnp.abs(qd[:, jnp.array([0, -1])]), axis=(1, 2)),
        asymmetry=asym,
        curvature=kappa,
        stretched=stretched,
    )


class _Checks(NamedTuple):
    """A candidate pool's checks (numpy, P trials)."""

    finite: np.ndarray  # (P,) bool: q and duration finite
    miss: np.ndarray  # (P,) [m] hand at the end vs the catch point
    track_error: np.ndarray  # (P,) [m]
    touch: np.ndarray  # (P, J) bool: the joint came within the shrunk limits

    def accepted(self, settings: DemoSettings) -> np.ndarray:
        """(P,) bool: finite, on the path and the catch point, clear of the IK's shrunk limits."""
        return (
            self.finite
            & (self.miss <= settings.catch_tolerance)
            & (self.track_error <= settings.catch_tolerance)
            & ~self.touch.any(axis=1)
        )


_simulate_program = one_shot_jit(_simulate, static_argnames=("dyn", "samples", "ik_iters"))


def _checks(trials: _Trials, settings: DemoSettings) -> _Checks:
    near = math.radians(settings.limit_margin_deg) + LIMIT_TOUCH_TOL
    return _Checks(
        finite=np.isfinite(trials.q).all(axis=(1, 2)) & np.isfinite(trials.duration),
        miss=np.linalg.norm(trials.final_pos - trials.target, axis=-1),
        track_error=np.asarray(trials.track_error),
        touch=np.asarray(trials.margin) <= near,
    )


def _failure(
    robot: Robot, settings: DemoSettings, res: Resolved, checks: _Checks, targets, n_valid
) -> str:
    """Why too few candidates passed: each cause with its count and figures, and what to change
    for the commonest one. ``targets (P, 3)``: the catch points of ``checks``' P trials."""
    region, centre = res.region, res.centre
    tol, n = settings.catch_tolerance, len(checks.miss)
    finite = checks.finite
    missed = finite & ~(checks.miss <= tol)
    strayed = finite & ~(checks.track_error <= tol)
    touched = finite & checks.touch.any(axis=1)
    causes, hints = [], []
    if touched.any():
        per_joint = checks.touch[finite].sum(axis=0)
        joints = {robot.joint_names[k]: int(per_joint[k]) for k in np.argsort(-per_joint)}
        joints = {name: c for name, c in joints.items() if c}
        causes.append(
            f"{int(touched.sum())} came within demos.limit_margin_deg = "
            f"{settings.limit_margin_deg:g} deg of a joint limit (by joint: {joints})"
        )
        hints.append(
            (
                int(touched.sum()),
                "lower demos.limit_margin_deg or move demos.region away from "
                f"the postures that need joint {next(iter(joints))!r} at its limit",
            )
        )
    if missed.any():
        workspace = sample_workspace(robot, math.radians(settings.limit_margin_deg))
        reach = float(np.linalg.norm(workspace.hand - centre, axis=1).max())
        far = np.linalg.norm(np.asarray(targets, np.float64)[missed] - centre, axis=1) > reach
        mm = 1e3 * checks.miss[missed]
        causes.append(
            f"{int(missed.sum())} missed the catch point by more than demos.catch_tolerance = "
            f"{tol:g} m (median {np.median(mm):.3g} mm, largest {mm.max():.3g} mm), "
            f"{int(far.sum())} of them farther from body {region.frame!r} than the hand reaches "
            f"within the joint limits ({reach:.3g} m over {len(workspace.hand)} sampled postures)"
        )
        if 2 * far.sum() >= missed.sum():
            fix = f"move demos.region inside the robot's reach (radius below {reach:.3g} m)"
        else:
            fix = "raise demos.ik_iters or move demos.region (the IK does not reach its points)"
        hints.append((int(missed.sum()), fix))
    if strayed.any():
        causes.append(f"{int(strayed.sum())} left the hand path by more than that")
    if not finite.all():
        causes.append(f"{int((~finite).sum())} had non-finite joint angles or durations")
    hint = max(hints)[1] + ", or raise demos.max_rounds" if hints else "raise demos.max_rounds"
    return (
        f"demos: only {n_valid} of {n} candidate trials passed the checks, expected "
        f"{settings.count}: {'; '.join(causes)}; {hint}"
    )


def generate_demonstrations(
    robot: Robot,
    dyn: Dynamics,
    settings: DemoSettings,
    key: jax.Array | None = None,
    cache_parts: Any = None,
    on_traced=None,
    costs: CostProgram | None = None,
) -> tuple[Database, dict]:
    """``settings.count`` synthetic catching demonstrations of ``robot`` and a report.

    key: the only randomness (default ``jax.random.key(settings.seed)``); split into the Halton
      shift and one key per candidate round. Same key -> bit-identical database.
    Returns ``(db, report)``: ``db`` holds exactly ``count`` valid human primitives, ``q (N, T, J)``
    from the rest posture to the catch posture, ``condition`` = hand position at the end (FK),
    ``cost`` = eq. 5. ``report``: provenance (``synthetic``, ``description``, ``citations``),
    counts, durations, region bounds, smallest limit margins, compile and wall time [s].
    cache_parts: what `run.cache.traced_program` keys the simulation by besides its
      arguments (the config sections and robot model behind ``robot``, ``dyn`` and
      ``settings``); None compiles it in this process only.
    on_traced: called once the simulation is traced, before it compiles
      (`run.cache.compile_traced`).
    costs: the `motion.objective.CostProgram` of ``dyn`` for ``settings.samples`` and at least
      ``settings.count`` rows that computes the eq. 5 costs (a run's own; default: one made here).
    Raises ``UserError`` when ``max_rounds`` rounds do not yield ``count`` valid trials.
    """
    t_start = time.perf_counter()
    key = jax.random.key(settings.seed) if key is None else key
    res = resolve_settings(robot, settings)
    dtype = np.dtype(dyn.dtype)
    shift, round_keys = _shift_and_round_keys_program()(key, settings.max_rounds)
    shift = np.asarray(shift, np.float64)
    pool = math.ceil(settings.count * settings.oversample)
    prm = _Params.of(settings, dtype)
    arrays = dict(
        res._asdict(),
        rest=robot.rest,
        lower=robot.lower,
        upper=robot.upper,
        velocity_limit=robot.velocity_limit,
    )
    rob = _Robot(**{f: np.asarray(arrays[f], dtype) for f in _Robot._fields})

    compiled, compile_s, chosen, n_valid = None, 0.0, [], 0
    all_checks: list[_Checks] = []
    all_targets: list[np.ndarray] = []
    for rnd in range(settings.max_rounds):  # rounds continue the Halton sequence
        u = (halton(np.arange(rnd * pool, (rnd + 1) * pool) + 1) + shift) % 1.0
        target = np.asarray(region_points(res.region, res.centre, u), dtype)
        args = (round_keys, np.asarray(rnd, np.int32), target, prm, rob)
        if compiled is None:
            t0 = time.perf_counter()
            statics = (dyn, settings.samples, settings.ik_iters)
            program_args: tuple
            options = one_shot()
            if cache_parts is None:  # `_simulate`'s own jit: traced once per process
                program, program_args, parts = _simulate_program(), (*statics, *args), None
            else:
                program = jax.jit(functools.partial(_simulate, *statics), compiler_options=options)
                program_args, parts = args, {"program": "demos._simulate", "parts": cache_parts}
            compiled = compile_cache.compile_traced(
                program, program_args, parts, options, on_traced
            )
            compile_s = time.perf_counter() - t0
        trials = _Trials(*(np.asarray(a) for a in jax.device_get(compiled(*args))))
        checks = _checks(trials, settings)
        ok = checks.accepted(settings)
        chosen.append(_Trials(*(a[ok] for a in trials)))
        all_checks.append(checks)
        all_targets.append(np.asarray(trials.target))
        n_valid += int(ok.sum())
        if n_valid >= settings.count:
            break
    else:
        every = _Checks(*(np.concatenate(a) for a in zip(*all_checks)))
        raise UserError(_failure(robot, settings, res, every, np.concatenate(all_targets), n_valid))
    good = _Trials(*(np.concatenate(a)[: settings.count] for a in zip(*chosen)))
    # Continuous joints on the branch of the rest posture (a no-op without them).
    good = good._replace(q=on_rest_branch(np.asarray(good.q), robot.rest, robot.continuous))
    if costs is None:
        costs = CostProgram(dyn, make_time_grid(settings.samples), settings.count, cache_parts)
    cost = costs(good.q, good.duration)[0]
    if not np.isfinite(cost).all():  # finite, in-range motions: not expected
        raise UserError(
            f"demos: {int((~np.isfinite(cost)).sum())} synthesised demonstrations have a "
            "non-finite torque cost (eq. 5); check the robot model's inertias"
        )
    db = make_database(good.q, good.duration, good.final_pos, cost)
    counts = {"candidates_tried": (rnd + 1) * pool, "candidates_valid": n_valid}
    timing = {"compile_s": compile_s, "wall_s": time.perf_counter() - t_start}
    return db, _report(robot, settings, res, good, cost, counts, timing)


def _report(robot, settings, res, good: _Trials, cost, counts: dict, timing: dict) -> dict:
    r = res.region
    description = (
        f"{settings.count} synthetic human-like catching demonstrations of robot {robot.name!r} "
        "(no motion capture; the paper's 311 captured catches are not available): catch points "
        f"in a shell sector around body {r.frame!r} (radius {r.radius[0]:g}-{r.radius[1]:g} m, "
        f"azimuth {r.azimuth_deg[0]:g}..{r.azimuth_deg[1]:g} deg, elevation "
        f"{r.elevation_deg[0]:g}..{r.elevation_deg[1]:g} deg) by shifted Halton sampling; "
        f"hand paths {1 - settings.arc_blend:g} straight line + {settings.arc_blend:g} "
        "shoulder-centred arc with a random end-vanishing bend; minimum-jerk progress (Flash & "
        "Hogan 1985) on a randomly asymmetric time warp; durations from Fitts' law (Fitts 1954; "
        f"a={settings.fitts_a:g} s, b={settings.fitts_b:g} s/bit, W={settings.target_width:g} m) "
        "with log-normal noise, stretched where the robot's velocity limits require; redundancy "
        "resolved by null-space IK toward a comfortable posture with per-trial noise (elbow "
        "swivel variability, Kang et al. 2005); rest to rest, inside the joint limits."
    )
    miss = np.linalg.norm(good.final_pos - good.target, axis=-1)
    return {
        "synthetic": True,
        "description": description,
        "citations": list(CITATIONS),
        "robot": robot.name,
        "count": len(good.duration),
        "samples": settings.samples,
        **counts,
        "duration_min_s": float(good.duration.min()),
        "duration_max_s": float(good.duration.max()),
        "duration_mean_s": float(good.duration.mean()),
        "duration_stretched": int(good.stretched.sum()),
        "region": {
            "frame": r.frame,
            "centre_m": np.round(res.centre, 4).tolist(),
            "radius_m": list(r.radius),
            "azimuth_deg": list(r.azimuth_deg),
            "elevation_deg": list(r.elevation_deg),
        },
        "robot_defaults": res.source,  # region and posture preference not set in demos
        "comfort_deg": dict(zip(robot.joint_names, np.round(np.rad2deg(res.comfort), 2).tolist())),
        "catch_points": good.target.tolist(),  # (count, 3) the targets, row i = db row i
        "catch_min_m": np.round(good.target.min(axis=0), 4).tolist(),
        "catch_max_m": np.round(good.target.max(axis=0), 4).tolist(),
        "catch_miss_max_m": float(miss.max()),
        "track_error_max_m": float(good.track_error.max()),
        "min_limit_margin_deg": _margins_deg(robot, good.margin.min(axis=0)),
        "max_speed_over_limit": float(good.speed_ratio.max()),
        "max_end_speed_rad_s": float(good.end_speed.max()),
        "asymmetry_range": [float(good.asymmetry.min()), float(good.asymmetry.max())],
        "curvature_range": [float(good.curvature.min()), float(good.curvature.max())],
        "cost_range": [float(cost.min()), float(cost.max())],
        **{k: round(v, 3) for k, v in timing.items()},
    }


def _margins_deg(robot: Robot, margin) -> dict:
    """Joint name -> smallest distance to a limit [deg], 2 decimals; None for a continuous joint
    (it has no limit)."""
    deg = np.round(np.rad2deg(np.asarray(margin)), 2).tolist()
    return {n: None if c else d for n, d, c in zip(robot.joint_names, deg, robot.continuous)}


def summarize_demonstrations(db: Database, robot: Robot) -> dict:
    """Summary of the valid human primitives of ``db`` for the CLI (plain numbers, lists, dicts).

    count, duration min/max/mean [s], catch (final hand position) bounds [m], smallest joint-limit
    margin per joint [deg], largest joint speed at the two ends [rad/s], mean cost (eq. 5).
    """
    keep = human_mask(db)
    if not keep.any():
        raise UserError("demonstrations: expected at least one valid human primitive, got none")
    q = np.asarray(db.q)[keep]
    dur = np.asarray(db.duration)[keep]
    cond = np.asarray(db.condition)[keep]
    qd, _ = derivatives(make_time_grid(q.shape[1]), q, dur)
    margin = np.minimum((q - robot.lower).min(axis=(0, 1)), (robot.upper - q).min(axis=(0, 1)))
    return {
        "count": int(keep.sum()),
        "samples": int(q.shape[1]),
        "duration_min_s": float(dur.min()),
        "duration_max_s": float(dur.max()),
        "duration_mean_s": float(dur.mean()),
        "catch_min_m": np.round(cond.min(axis=0), 4).tolist(),
        "catch_max_m": np.round(cond.max(axis=0), 4).tolist(),
        "min_limit_margin_deg": _margins_deg(robot, margin),
        "max_end_speed_rad_s": float(np.abs(np.asarray(qd)[:, [0, -1]]).max()),
        "cost_mean": float(np.mean(np.asarray(db.cost)[keep])),
    }
