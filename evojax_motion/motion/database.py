"""The movement primitive database (paper sec. 2 and 4.1; DESIGN.md step 2).

A fixed-capacity pytree of arrays; missing entries are masked by ``valid``, never removed, so shapes
stay static under jit. Saved as ``.npz`` (``allow_pickle=False``) with these keys:

| key | shape | unit / meaning |
|---|---|---|
| ``q`` | (N, T, J) | joint angles [rad] at normalised time ``s_i = i/(T-1)`` (see below) |
| ``duration`` | (N,) | [s] |
| ``condition`` | (N, 3) | hand (end-effector site) position at the end of the motion [m] |
| ``cost`` | (N,) | ``0.5 * int |tau|^2 dt`` [N^2 m^2 s] (paper eq. 5) |
| ``origin`` | (N,) | 0 = human demonstration, 1 = evolved |
| ``valid`` | (N,) | entry holds a primitive |
| ``generation`` | (N,) | generation that produced it (0 for humans) |
| ``joint_names`` | (J,) | controlled joints, in column order |
| ``robot_name``, ``robot_mjcf``, ``site_name`` | () | the robot the trajectories belong to |
| ``synthetic`` | () | True when the human demonstrations are synthetic |
| ``description`` | () | where the demonstrations come from |
| ``format_version`` | () | file format version |

Continuous joints (no range) are written and read on the rest branch (`on_robot_branch`).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evojax_motion.errors import UserError

HUMAN, EVOLVED = 0, 1
FORMAT_VERSION = 1
_ARRAY_KEYS = ("q", "duration", "condition", "cost", "origin", "valid", "generation")
_META_KEYS = ("joint_names", "robot_name", "robot_mjcf", "site_name", "synthetic", "description")


class Database(NamedTuple):
    """Primitive database. Leading axis N = capacity."""

    q: np.ndarray  # (N, T, J) float32
    duration: np.ndarray  # (N,) float32
    condition: np.ndarray  # (N, 3) float32
    cost: np.ndarray  # (N,) float32
    origin: np.ndarray  # (N,) int32
    valid: np.ndarray  # (N,) bool
    generation: np.ndarray  # (N,) int32


@dataclass(frozen=True)
class DatabaseMeta:
    """What the arrays belong to: the robot (by name and full MJCF) and the data's provenance."""

    robot_name: str
    mjcf: str
    joint_names: tuple[str, ...]
    site_name: str
    synthetic: bool
    description: str = ""

    @classmethod
    def of_robot(cls, robot, synthetic: bool, description: str) -> DatabaseMeta:
        """The meta of data recorded for ``robot`` (a `model.robot.Robot`)."""
        return cls(
            robot_name=robot.name,
            mjcf=robot.mjcf,
            joint_names=tuple(robot.joint_names),
            site_name=robot.site_name,
            synthetic=synthetic,
            description=description,
        )


def make_database(q, duration, condition, cost=None, capacity: int | None = None) -> Database:
    """Database of human primitives ``q (n, T, J)`` padded to ``capacity`` with empty evolved slots.

    Empty slots are ``valid=False``, ``origin=EVOLVED``, ``cost=inf``, zero trajectories.
    """
    q = np.asarray(q, np.float32)
    n = q.shape[0]
    capacity = n if capacity is None else capacity
    if capacity < n:
        raise ValueError(f"capacity {capacity} < number of primitives {n}")
    pad = capacity - n
    cost = np.full(n, np.nan, np.float32) if cost is None else np.asarray(cost, np.float32)

    def padded(a, fill, dtype):
        a = np.asarray(a, dtype)
        filler = np.full((pad, *a.shape[1:]), fill, dtype)
        return np.concatenate([a, filler], axis=0)

    return Database(
        q=padded(q, 0.0, np.float32),
        duration=padded(duration, 1.0, np.float32),
        condition=padded(condition, 0.0, np.float32),
        cost=padded(cost, np.inf, np.float32),
        origin=np.concatenate([np.full(n, HUMAN, np.int32), np.full(pad, EVOLVED, np.int32)]),
        valid=np.concatenate([np.ones(n, bool), np.zeros(pad, bool)]),
        generation=np.zeros(capacity, np.int32),
    )


