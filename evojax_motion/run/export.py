"""Trajectory files: what ``evojax-motion generate`` and ``catch`` write (paper sec. 3.2 output).

One motion per file, sampled on the primitive's time grid, in three formats:

- ``csv``: the meta first, one comment line ``# KEY: VALUE`` (VALUE in JSON) per entry (target,
  duration, margins...; ``numpy.loadtxt`` and ``pandas.read_csv(comment="#")`` skip them), then a
  header row, then one row per sample. Columns: ``t`` [s], then ``q_<joint>`` [rad]
  for every joint, then ``qd_<joint>`` [rad/s], ``qdd_<joint>`` [rad/s^2] and ``tau_<joint>``
  [N m] (blocks in that order, joints in the robot's column order). Floats are written with
  enough digits to read back bit for bit (9 significant for float32, 17 for float64).
- ``npz``: arrays ``t (T,)``, ``q, qd, qdd, tau (T, J)``, ``joint_names (J,)`` and ``meta_json``
  (a JSON string: target, duration, costs, margins...).
- ``json``: ``{"joint_names": [...], "t": [...], "q": [[...]], ..., "meta": {...}}``.

The torques are ``Dynamics.inverse(q, qd, qdd)`` of the written rows (MuJoCo's ``mj_inverse``
``qfrc_inverse`` for the controlled joints; ``tests/run/test_export.py`` recomputes them from the
file).
A trajectory with a NaN or inf is refused (`UserError`) and nothing is written: a file on disk is
always a usable motion. Writes are atomic (temporary file, then rename).
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evojax_motion.errors import UserError

FORMATS = ("csv", "npz", "json")
QUANTITIES = ("q", "qd", "qdd", "tau")  # column blocks after ``t``, in file order


class TrajectoryData(NamedTuple):
    """One motion. ``t (T,)`` [s]; ``q, qd, qdd, tau (T, J)``; ``joint_names (J,)``; ``meta``."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    joint_names: tuple[str, ...]
    meta: dict


def column_names(joint_names) -> list[str]:
    """CSV header: ``t``, then ``<quantity>_<joint>`` for each quantity block of `QUANTITIES`."""
    return ["t"] + [f"{quantity}_{name}" for quantity in QUANTITIES for name in joint_names]


