"""Synthetic demonstrations shipped with the package: the shipped configurations start without
synthesising.

Synthesis (`demonstrations.synthetic`) is deterministic: one config gives one database. For
the configurations in ``configs/`` its result is shipped under ``evojax_motion/data/demos/``,
one ``.npz`` per `demos_key`, so that a run of them reads its demonstrations instead of compiling
and simulating their trials (on 2 CPU cores 11.9 s of a cold ``train configs/catch_ball.yaml``'s
33.9 s went to that; `benchmarks/cold_start.py`). Any other config, robot model or package
without the file synthesises as before.

The key holds everything a synthesis depends on: the config's ``robot``, ``dynamics`` and
``demos`` sections and the robot's MJCF text. `tests/demonstrations/test_shipped.py` synthesises
each shipped database again and compares, so a change of the synthesis that leaves a file stale
fails the tests. To write them again::

    python -m evojax_motion.demonstrations.shipped configs/catch_ball.yaml configs/tiny.yaml ...
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

from evojax_motion.model.robot import Robot
from evojax_motion.motion.database import Database, DatabaseMeta, load_database
from evojax_motion.settings import Config, config_to_dict

SHIPPED_DIR = Path(__file__).resolve().parents[1] / "data" / "demos"


def demos_key(cfg: Config, robot: Robot) -> str:
    """sha256 of what ``cfg``'s synthetic demonstrations depend on (module docstring)."""
    sections = config_to_dict(cfg)
    record = {
        "robot": sections["robot"],
        "dynamics": sections["dynamics"],
        "demos": sections["demos"],
        "mjcf": hashlib.sha256(robot.mjcf.encode()).hexdigest(),
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def shipped_path(cfg: Config, robot: Robot) -> Path:
    """Where the shipped demonstrations of ``cfg`` are (or would be)."""
    return SHIPPED_DIR / f"{demos_key(cfg, robot)}.npz"


def shipped_demonstrations(cfg: Config, robot: Robot) -> tuple[Database, DatabaseMeta] | None:
    """``(db, meta)`` shipped for ``cfg`` (synthetic configs only), else None."""
    if cfg.demos_file is not None:
        return None
    path = shipped_path(cfg, robot)
    return load_database(path) if path.is_file() else None


def write_shipped(config_paths: list[str]) -> list[Path]:
    """Synthesise the demonstrations of each config (compiled here, no cache) and write them
    where `shipped_demonstrations` finds them. Returns the files written."""
    from evojax_motion.motion.database import save_database
    from evojax_motion.run.workflow import make_robot_dynamics, synthesise
    from evojax_motion.settings import load_config

    written = []
    for cfg_path in config_paths:
        cfg = load_config(cfg_path)
        robot, dyn = make_robot_dynamics(cfg)
        db, meta = synthesise(cfg, robot, dyn)
        path = shipped_path(cfg, robot)
        path.parent.mkdir(parents=True, exist_ok=True)
        written.append(save_database(path, db, meta))
        print(f"{cfg_path}: {path.name}")
    return written


if __name__ == "__main__":
    write_shipped(sys.argv[1:])
