"""``evojax-motion simulate``: execute a planned motion in MuJoCo physics (`simulate`).

    evojax-motion simulate --db RUN --target X Y Z [--duration S] [--out DIR]
    evojax-motion simulate --db RUN --ball PX PY PZ VX VY VZ [--out DIR]

The motion is planned as ``generate`` or ``catch`` plans it (the same checks and refusals: an
unreachable target, an uncatchable ball, a motion that no allowed duration brings within the
velocity and torque limits: one line ``error: ...``, exit status 2), then executed by the
tracking controller of `simulate`, with the ball thrown for ``--ball``. ``--delay`` starts the
motion later than planned (how much timing error a catch tolerates). Prints a short summary
(tracking error, time at a torque limit, caught or not and the closest distance); with ``--out``
also writes ``simulation.json`` (the same figures, the controller's gains, the catch criterion)
and ``simulation.gif`` (the simulated motion, rendered by `render`).

``cli.entry.build_parser`` calls `add_simulate_parser` on its subparsers.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from evojax_motion.errors import UserError

RESULT_FILE = "simulation.json"
ANIMATION_FILE = "simulation.gif"
ANIMATION_SIZE = (320, 240)  # width, height [px]
_NEAR_PATH = 1.0  # [m] ball positions this close to the hand's path are kept in the picture


def add_simulate_parser(subparsers) -> None:
    """Add ``simulate`` to an argparse subparsers object."""
    from evojax_motion.cli.online import add_query_arguments

    p = subparsers.add_parser(
        "simulate", help="execute a planned motion in MuJoCo physics (tracking, catching)"
    )
    p.add_argument("--db", required=True, help="database .npz or run directory (db_final.npz)")
    task = p.add_mutually_exclusive_group(required=True)
    task.add_argument("--target", nargs=3, type=float, metavar=("X", "Y", "Z"))
    task.add_argument(
        "--ball",
        nargs=6,
        type=float,
        metavar=("PX", "PY", "PZ", "VX", "VY", "VZ"),
        help="release position [m] and velocity [m/s]",
    )
    p.add_argument("--duration", type=float, default=None, help="[s] (--target); default: natural")
    p.add_argument("--reaction", type=float, default=None, help="reaction time [s] (--ball)")
    p.add_argument("--horizon", type=float, default=None, help="flight time examined [s] (--ball)")
    p.add_argument(
        "--delay", type=float, default=0.0, help="start the motion this much later than planned [s]"
    )
    p.add_argument("--out", default=None, help="folder for simulation.json and simulation.gif")
    p.add_argument("--force", action="store_true", help="overwrite the files in --out")
    p.add_argument("--renderer", choices=("auto", "mujoco", "stick"), default="auto")
    add_query_arguments(p)
    p.set_defaults(func=cmd_simulate, drag=0.0)  # the simulated ball flies in vacuum, as planned


def _check_args(args) -> Path | None:
    if not (math.isfinite(args.delay) and 0.0 <= args.delay <= 10.0):
        raise UserError(f"--delay: expected a number in [0, 10] [s], got {args.delay}")
    if args.target is not None and (args.reaction is not None or args.horizon is not None):
        raise UserError("--reaction/--horizon: only with --ball")
    if args.ball is not None and args.duration is not None:
        raise UserError("--duration: only with --target (a catch's duration follows the ball)")
    if args.out is None:
        return None
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: expected a folder for {RESULT_FILE} and {ANIMATION_FILE}")
    taken = [name for name in (RESULT_FILE, ANIMATION_FILE) if (out / name).exists()]
    if taken and not args.force:
        raise UserError(f"{out}: already holds {', '.join(taken)} (pass --force to overwrite)")
    return out


def _plan_target(args, opened):
    """The motion to ``--target``: ``(motion, description)`` (numpy `OnlineResult`)."""
    from evojax_motion.cli.online import _generate_one, _vec
    from evojax_motion.online.explain import explain_unusable

    model = opened[0]
    target = np.asarray(args.target, np.float32)
    motion = _generate_one(opened, target, args.duration, None)
    if not bool(motion.reachable[0]):
        raise UserError(
            f"target {_vec(target)} m is outside the reachable region (`evojax-motion generate "
            "--nearest` finds the nearest reachable point)"
        )
    if not bool(motion.ok[0]):
        raise UserError(explain_unusable(model.robot, motion, 0, model.settings))
    return motion, {"task": "target", "target": _vec(target)}


def _plan_catch(args, opened):
    """The catch of ``--ball``: ``(motion, description, ball)``."""
    import jax

    from evojax_motion.cli.online import _catch_settings, _catcher, _vec
    from evojax_motion.online.catching import explain_plan, validate_ball
    from evojax_motion.online.explain import explain_unusable
    from evojax_motion.online.simulate import Ball

    model = opened[0]
    p0, v0 = validate_ball(args.ball)
    catch = _catch_settings(args)
    q0 = np.asarray(model.robot.rest, np.float32)[None]
    plan, motion = jax.device_get(_catcher(opened, catch)(model.db_device, p0, v0, q0))
    line = explain_plan(plan, 0)
    if not bool(plan.feasible[0]):
        raise UserError(line)
    if not bool(motion.ok[0]):
        window = "between the reaction time and the ball's arrival"
        raise UserError(explain_unusable(model.robot, motion, 0, model.settings, window))
    about = {
        "task": "catch",
        "ball": _vec(np.concatenate([p0[0], v0[0]])),
        "plan": line,
        "catch_time": float(plan.catch_time[0]),
        "catch_point": _vec(plan.catch_point[0]),
    }
    return motion, about, Ball(p0[0].astype(np.float64), v0[0].astype(np.float64))


def _json_safe(x):
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _animate(args, robot, rollout, settings, out: Path) -> str:
    """Render the rollout into ``out / ANIMATION_FILE``; returns the renderer used."""
    from evojax_motion.online.simulate import frame_indices
    from evojax_motion.report import kinematics, render

    idx = frame_indices(rollout, settings.fps)
    q, balls = rollout.q[idx], rollout.ball[idx]
    near = np.min(
        np.linalg.norm(balls[:, None, :] - rollout.hand_ref[None, ::10, :], axis=2), axis=1
    )
    extra = balls[np.isfinite(near) & (near <= _NEAR_PATH)]
    view = kinematics.VIEWS["catch" if np.isfinite(balls).any() else "three_quarter"]
    camera = kinematics.fit_camera(robot, [q], view, extra_points=extra if extra.size else None)
    floor = kinematics.floor_height(robot, [q])
    width, height = ANIMATION_SIZE
    frames = render.render_motion(
        robot, q, [camera], balls, width, height, floor, renderer=args.renderer
    )
    render.save_gif(frames.images, out / ANIMATION_FILE, fps=settings.fps)
    return frames.renderer


def cmd_simulate(args) -> int:
    """``evojax-motion simulate``: plan, execute in MuJoCo, report; exit 0, or `UserError`."""
    from evojax_motion.cli.online import _open, _print_table
    from evojax_motion.online.explain import describe_limits
    from evojax_motion.online.simulate import Plan, simulate, summarise
    from evojax_motion.report.render import RenderUnavailable
    from evojax_motion.settings.online import SimSettings

    out = _check_args(args)
    opened = _open(args)
    model = opened[0]
    robot = model.robot
    ball = None
    if args.target is not None:
        motion, about = _plan_target(args, opened)
    else:
        motion, about, ball = _plan_catch(args, opened)
    settings = SimSettings()
    plan = Plan(motion.t[0] + args.delay, motion.q[0], motion.qd[0], motion.qdd[0])
    t_end = float(plan.t[-1]) + settings.hold
    if "catch_time" in about:
        t_end = max(t_end, about["catch_time"] + settings.hold)
    rollout = simulate(robot, plan, settings, ball, t_end)
    summary = summarise(rollout, ball is not None)

    rows = {
        "motion": f"{float(plan.t[0]):.3f} -> {float(plan.t[-1]):.3f} s"
        + (f" (started {args.delay:.3f} s late)" if args.delay else ""),
        **describe_limits(robot, motion, 0),
        "tracking error": f"RMS {summary.tracking_rms:.2e} rad, max {summary.tracking_max:.2e} "
        f"rad; hand RMS {summary.hand_rms_mm:.2f} mm, max {summary.hand_max_mm:.2f} mm",
        "at a torque limit": f"{summary.at_torque_limit:.1%} of the steps",
    }
    if ball is not None:
        needs = (
            f"a catch needs <= {settings.capture_radius * 1e3:.0f} mm at <= "
            f"{settings.max_relative_speed:.1f} m/s relative"
        )
        closest = (
            f"closest {summary.closest_distance * 1e3:.1f} mm at t = {summary.closest_time:.3f} "
            f"s, {summary.closest_relative_speed:.2f} m/s relative"
        )
        rows["caught"] = (
            f"yes, at t = {summary.capture_time:.3f} s: {summary.capture_distance * 1e3:.1f} mm "
            f"from the catching point at {summary.capture_relative_speed:.2f} m/s relative "
            f"({needs}; {closest})"
            if summary.caught
            else f"no ({closest}; {needs})"
        )
    if out is not None:
        renderer = "none"
        try:
            renderer = _animate(args, robot, rollout, settings, out)
        except RenderUnavailable as e:  # --renderer mujoco without OpenGL
            raise UserError(f"--renderer mujoco: {e}") from None
        doc = _result_document(model, motion, about, args, settings, rollout, summary, renderer)
        from evojax_motion.run.atomic import atomic_write_text

        atomic_write_text(out / RESULT_FILE, json.dumps(_json_safe(doc), indent=1) + "\n")
        rows["written to"] = f"{out / RESULT_FILE}, {out / ANIMATION_FILE} ({renderer})"
    _print_table(rows)
    return 0


def _result_document(model, motion, about, args, settings, rollout, summary, renderer) -> dict:
    """What ``simulation.json`` holds."""
    import mujoco

    from evojax_motion.online.explain import limit_meta
    from evojax_motion.online.simulate import simulation_model

    sim = simulation_model(model.robot, settings, None)
    return {
        "database": model.source,
        "robot": model.robot.name,
        "site": model.robot.site_name,
        **about,
        "motion": {
            "start": float(motion.t[0, 0]) + args.delay,
            "end": float(motion.t[0, -1]) + args.delay,
            "delay": args.delay,
            "duration": float(motion.duration[0]),
            **limit_meta(motion, 0),
        },
        "controller": {
            "law": "tau = clip(mj_inverse(q_ref, qd_ref, qdd_ref) + M(q) (kp e + kd de), limits)",
            "bandwidth_hz": settings.bandwidth,
            "damping_ratio": settings.damping_ratio,
            "kp_per_inertia": settings.kp,
            "kd_per_inertia": settings.kd,
            "timestep": float(sim.opt.timestep),
            "integrator": mujoco.mjtIntegrator(int(sim.opt.integrator)).name,
            "torque_limit": [float(x) for x in model.robot.torque_limit],
        },
        "ball_model": {"radius": settings.ball_radius, "mass": settings.ball_mass},
        "catch_criterion": {
            "capture_radius": settings.capture_radius,
            "grip_time": settings.grip_time,
            "max_relative_speed": settings.max_relative_speed,
        },
        "steps": int(rollout.time.shape[0]),
        "result": summary._asdict(),
        "animation": ANIMATION_FILE,
        "renderer": renderer,
    }