def resolve_format(path: str | os.PathLike, fmt: str | None = None) -> str:
    """The file format: ``fmt`` if given (must agree with a known suffix), else from the suffix."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if fmt is None:
        if suffix not in FORMATS:
            raise UserError(
                f"{path}: cannot tell the format from the suffix {suffix!r}; expected one of "
                f"{', '.join('.' + f for f in FORMATS)} or --format {'|'.join(FORMATS)}"
            )
        return suffix
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {'|'.join(FORMATS)}, got {fmt!r}")
    if suffix in FORMATS and suffix != fmt:
        raise UserError(f"{path}: suffix .{suffix} contradicts --format {fmt}")
    return fmt


def make_trajectory_data(t, q, qd, qdd, tau, joint_names, meta=None) -> TrajectoryData:
    """Validated `TrajectoryData` (numpy arrays). Raises `UserError` on NaN/inf or bad shapes."""
    t = np.asarray(t)
    arrays = {name: np.asarray(a) for name, a in zip(QUANTITIES, (q, qd, qdd, tau))}
    names = tuple(str(n) for n in joint_names)
    if t.ndim != 1:
        raise UserError(f"trajectory.t: expected shape (T,), got {t.shape}")
    for name, a in arrays.items():
        if a.shape != (t.shape[0], len(names)):
            raise UserError(
                f"trajectory.{name}: expected shape ({t.shape[0]}, {len(names)}), got {a.shape}"
            )
    for name, a in {"t": t, **arrays}.items():
        if not np.isfinite(a).all():
            raise UserError(f"trajectory.{name}: contains NaN/inf; refusing to write it")
    return TrajectoryData(t=t, joint_names=names, meta=dict(meta or {}), **arrays)


def _float_format(*arrays) -> str:
    wide = any(np.asarray(a).dtype == np.float64 for a in arrays)
    return "%.17g" if wide else "%.9g"


def _csv_text(data: TrajectoryData) -> str:
    table = np.concatenate([data.t[:, None], data.q, data.qd, data.qdd, data.tau], axis=1)
    fmt = _float_format(data.t, data.q, data.qd, data.qdd, data.tau)
    buf = io.StringIO()
    for key, value in _json_safe(data.meta).items():
        buf.write(f"# {key}: {json.dumps(value, allow_nan=False)}\n")
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(column_names(data.joint_names))
    for row in table:
        writer.writerow([fmt % v for v in row])
    return buf.getvalue()


def _json_safe(x):
    """Meta values as plain JSON types (numpy scalars and arrays become floats and lists)."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
    if isinstance(x, np.generic):
        return _json_safe(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None  # JSON has no NaN; "unknown" reads better than an invalid file
    return x


def _json_text(data: TrajectoryData) -> str:
    doc = {
        "joint_names": list(data.joint_names),
        "t": data.t.tolist(),
        **{name: getattr(data, name).tolist() for name in QUANTITIES},
        "meta": _json_safe(data.meta),
    }
    return json.dumps(doc, indent=1, allow_nan=False)


def write_trajectory(
    path: str | os.PathLike,
    data: TrajectoryData,
    fmt: str | None = None,
) -> Path:
    """Write ``data`` to ``path`` in ``fmt`` (default: by suffix). Atomic; returns the path."""
    from evojax_motion.motion.database import atomic_savez
    from evojax_motion.run.atomic import atomic_write_text

    path = Path(path)
    fmt = resolve_format(path, fmt)
    data = make_trajectory_data(*data)  # re-validate: never write NaN
    if fmt == "csv":
        return atomic_write_text(path, _csv_text(data))
    if fmt == "json":
        return atomic_write_text(path, _json_text(data))
    arrays = {name: getattr(data, name) for name in ("t", *QUANTITIES)}
    arrays["joint_names"] = np.asarray(data.joint_names, dtype=str)
    arrays["meta_json"] = np.asarray(json.dumps(_json_safe(data.meta), allow_nan=False))
    return atomic_savez(path, arrays)


def read_trajectory(path: str | os.PathLike, fmt: str | None = None) -> TrajectoryData:
    """Read a file written by `write_trajectory` (float64 from CSV/JSON, as stored from npz)."""
    path = Path(path)
    fmt = resolve_format(path, fmt)
    if not path.is_file():
        raise UserError(f"{path}: trajectory file not found")
    if fmt == "npz":
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta_json"]))
            names = tuple(str(n) for n in f["joint_names"])
            return TrajectoryData(f["t"], f["q"], f["qd"], f["qdd"], f["tau"], names, meta)
    if fmt == "json":
        doc = json.loads(path.read_text())
        arrays = {k: np.asarray(doc[k], np.float64) for k in ("t", *QUANTITIES)}
        return TrajectoryData(
            **arrays, joint_names=tuple(doc["joint_names"]), meta=doc.get("meta", {})
        )
    with path.open(newline="") as f:
        lines = f.read().splitlines()
    meta = {}
    while lines and lines[0].startswith("#"):
        key, _, value = lines.pop(0)[1:].partition(":")
        try:
            meta[key.strip()] = json.loads(value)
        except ValueError:
            raise UserError(f"{path}: expected comment lines '# KEY: JSON', got {key!r}") from None
    rows = list(csv.reader(lines))
    header, body = rows[0], np.asarray(rows[1:], np.float64)
    if header[0] != "t" or (len(header) - 1) % len(QUANTITIES):
        raise UserError(f"{path}: expected a header 't, q_<joint>..., ...', got {header[:3]}...")
    j = (len(header) - 1) // len(QUANTITIES)
    names = tuple(h[2:] for h in header[1 : 1 + j])
    if header != column_names(names):
        raise UserError(f"{path}: header does not follow 't, q_*, qd_*, qdd_*, tau_*'")
    blocks = {name: body[:, 1 + i * j : 1 + (i + 1) * j] for i, name in enumerate(QUANTITIES)}
    return TrajectoryData(t=body[:, 0], **blocks, joint_names=names, meta=meta)
