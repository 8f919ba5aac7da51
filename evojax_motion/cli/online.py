"""The online subcommands of ``evojax-motion``: ``generate`` and ``catch`` (paper sec. 3.2, 4).

    evojax-motion generate --db FILE --target X Y Z [--duration S] --out traj.csv
    evojax-motion catch --db FILE --ball PX PY PZ VX VY VZ --out traj.csv

``--db`` is a database ``.npz`` or a run directory (its ``db_final.npz``; the basis settings then
come from its ``config.yaml``). The output's format follows its suffix or ``--format``
(`export`). An unreachable target or an uncatchable ball is a `UserError` (one line ``error:
...``, exit status 2) that says how far the reachable region is; ``--nearest`` takes the nearest
reachable point instead. The hand (forward kinematics of the written final posture; for a catch, at
the catch time) must end within ``--tolerance`` mm (default 5) of the target, else exit 2 with
the miss, where the hand is and the nearest reachable point, or with ``--nearest`` a motion to
that point (the output says so). Nothing is written unless the motion is finite and inside the
joint, velocity and torque limits: a motion too fast for them is slowed down (`online`, time
scaling; the summary says so), and one that no duration allowed can bring within them is a
`UserError` that names the joint, the speed or torque it needs against its limit, and when.

The lead's ``cli.entry.build_parser`` calls `add_online_parsers` on its subparsers.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import numpy as np

from evojax_motion.errors import UserError

DEFAULT_TOLERANCE_MM = 5.0  # the largest miss of the hand at the target a written motion may have


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", required=True, help="database .npz or run directory (db_final.npz)")
    p.add_argument("--out", required=True, help="trajectory file (.csv, .npz or .json)")
    p.add_argument("--format", choices=("csv", "npz", "json"), default=None)
    p.add_argument("--nearest", action="store_true", help="use the nearest reachable point")
    p.add_argument(
        "--tolerance",
        type=float,
        default=DEFAULT_TOLERANCE_MM,
        metavar="MM",
        help=f"largest miss of the hand at the target [mm] (default {DEFAULT_TOLERANCE_MM:g})",
    )
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    add_query_arguments(p)


def add_query_arguments(p: argparse.ArgumentParser) -> None:
    """``--dynamics`` and ``--device``: how a command's online queries are computed."""
    p.add_argument("--dynamics", choices=("rnea", "mjx"), default="rnea", help="torque backend")
    add_device_argument(p)


def add_device_argument(p: argparse.ArgumentParser) -> None:
    """``--device`` (`use_device`) of a command whose JAX work is a few one-off queries."""
    p.add_argument(
        "--device",
        choices=("cpu", "default"),
        default="cpu",
        help="where the queries run: the host's CPU (default; a query takes milliseconds, a "
        "GPU's start-up and compile take seconds) or JAX's default device",
    )


def add_online_parsers(subparsers) -> None:
    """Add ``generate`` and ``catch`` to an argparse subparsers object."""
    p = subparsers.add_parser(
        "generate", help="a motion to a hand target from a learned database (online process)"
    )
    _common(p)
    p.add_argument("--target", required=True, nargs=3, type=float, metavar=("X", "Y", "Z"))
    p.add_argument("--duration", type=float, default=None, help="[s]; default: neighbours'")
    p.add_argument(
        "--start", nargs="+", type=float, default=None, metavar="Q", help="start posture [rad]"
    )
    p.set_defaults(func=cmd_generate)

    p = subparsers.add_parser("catch", help="catch a thrown ball: plan the catch and the motion")
    _common(p)
    p.add_argument(
        "--ball",
        required=True,
        nargs=6,
        type=float,
        metavar=("PX", "PY", "PZ", "VX", "VY", "VZ"),
        help="release position [m] and velocity [m/s]",
    )
    p.add_argument("--drag", type=float, default=0.0, help="quadratic drag k [1/m] (0: none)")
    p.add_argument("--reaction", type=float, default=None, help="reaction time [s]")
    p.add_argument("--horizon", type=float, default=None, help="flight time examined [s]")
    p.set_defaults(func=cmd_catch)


