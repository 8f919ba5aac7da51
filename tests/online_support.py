"""Shared, cached set-up of the online tests (test_online, test_online_limits, test_catching,
test_simulate, test_export).

A small synthetic database is built in numpy with C MuJoCo's forward kinematics
(`online.generation.final_hand`, no XLA compile), and the jitted online functions are built once
per test process (`functools.cache`), so the test modules share their compilations. The command
line runs in-process (`run_cli`) on those compilations (`prepare_cli`, `cli_session`).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evojax_motion.model.dynamics import Dynamics, make_dynamics
from evojax_motion.model.robot import Robot, load_robot
from evojax_motion.model.robot import mj_inverse_torques as reference_torques
from evojax_motion.motion.database import Database, DatabaseMeta, make_database, save_database
from evojax_motion.motion.timegrid import TimeGrid, make_time_grid
from evojax_motion.online.generation import final_hand, make_online_generator, online_database
from evojax_motion.settings.compiler import BasisSettings
from evojax_motion.settings.online import OnlineSettings

SAMPLES = 32  # T: small for compile time, large enough for the BC algebra (compile_interp)
N_PRIMITIVES = 60
BASIS = BasisSettings(radius=0.15, neighbours=8)
SETTINGS = OnlineSettings()


def synthetic_database(robot: Robot, n: int, samples: int, seed: int) -> Database:
    """``n`` rest-to-rest reaching primitives: minimum-jerk joint paths with per-joint time warps
    (so the neighbours' PCA has several components) from ``robot.rest`` to random final postures
    around a forward reach, well inside the joint limits."""
    rng = np.random.default_rng(seed)
    j = robot.n_joints
    lo, hi = robot.lower, robot.upper
    span = hi - lo
    centre = np.clip(
        robot.rest + 0.35 * span * np.r_[0.0, 1.0, 0.3, 0.0, 0.8, 0.0, 0.0][:j], lo, hi
    )
    final = centre + rng.normal(0.0, 0.08, (n, j)) * span
    final = np.clip(final, lo + 0.1 * span, hi - 0.1 * span)
    s = np.linspace(0.0, 1.0, samples)
    warp = rng.uniform(-0.3, 0.3, (n, 1, j))
    w = s[None, :, None] + warp * s[None, :, None] * (1.0 - s[None, :, None])
    shape = w**3 * (10.0 - 15.0 * w + 6.0 * w**2)
    q = robot.rest[None, None, :] + (final - robot.rest)[:, None, :] * shape
    duration = rng.uniform(0.5, 0.9, n)
    return make_database(q, duration, final_hand(robot, final))


class Env(NamedTuple):
    robot: Robot
    dyn: Dynamics
    db: Database
    db_device: Database
    meta: DatabaseMeta
    grid: TimeGrid
    generate: object


@functools.cache
def online_env() -> Env:
    """The robot, its float32 RNEA dynamics, a 60-primitive database and the jitted query."""
    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot)
    db = synthetic_database(robot, N_PRIMITIVES, SAMPLES, seed=0)
    meta = DatabaseMeta(
        robot.name, robot.mjcf, robot.joint_names, robot.site_name, True, "online tests"
    )
    grid = make_time_grid(SAMPLES)
    generate = make_online_generator(robot, dyn, grid, BASIS, SETTINGS)
    return Env(robot, dyn, db, online_database(db), meta, grid, generate)


@functools.cache
def reach_checker():
    """The jitted `online.reach.make_reach_checker` of `online_env`."""
    from evojax_motion.online.reach import make_reach_checker

    env = online_env()
    return make_reach_checker(env.robot, env.dyn, BASIS, SETTINGS)


CATCH_KW = {"horizon": 1.2, "samples": 121}  # = the CLI's settings for ``--horizon 1.2``


@functools.cache
def catcher():
    """``(settings, jitted catcher)`` of `online_env` (`online.catching.make_catcher`)."""
    from evojax_motion.online.catching import make_catcher
    from evojax_motion.settings.online import CatchSettings

    env = online_env()
    catch = CatchSettings(**CATCH_KW)
    return catch, make_catcher(env.robot, env.dyn, env.grid, BASIS, SETTINGS, catch)


def cli_session(env: Env, db_path) -> tuple:
    """What ``cli.online._session`` returns for ``db_path``, built from the cached functions, so
    CLI tests reuse the compilations (the loader itself is tested separately)."""
    from evojax_motion.cli import online as online_cli
    from evojax_motion.online.generation import OnlineModel

    model = OnlineModel(
        robot=env.robot,
        dyn=env.dyn,
        db=env.db,
        db_device=env.db_device,
        meta=env.meta,
        grid=env.grid,
        basis_settings=BASIS,
        settings=SETTINGS,
        source=str(db_path),
        settings_source="tests",
    )
    opened = (model, env.generate, reach_checker())
    catch, fn = catcher()
    online_cli._CATCHERS[(id(model), catch)] = fn
    return opened


def save_env_database(directory: Path, env: Env) -> Path:
    """`online_env`'s database written to ``directory/db.npz`` (the CLI's ``--db``)."""
    path = Path(directory) / "db.npz"
    save_database(path, env.db, env.meta)
    return path


def prepare_cli(monkeypatch, opened: tuple | None = None) -> tuple | None:
    """Set up in-process CLI runs for one test: no persistent compilation cache
    (``EVOJAX_MOTION_JAX_CACHE=off``) and, if given, ``opened`` (e.g. `cli_session`'s) in place
    of what ``cli.online._session`` would load. Returns ``opened``."""
    from evojax_motion.cli import online as online_cli

    monkeypatch.setenv("EVOJAX_MOTION_JAX_CACHE", "off")
    if opened is not None:
        monkeypatch.setattr(online_cli, "_session", lambda *args: opened)
    return opened


def run_cli(argv) -> int:
    """``evojax-motion <argv>`` in-process with the online subcommands (``generate``, ``catch``,
    ``simulate``); the exit status. A `UserError` prints ``error: <msg>`` on stdout and gives 2."""
    from evojax_motion.cli.entry import _Parser
    from evojax_motion.cli.online import add_online_parsers
    from evojax_motion.cli.simulate import add_simulate_parser
    from evojax_motion.errors import UserError

    parser = _Parser(prog="evojax-motion")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    add_online_parsers(sub)
    add_simulate_parser(sub)
    try:
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"error: {e}")
        return 2


def query(env: Env, targets, duration=None, q_start=None):
    """Run the cached generator on ``targets (C, 3)``; numpy `OnlineResult`."""
    from evojax_motion.online.generation import check_query, to_numpy

    t, d, q0 = check_query(env.robot, targets, duration, q_start)
    return to_numpy(env.generate(env.db_device, t, d, q0))


def mj_inverse_torques(robot: Robot, q, qd, qdd) -> np.ndarray:
    """C MuJoCo ``mj_inverse`` (float64) of the controlled joints, rows ``(T, J)`` -> ``(T, J)``."""
    return reference_torques(robot, q, qd, qdd)
