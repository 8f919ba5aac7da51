"""Glue from a validated ``Config`` to the pipeline's objects (robot, dynamics, demonstrations),
and the checks across its sections that a run makes before any work (`check_settings`).

The CLI and the training run both start here, so one config always yields the same robot and the
same demonstration database.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import Dynamics, make_dynamics
from evojax_motion.model.robot import Robot, robot_from_config
from evojax_motion.motion.database import (
    Database,
    DatabaseMeta,
    human_mask,
    load_database,
    save_database,
)
from evojax_motion.run.memory import check_demos_memory
from evojax_motion.run.memory import check_run_memory as check_run_memory  # train's hook
from evojax_motion.settings import Config, config_to_dict


def make_robot(cfg: Config) -> Robot:
    """The robot named by ``cfg.robot`` (a shipped name, or an MJCF path + joints + site)."""
    return robot_from_config(cfg.robot)


def make_robot_dynamics(cfg: Config) -> tuple[Robot, Dynamics]:
    robot = make_robot(cfg)
    return robot, make_dynamics(robot, backend=cfg.dynamics)


def check_database_matches_robot(meta: DatabaseMeta, robot: Robot, where: str) -> None:
    """Refuse a database recorded for another robot: joint names or count differ, or its hand
    positions (conditions) are of another end effector."""
    if tuple(meta.joint_names) != tuple(robot.joint_names):
        raise UserError(
            f"{where}: database joints {list(meta.joint_names)} do not match robot "
            f"{robot.name!r} joints {list(robot.joint_names)}"
        )
    if meta.site_name != robot.site_name:
        raise UserError(
            f"{where}: its hand positions are of end effector {meta.site_name!r}; the config's "
            f"robot has {robot.site_name!r} (robot.end_effector): import the recordings for it"
        )


def check_settings(cfg: Config) -> None:
    """Checks across config sections that need no data, before anything is computed or written.

    Raises ``UserError`` naming the field: ``train.plot_condition`` beyond the conditions,
    ``parallel.devices`` beyond the devices JAX sees, ``compiler.n_components`` not below the
    samples T of synthetic demonstrations (a ``demos_file``'s T is checked once it is read).
    """
    from evojax_motion.evolution.sharding import resolve_devices

    evo, tr = cfg.evolution, cfg.train
    if tr.plot_condition is not None and tr.plot_condition >= evo.conditions:
        raise UserError(
            f"train.plot_condition: expected < evolution.conditions ({evo.conditions}), "
            f"got {tr.plot_condition}"
        )
    resolve_devices(cfg.parallel.devices)
    if cfg.demos_file is None:
        check_samples(cfg, cfg.demos.samples)


def check_samples(cfg: Config, samples: int) -> None:
    """The basis of eq. 3 needs fewer components than time samples (K + 1 <= T)."""
    k = cfg.compiler.n_components
    if k >= samples:
        where = cfg.demos_file if cfg.demos_file is not None else "demos.samples"
        raise UserError(
            f"compiler.n_components: expected < the {samples} time samples of the "
            f"demonstrations ({where}), got {k}"
        )


def _model_outline(mjcf: str) -> tuple[str, tuple[str, ...]] | None:
    """``(model name, joint names)`` of MJCF text; None where it is not XML."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(mjcf)
    except ET.ParseError:
        return None
    joints = tuple(j.get("name", "") for j in root.iter("joint"))
    return root.get("model", ""), joints


def check_database_of_run(path: str | Path) -> None:
    """Refuse a database file inside a run folder (``robot.xml`` beside it, `train`) that was
    recorded for another robot than that folder's: its stored joint names must be joints of
    ``robot.xml``, and both models must have the same name and joints. Reads the database's meta
    only (`motion.database.read_database_meta`); nothing where there is no ``robot.xml``. Raises
    `UserError` naming the database, its robot and joints, and ``robot.xml``."""
    from evojax_motion.motion.database import read_database_meta
    from evojax_motion.run.training import ROBOT_FILE

    path = Path(path)
    robot_xml = path.parent / ROBOT_FILE
    if not robot_xml.is_file():
        return
    try:
        run_text = robot_xml.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{robot_xml}: unreadable robot model ({type(e).__name__})") from None
    meta = read_database_meta(path)
    if run_text.strip() == meta.mjcf.strip():
        return
    ours, theirs = _model_outline(meta.mjcf), _model_outline(run_text)
    if theirs is None:
        raise UserError(f"{robot_xml}: not an MJCF model (XML); expected the run's robot")
    name, run_joints = theirs
    if ours is not None and ours == theirs and set(meta.joint_names) <= set(run_joints):
        return  # the same model, written differently
    raise UserError(
        f"{path}: a database of robot {meta.robot_name!r} (joints {list(meta.joint_names)}), "
        f"but {robot_xml} beside it is robot {name!r} (joints {list(run_joints)}); expected "
        "the run's own database"
    )


def cache_parts(cfg: Config, robot: Robot, dyn: Dynamics) -> dict:
    """What a run's compiled programs depend on besides their arguments, for the traced-program
    cache (`run.cache.compile_traced`): the config sections that shape them (robot,
    dynamics, demos, basis, compiler, evolution without ``generations``), the RNEA layout
    ``dyn`` traces (`model.dynamics.training_layout` picks it) and the digest of the robot's
    compiled MuJoCo model."""
    from evojax_motion.run.cache import model_digest

    sections = config_to_dict(cfg)
    sections["evolution"].pop("generations")  # how often the step runs, not what it is
    names = ("robot", "dynamics", "demos", "basis", "compiler", "evolution")
    return {
        "config": {k: sections[k] for k in names},
        "layout": dyn.form,
        "model": model_digest(robot.mj_model),
    }


def build_demonstrations(cfg: Config) -> tuple[Database, DatabaseMeta, dict]:
    """The human demonstration database of a config: ``demos_file`` if set, else synthetic ones.

    Returns ``(db, meta, report)``; ``report`` is the summary printed by the CLI.
    """
    from evojax_motion.demonstrations.synthetic import summarize_demonstrations

    robot, dyn = make_robot_dynamics(cfg)
    if cfg.demos_file is None:
        check_demos_memory(cfg, robot)  # sizes that cannot fit: refused before any work
    db, meta = demonstrations(cfg, robot, dyn)
    return db, meta, summarize_demonstrations(db, robot)


def kept_demonstrations(cache: Any):
    """Where `demonstrations` keeps the synthesised demonstrations of a run with `cache_parts`
    ``cache`` (None: not kept)."""
    from evojax_motion.run.cache import result_path

    return None if cache is None else result_path({"result": "demonstrations", "parts": cache})


def synthesises(cfg: Config, robot: Robot, dyn: Dynamics) -> bool:
    """Whether `demonstrations` will synthesise (no ``demos_file``, none shipped or kept for
    ``cfg`` and ``dyn``)."""
    from evojax_motion.demonstrations.shipped import shipped_path

    if cfg.demos_file is not None or shipped_path(cfg, robot).is_file():
        return False
    path = kept_demonstrations(cache_parts(cfg, robot, dyn))
    return path is None or not path.is_file()


def read_demonstrations_file(cfg: Config, robot: Robot) -> tuple[Database, DatabaseMeta]:
    """``(db, meta)``: the valid human rows of ``cfg.demos_file``, a database of ``robot``'s
    joints and end effector (`load_database`'s checks; `UserError` naming the file otherwise).
    ``meta`` names ``robot`` (its MJCF, with the config's velocity limits): the run computes
    with that model, and the databases it writes keep it for the queries that read them."""
    path = cfg.demos_file
    if path is None:
        raise ValueError("read_demonstrations_file: the config has no demos_file")
    db, meta = load_database(path)
    check_database_matches_robot(meta, robot, path)
    keep = human_mask(db)
    ours = DatabaseMeta.of_robot(robot, meta.synthetic, meta.description)
    return Database(*(np.asarray(a)[keep] for a in db)), ours


def demonstrations(
    cfg: Config, robot: Robot, dyn: Dynamics, cache: Any = None, on_traced=None, costs=None
) -> tuple[Database, DatabaseMeta]:
    """``(db, meta)`` of `build_demonstrations` for the config's ``robot`` and ``dyn``, without
    the summary: the valid human rows only; those shipped for the config where there are
    (`demonstrations.shipped`). ``cache``: `cache_parts` of ``cfg``, to keep the
    synthesis's traced program and its result across processes while the compilation cache is
    on (`run.cache.result_path`; None: synthesised and compiled in this process only).
    ``on_traced``, ``costs``: see `demonstrations.synthetic.generate_demonstrations` (only where
    they are
    synthesised)."""
    from evojax_motion.demonstrations.shipped import shipped_demonstrations

    if cfg.demos_file is not None:
        return read_demonstrations_file(cfg, robot)
    shipped = shipped_demonstrations(cfg, robot)
    if shipped is not None:
        return shipped
    path = kept_demonstrations(cache)
    if path is not None and path.is_file():
        try:
            return load_database(path)
        except UserError as e:  # damaged: synthesise again (the result is the same)
            print(f"warning: cached demonstrations unreadable ({e}); synthesising", file=sys.stderr)
            path.unlink(missing_ok=True)
    db, meta = synthesise(cfg, robot, dyn, cache, on_traced, costs)
    if path is not None:
        try:
            save_database(path, db, meta)
        except OSError as e:  # a read-only cache: synthesised again next time
            print(f"warning: {path}: demonstrations not cached ({e})", file=sys.stderr)
    return db, meta


def synthesise(
    cfg: Config, robot: Robot, dyn: Dynamics, cache: Any = None, on_traced=None, costs=None
) -> tuple[Database, DatabaseMeta]:
    """``(db, meta)``: the synthetic demonstrations of ``cfg`` (`demonstrations`' arguments),
    synthesised here."""
    from evojax_motion.demonstrations.synthetic import generate_demonstrations

    key = jax.random.key(cfg.demos.seed)
    db, report = generate_demonstrations(robot, dyn, cfg.demos, key, cache, on_traced, costs)
    description = str(report.get("description", "synthetic human-like demonstrations"))
    return db, DatabaseMeta.of_robot(robot, synthetic=True, description=description)


def print_demo_summary(report: dict, path: Path | None = None) -> None:
    """Human-readable summary of a demonstration database (count, durations, region, margins)."""
    width = max(len(k) for k in report)
    for key, value in report.items():
        if isinstance(value, float):
            value = f"{value:.4g}"
        print(f"{key:<{width}}  {value}")
    if path is not None:
        print(f"{'written to':<{width}}  {path}")