def _tolerance(args) -> float:
    """``--tolerance`` [mm] -> [m]."""
    tol = args.tolerance
    if not (np.isfinite(tol) and tol > 0):
        raise UserError(f"--tolerance: expected a number > 0 [mm], got {tol:g}")
    return tol * 1e-3


def _miss(model, motion, i: int) -> tuple[np.ndarray, float]:
    """Where the written final posture of motion ``i`` puts the hand (``(3,)`` [m]) and how far
    that is from its target [m]."""
    from evojax_motion.online.generation import final_hand

    hand = final_hand(model.robot, motion.q[i, -1])[0]
    return hand, float(np.linalg.norm(hand - np.asarray(motion.target[i], np.float64)))


def _miss_line(model, motion, i: int, tol: float, at: str = "") -> str | None:
    """None when motion ``i`` ends within ``tol`` [m] of its target, else what misses and why."""
    hand, miss = _miss(model, motion, i)
    if miss <= tol:
        return None
    line = (
        f"the hand misses the target {_vec(motion.target[i])} m by {miss * 1e3:.1f} mm"
        f"{' ' + at if at else ''} (tolerance {tol * 1e3:g} mm): the final posture puts it at "
        f"{_vec(hand)} m"
    )
    excess = float(motion.limit_excess[i])
    if excess > 0:
        how = "minimum-jerk blend" if bool(motion.fallback[i]) else "null-space projection"
        line += (
            f"; plain interpolation exceeded the joint limits by {excess:.4f} rad and the {how} "
            "moved the motion off the target"
        )
    return line


def _check_out(args) -> str:
    from evojax_motion.run.export import resolve_format

    fmt = resolve_format(args.out, args.format)
    if Path(args.out).exists() and not args.force:
        raise UserError(f"{args.out}: already exists (pass --force to overwrite)")
    return fmt


def _vec(x) -> list[float]:
    return [round(float(v), 4) for v in np.asarray(x).ravel()]


def _print_table(rows: dict) -> None:
    width = max(len(k) for k in rows)
    for key, value in rows.items():
        print(f"{key:<{width}}  {value}")


def _write(args, fmt, model, motion, i: int, meta: dict, window: str = "") -> Path:
    from evojax_motion.online.explain import explain_unusable
    from evojax_motion.run.export import make_trajectory_data, write_trajectory

    missed = _miss_line(model, motion, i, _tolerance(args))
    if missed:
        raise UserError(f"{missed}; nothing written")
    if not bool(motion.ok[i]):
        why = explain_unusable(model.robot, motion, i, model.settings, window)
        raise UserError(f"{why}; nothing written")
    data = make_trajectory_data(
        motion.t[i],
        motion.q[i],
        motion.qd[i],
        motion.qdd[i],
        motion.tau[i],
        model.robot.joint_names,
        meta,
    )
    return write_trajectory(args.out, data, fmt)


def _motion_meta(model, motion, i: int) -> dict:
    from evojax_motion.online.explain import limit_meta

    return {
        "database": model.source,
        "robot": model.robot.name,
        "site": model.robot.site_name,
        "target": _vec(motion.target[i]),
        "duration": float(motion.duration[i]),
        "cost": float(motion.cost[i]),
        "hand_error": float(motion.hand_error[i]),
        "limit_excess_before_projection": float(motion.limit_excess[i]),
        "limit_fallback": bool(motion.fallback[i]),
        **limit_meta(motion, i),
    }


def _limits_line(motion, i: int) -> str:
    excess = float(motion.limit_excess[i])
    if excess <= 0:
        return "inside (plain interpolation was inside)"
    how = "minimum-jerk blend" if bool(motion.fallback[i]) else "null-space projection"
    return f"inside ({how}; plain interpolation exceeded them by {excess:.4f} rad)"