def human_mask(db: Database) -> np.ndarray:
    """``(N,)`` valid human demonstrations."""
    return np.asarray(db.valid) & (np.asarray(db.origin) == HUMAN)


def count_human(db: Database) -> int:
    """Rows of human origin: the human part of an evolving database comes first, so its evolved
    slots start at this index."""
    return int(np.sum(np.asarray(db.origin) == HUMAN))


def humans_only(db: Database) -> Database:
    """The same arrays with every evolved entry masked out (``valid=False``)."""
    return db._replace(valid=human_mask(db))


def nonfinite_rows(db: Database) -> np.ndarray:
    """Indices of the valid entries with NaN/inf in ``q``, ``condition`` or ``cost``, or a
    duration that is not a finite number > 0: what a numerical failure leaves behind."""
    q, cond = np.asarray(db.q), np.asarray(db.condition)
    dur, cost = np.asarray(db.duration), np.asarray(db.cost)
    finite = np.isfinite(q).all(axis=(1, 2)) & np.isfinite(cond).all(axis=1) & np.isfinite(cost)
    finite &= np.isfinite(dur) & (dur > 0)
    return np.flatnonzero(np.asarray(db.valid) & ~finite)


def on_robot_branch(db: Database, meta: DatabaseMeta) -> Database:
    """``db`` with the continuous joints of ``meta``'s robot on its rest branch
    (`motion.angles.on_rest_branch`: each trajectory unwrapped along time, its mean within pi of the
    rest posture), so that averages and distances over joint angles compare like with like.
    Unchanged where the robot has no continuous joint, or its stored MJCF does not build a
    robot with these joints (then no joint is known to be continuous)."""
    from evojax_motion.model.robot import robot_from_mjcf_text
    from evojax_motion.motion.angles import on_rest_branch

    try:
        robot = robot_from_mjcf_text(meta.robot_name, meta.mjcf, meta.joint_names, meta.site_name)
    except UserError:
        return db
    if not robot.continuous.any():
        return db
    return db._replace(q=on_rest_branch(np.asarray(db.q), robot.rest, robot.continuous))


def save_database(path: str | os.PathLike, db: Database, meta: DatabaseMeta) -> Path:
    """Write ``db`` and ``meta`` to ``path`` (.npz) atomically: a crash keeps the old file.
    Continuous joints are written on the rest branch (`on_robot_branch`)."""
    path = Path(path)
    db = on_robot_branch(db, meta)
    arrays = {k: np.asarray(v) for k, v in db._asdict().items()}
    arrays.update(
        joint_names=np.asarray(meta.joint_names, dtype=str),
        robot_name=np.asarray(meta.robot_name),
        robot_mjcf=np.asarray(meta.mjcf),
        site_name=np.asarray(meta.site_name),
        synthetic=np.asarray(meta.synthetic),
        description=np.asarray(meta.description),
        format_version=np.asarray(FORMAT_VERSION),
    )
    return atomic_savez(path, arrays)


def atomic_savez(path: Path, arrays: dict) -> Path:
    """``np.savez`` to a temporary file in the same folder, then ``os.replace`` onto ``path``
    (`run.atomic.atomic_write`: a failed write names ``path`` and leaves no temporary file)."""
    from evojax_motion.run.atomic import atomic_write

    return atomic_write(path, lambda f: np.savez(f, **arrays))


def _read_npz(path: Path, keys: tuple[str, ...] | None = None) -> dict:
    """The arrays ``keys`` (default: all) of the ``.npz`` ``path``, read without pickles. Raises
    ``UserError`` naming the file when it is missing, unreadable or lacks one of ``keys``."""
    if not path.is_file():
        raise UserError(f"{path}: database file not found")
    try:
        with np.load(path, allow_pickle=False) as f:
            missing = [k for k in keys or () if k not in f.files]
            if missing:
                raise UserError(
                    f"{path}: missing keys {missing}; expected an evojax-motion database"
                )
            return {k: f[k] for k in (f.files if keys is None else keys)}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise UserError(f"{path}: not a readable .npz database ({e})") from None


