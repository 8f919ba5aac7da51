"""Checkpoints of a training run (one per generation) with corruption detection.

A checkpoint is an orbax ``CheckpointManager`` step named by the generation index. It holds two
items: ``state``, a pytree of numpy arrays (the database, the condition set, the generation), and
``meta``, JSON (the metrics history up to that generation and a SHA-256 checksum of ``state``).

Orbax writes a step into a temporary folder and renames it when complete, so a run killed during a
save leaves no half-written step behind. A step that is complete but damaged afterwards (a missing
or truncated file, flipped bytes) fails to restore or fails its checksum; ``restore_latest`` then
reports it and falls back to the previous step.
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

STATE, META = "state", "meta"


def _quiet_orbax() -> None:
    """Orbax logs every save at INFO through absl; a run's output is the progress bar."""
    for name in ("absl", "orbax", "orbax.checkpoint"):
        logging.getLogger(name).setLevel(logging.WARNING)


def open_manager(directory: str | os.PathLike, max_to_keep: int) -> ocp.CheckpointManager:
    """A synchronous manager over ``directory`` (created if missing), keeping ``max_to_keep``."""
    _quiet_orbax()
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, create=True, enable_async_checkpointing=False
    )
    return ocp.CheckpointManager(Path(directory).absolute(), options=options)


def tree_checksum(tree: Any) -> str:
    """SHA-256 over every leaf's path, dtype, shape and bytes (leaves in pytree order)."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(jax.tree_util.keystr(path).encode())
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_checkpoint(manager: ocp.CheckpointManager, step: int, state: Any, meta: dict) -> None:
    """Save ``state`` (pytree of arrays) and ``meta`` (JSON-able) as ``step``; returns when on disk.

    The checksum of ``state`` is added to ``meta`` under ``"checksum"``.
    """
    state = jax.tree_util.tree_map(np.asarray, state)
    meta = {**meta, "checksum": tree_checksum(state)}
    manager.save(
        step,
        args=ocp.args.Composite(
            **{STATE: ocp.args.StandardSave(state), META: ocp.args.JsonSave(meta)}
        ),
        force=True,
    )
    manager.wait_until_finished()


class Restored(NamedTuple):
    """A restored checkpoint: its step, state (numpy pytree shaped like the template), meta."""

    step: int
    state: Any
    meta: dict


def restore_latest(
    manager: ocp.CheckpointManager, template: Any
) -> tuple[Restored | None, list[str]]:
    """The newest step that restores and passes its checksum, newest first.

    ``template``: a pytree of numpy arrays with the expected structure, shapes and dtypes.
    Returns ``(restored or None, problems)``; ``problems`` has one line per skipped step.
    """
    manager.reload()
    problems = []
    for step in sorted(manager.all_steps(), reverse=True):
        try:
            out = manager.restore(
                step,
                args=ocp.args.Composite(
                    **{STATE: ocp.args.StandardRestore(template), META: ocp.args.JsonRestore()}
                ),
            )
            state = jax.tree_util.tree_map(np.asarray, out[STATE])
            meta = dict(out[META])
        except Exception as e:  # orbax/tensorstore raise many kinds: all mean unusable
            problems.append(f"checkpoint {step}: unreadable ({type(e).__name__}: {_first_line(e)})")
            continue
        problem = _check_restored(state, template, meta)
        if problem:
            problems.append(f"checkpoint {step}: {problem}")
            continue
        return Restored(step, state, meta), problems
    return None, problems


def _check_restored(state, template, meta) -> str | None:
    if _paths(state) != _paths(template):
        return "structure differs from this run's state"
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(template)):
        if a.shape != b.shape or a.dtype != b.dtype:
            return f"array {a.dtype}{a.shape} where {b.dtype}{b.shape} was expected"
    if meta.get("checksum") != tree_checksum(state):
        return "checksum mismatch (the data changed after it was written)"
    return None


def _paths(tree) -> list[str]:
    return [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]


def _first_line(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return text[0][:200] if text else ""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to a temporary file beside ``path``, fsync, then ``os.replace`` onto it."""
    import tempfile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual file mode
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """`atomic_write_bytes` of UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"))