@functools.lru_cache(maxsize=4)
def _session(path: str, mtime_ns: int, backend: str):
    """The loaded model and its jitted functions, kept per database file and version: repeated
    commands in one process (tests, notebooks) do not recompile."""
    from evojax_motion.online.generation import (
        load_online_model,
        make_online_generator,
        program_parts,
    )
    from evojax_motion.online.reach import make_reach_checker

    model = load_online_model(path, backend=backend)
    args = (model.robot, model.dyn, model.basis_settings, model.settings)
    gen = make_online_generator(
        model.robot, model.dyn, model.grid, *args[2:], one_shot=True,
        cache_parts=program_parts(model),
    )  # fmt: skip
    return model, gen, make_reach_checker(*args)


def use_device(choice: str) -> None:
    """``--device``: with ``cpu``, make the host's CPU JAX's platform for this process; with
    ``default``, let a GPU backend take memory as the queries need it
    (`run.memory.take_gpu_memory_on_demand`). Either takes effect only where no JAX backend is
    started yet (the command line's own process); a process already computing on a GPU keeps
    it."""
    if choice == "cpu":
        import jax

        jax.config.update("jax_platforms", "cpu")
    else:
        from evojax_motion.run.memory import take_gpu_memory_on_demand

        take_gpu_memory_on_demand()


def _open(args):
    """The `_session` of ``--db``, on ``--device``, with the compile cache on."""
    from evojax_motion.online.generation import resolve_database_path
    from evojax_motion.run.cache import enable_compile_cache
    from evojax_motion.run.workflow import check_database_of_run

    use_device(args.device)  # before anything starts a JAX backend
    enable_compile_cache()
    path = resolve_database_path(args.db)
    if not path.is_file():
        raise UserError(f"{path}: database file not found")
    check_database_of_run(path)
    return _session(str(path.resolve()), path.stat().st_mtime_ns, args.dynamics)


def _generate_one(opened, target, duration, q_start):
    from evojax_motion.online.generation import check_query, to_numpy

    model, gen, _ = opened
    targets, dur, q0 = check_query(model.robot, target, duration, q_start)
    return to_numpy(gen(model.db_device, targets, dur, q0))


def cmd_generate(args) -> int:
    """``evojax-motion generate``: one motion to ``--target``; exit 0, or `UserError`."""
    from evojax_motion.online.explain import describe_limits
    from evojax_motion.online.reach import nearest_reachable

    fmt = _check_out(args)
    opened = _open(args)
    model, _, check = opened
    target = np.asarray(args.target, np.float32)
    tol = _tolerance(args)
    motion = _generate_one(opened, target, args.duration, args.start)
    note = None
    missed = _miss_line(model, motion, 0, tol)
    if not bool(motion.reachable[0]) or missed:
        point, dist = nearest_reachable(check, model.db_device, target)
        nearest = f"the nearest reachable point is {_vec(point)} m, {dist:.3f} m away"
        if bool(motion.reachable[0]):
            where = f"{missed}; {nearest}"
        else:
            _, miss = _miss(model, motion, 0)
            if miss <= tol:  # the arm reaches it; the database has too few motions near it
                where = (
                    f"target {_vec(target)} m is outside the database's region: "
                    f"{int(motion.n_inside[0])} valid motions within basis.radius of it "
                    f"({model.settings_source}), {float(motion.region_gap[0]) * 1e3:.0f} mm "
                    f"too far for the neighbours the query needs: {nearest}"
                )
            else:
                where = (
                    f"target {_vec(target)} m is outside the reachable region (the hand would "
                    f"miss it by {miss * 1e3:.1f} mm; tolerance {tol * 1e3:g} mm): {nearest}"
                )
        if not args.nearest:
            raise UserError(f"{where}; pass --nearest to use it; nothing written")
        note = f"{where}; using it (--nearest)"
        motion = _generate_one(opened, point, args.duration, args.start)
        if not bool(motion.reachable[0]):
            raise UserError(f"{where}, but it could not be reached either; nothing written")
    meta = _motion_meta(model, motion, 0)
    meta["requested_target"] = _vec(target)
    out = _write(args, fmt, model, motion, 0, meta)
    if note:
        print(f"note: {note}")
    given = args.duration is not None
    _print_table(
        {
            "target": f"{_vec(motion.target[0])} m",
            "duration": f"{float(motion.duration[0]):.3f} s"
            + ("" if given else " (neighbours' mean)"),
            "hand error": f"{float(motion.hand_error[0]) * 1e3:.3f} mm",
            "cost (eq. 5)": f"{float(motion.cost[0]):.4g} N^2 m^2 s",
            "peak |tau|": f"{float(np.abs(motion.tau[0]).max()):.3f} N m",
            "joint limits": _limits_line(motion, 0),
            **describe_limits(model.robot, motion, 0),
            "neighbours": f"{int(motion.n_inside[0])} within the radius ({model.settings_source})",
            "written to": f"{out} ({fmt})",
        }
    )
    return 0