def _meta_from(data: dict) -> DatabaseMeta:
    return DatabaseMeta(
        robot_name=str(data["robot_name"]),
        mjcf=str(data["robot_mjcf"]),
        joint_names=tuple(str(x) for x in np.atleast_1d(data["joint_names"])),
        site_name=str(data["site_name"]),
        synthetic=bool(data["synthetic"]),
        description=str(data["description"]),
    )


def read_database_meta(path: str | os.PathLike) -> DatabaseMeta:
    """The `DatabaseMeta` of a database file, without reading its arrays (which robot it is of).
    Raises ``UserError`` naming the file when it is not a readable database."""
    return _meta_from(_read_npz(Path(path), _META_KEYS))


def database_shape(path: str | os.PathLike) -> tuple[int, ...]:
    """The shape ``(N, T, J)`` of a database file's ``q``, read from its header alone (no array
    is loaded). Raises ``UserError`` naming the file when it is not a readable database."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: database file not found")
    try:
        with zipfile.ZipFile(path) as z, z.open("q.npy") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, _ = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, _ = np.lib.format.read_array_header_2_0(f)
    except KeyError:
        raise UserError(f"{path}: missing keys ['q']; expected an evojax-motion database") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise UserError(f"{path}: not a readable .npz database ({e})") from None
    if len(shape) != 3:
        raise UserError(f"{path}: q must have shape (N, T, J), got {shape}")
    return tuple(int(x) for x in shape)


def load_database(path: str | os.PathLike) -> tuple[Database, DatabaseMeta]:
    """Read and validate a database file. Raises ``UserError`` naming the file and the problem.
    Continuous joints come back on the rest branch (`on_robot_branch`), also from files written
    before databases were stored that way."""
    path = Path(path)
    data = _read_npz(path)
    missing = [k for k in (*_ARRAY_KEYS, *_META_KEYS) if k not in data]
    if missing:
        raise UserError(f"{path}: missing keys {missing}; expected an evojax-motion database")
    db = Database(
        q=data["q"].astype(np.float32),
        duration=data["duration"].astype(np.float32),
        condition=data["condition"].astype(np.float32),
        cost=data["cost"].astype(np.float32),
        origin=data["origin"].astype(np.int32),
        valid=data["valid"].astype(bool),
        generation=data["generation"].astype(np.int32),
    )
    meta = _meta_from(data)
    validate_database(db, meta, str(path))
    return on_robot_branch(db, meta), meta


def validate_database(db: Database, meta: DatabaseMeta, where: str = "database") -> None:
    """Shapes agree, valid entries are finite with positive durations. Raises ``UserError``."""
    if db.q.ndim != 3:
        raise UserError(f"{where}: q must have shape (N, T, J), got {db.q.shape}")
    n, _, j = db.q.shape
    if len(meta.joint_names) != j:
        raise UserError(f"{where}: {len(meta.joint_names)} joint_names but q has {j} joint columns")
    expected = {"duration": (n,), "condition": (n, 3), "cost": (n,), "origin": (n,)}
    expected.update(valid=(n,), generation=(n,))
    for key, shape in expected.items():
        if getattr(db, key).shape != shape:
            raise UserError(f"{where}: {key} must have shape {shape}, got {getattr(db, key).shape}")
    v = db.valid
    if not v.any():
        raise UserError(f"{where}: holds no valid primitive")
    bad = ~np.isfinite(db.q[v]).all(axis=(1, 2)) | ~np.isfinite(db.condition[v]).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(v)[np.flatnonzero(bad)[0]])
        raise UserError(f"{where}: primitive {first} has NaN/inf in q or condition")
    if not (db.duration[v] > 0).all():
        raise UserError(f"{where}: every duration must be > 0 s")
    if not np.isin(db.origin, (HUMAN, EVOLVED)).all():
        raise UserError(f"{where}: origin must be 0 (human) or 1 (evolved)")