def _catch_settings(args):
    import dataclasses

    from evojax_motion.settings.online import CatchSettings

    for flag, value in (("--drag", args.drag), ("--reaction", args.reaction)):
        if value is not None and not np.isfinite(value):
            raise UserError(f"{flag}: expected a finite number, got {value}")
    changes = {"drag": args.drag}
    if args.reaction is not None:
        changes["reaction_time"] = args.reaction
    if args.horizon is not None:
        changes["horizon"] = args.horizon
        steps = args.horizon / 0.01
        if np.isfinite(steps):  # else CatchSettings refuses the horizon itself
            changes["samples"] = max(2, round(steps) + 1)
    try:
        return dataclasses.replace(CatchSettings(), **changes)
    except ValueError as e:
        raise UserError(f"catch: {e}") from None


def cmd_catch(args) -> int:
    """``evojax-motion catch``: plan the catch of ``--ball`` and write the motion."""
    import jax

    from evojax_motion.online.catching import explain_plan, validate_ball
    from evojax_motion.online.explain import describe_limits
    from evojax_motion.online.reach import nearest_reachable

    fmt = _check_out(args)
    p0, v0 = validate_ball(args.ball)
    catch = _catch_settings(args)
    opened = _open(args)
    model = opened[0]
    catcher = _catcher(opened, catch)
    q0 = np.asarray(model.robot.rest, np.float32)[None]
    plan, motion = jax.device_get(catcher(model.db_device, p0, v0, q0))
    line = explain_plan(plan, 0)
    note = None
    tol = _tolerance(args)
    if not bool(plan.feasible[0]):
        if not args.nearest:
            raise UserError(f"{line}; pass --nearest to move toward the ball anyway")
        motion, note = _nearest_attempt(opened, catch, plan)
    else:
        at = f"at the catch time t = {float(plan.catch_time[0]):.3f} s"
        missed = _miss_line(model, motion, 0, tol, at)
        if missed:
            point, dist = nearest_reachable(opened[2], model.db_device, motion.target[0])
            where = f"{missed}; the nearest reachable point is {_vec(point)} m, {dist:.3f} m away"
            if not args.nearest:
                raise UserError(f"{where}; pass --nearest to use it; nothing written")
            plan = plan._replace(feasible=np.zeros_like(plan.feasible))
            motion = _retimed(opened, point, float(plan.catch_time[0]), motion)
            note = f"{where}; moving there instead (--nearest, not a catch)"
    meta = _motion_meta(model, motion, 0)
    meta.update(
        ball=_vec(np.concatenate([p0[0], v0[0]])),
        caught=bool(plan.feasible[0]),
        time_axis="seconds after release",
    )
    if bool(plan.feasible[0]):
        meta.update(
            catch_time=float(plan.catch_time[0]),
            time_margin=float(plan.time_margin[0]),
            depth=float(plan.depth[0]),
        )
    window = "between the reaction time and the ball's arrival" if note is None else ""
    out = _write(args, fmt, model, motion, 0, meta, window)
    print(line if note is None else f"note: {line}; {note}")
    _print_table(
        {
            "motion": f"{float(motion.t[0, 0]):.3f} -> {float(motion.t[0, -1]):.3f} s "
            "after release",
            "hand at": f"{_vec(motion.target[0])} m",
            "hand error": f"{float(motion.hand_error[0]) * 1e3:.3f} mm",
            "cost (eq. 5)": f"{float(motion.cost[0]):.4g} N^2 m^2 s",
            "joint limits": _limits_line(motion, 0),
            **describe_limits(model.robot, motion, 0),
            "written to": f"{out} ({fmt})",
        }
    )
    return 0


_CATCHERS: dict = {}


def _catcher(opened, catch):
    """The jitted catcher of an opened database and catch settings (kept, like `_session`)."""
    from evojax_motion.online.catching import make_catcher
    from evojax_motion.online.generation import program_parts

    key = (id(opened[0]), catch)
    if key not in _CATCHERS:
        model = opened[0]
        _CATCHERS[key] = make_catcher(
            model.robot, model.dyn, model.grid, model.basis_settings, model.settings, catch,
            one_shot=True, cache_parts=program_parts(model),
        )  # fmt: skip
    return _CATCHERS[key]


def _nearest_attempt(opened, catch, plan):
    """``--nearest`` for an uncatchable ball: move toward it as well as the arm can.

    Too early: to the reachable sample with the best time margin, as fast as allowed (arriving
    ``time_short`` late). Out of reach: to the reachable point nearest the ball's closest
    approach, timed to arrive then if possible. Returns ``(motion, note)``.
    """
    from evojax_motion.online.reach import nearest_reachable

    model, _, check = opened
    if bool(plan.passes_region[0]):
        k = int(plan.late_index[0])
        point = np.asarray(plan.ball[0, k], np.float32)
        d_nat = float(plan.natural_duration[0, k])
        note = f"moving to {_vec(point)} m as fast as allowed (not a catch)"
    else:
        k = int(plan.closest_index[0])
        point, dist = nearest_reachable(check, model.db_device, plan.ball[0, k])
        d_nat = _natural_duration(check, model, point)
        note = f"moving to the reachable point {_vec(point)} m, {dist:.3f} m from its path"
    t_ball = float(plan.times[0, k])
    duration = float(np.clip(t_ball - catch.reaction_time, d_nat / catch.speedup, d_nat))
    motion = _generate_one(opened, point, duration, None)
    if not bool(motion.reachable[0]):
        raise UserError(f"the nearest point {_vec(point)} m could not be reached; nothing written")
    start = max(catch.reaction_time, t_ball - float(motion.duration[0]))  # after time scaling
    return motion._replace(t=motion.t + start), note


def _retimed(opened, point, end: float, like):
    """A motion to ``point (3,)`` over the duration of motion ``like``, ending at ``end`` [s after
    release] (later if time scaling stretched it)."""
    motion = _generate_one(opened, np.asarray(point, np.float32), float(like.duration[0]), None)
    if not bool(motion.reachable[0]):
        raise UserError(f"the nearest point {_vec(point)} m could not be reached; nothing written")
    start = float(like.t[0, 0])
    return motion._replace(t=motion.t + start)


def _natural_duration(check, model, point) -> float:
    """The natural (neighbours' mean) duration at ``point (3,)`` [s]."""
    from evojax_motion.online.reach import check_points

    reach = check_points(check, model.db_device, np.asarray(point, np.float32)[None], 64)
    return float(reach.natural_duration[0])
