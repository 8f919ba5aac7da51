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
import re
import sys
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

__all__ = [
    "Restored",
    "open_manager",
    "restore_latest",
    "restore_step",
    "save_checkpoint",
    "tree_checksum",
]

STATE, META = "state", "meta"
# tensorstore reports a failed file operation as ValueError("...: No space left on device
# [os_error_code='28']"): the errno of the OSError it stands for
_OS_ERROR_CODE = re.compile(r"\[os_error_code='(\d+)'\]")


def _quiet_orbax() -> None:
    """Orbax logs every save at INFO through absl; a run's output is the progress bar. A save
    that fails in orbax's writer thread is logged there with its traceback (ERROR), then raised
    to `save_checkpoint`, which reports it: the log record is dropped (`_ReRaised`)."""
    for name in ("absl", "orbax", "orbax.checkpoint"):
        logging.getLogger(name).setLevel(logging.WARNING)
    absl = logging.getLogger("absl")
    if not any(isinstance(f, _ReRaised) for f in absl.filters):
        absl.addFilter(_ReRaised())


class _ReRaised(logging.Filter):
    """Drops orbax's log of an exception its writer thread keeps and raises to the caller."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "_SignalingThread.run() raised an exception" not in str(record.msg)


def open_manager(directory: str | os.PathLike, max_to_keep: int) -> ocp.CheckpointManager:
    """A synchronous manager over ``directory`` (created if missing), keeping ``max_to_keep``.

    The temporary folders of steps whose save did not complete (killed, disk full) are removed
    (before the first save): the caller is the folder's only writer (`run_lock`).
    """
    _quiet_orbax()
    _ignore_closed_loop_callbacks()
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep,
        create=True,
        enable_async_checkpointing=False,
        cleanup_tmp_directories=True,
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

    The checksum of ``state`` is added to ``meta`` under ``"checksum"``. A file-system error
    (no space left, read-only file system) is an ``OSError`` naming the step's folder, whichever
    way orbax or tensorstore reported it; the step is then not saved (orbax renames a step's
    temporary folder only once it is complete), the previous ones are intact.
    """
    state = jax.tree_util.tree_map(np.asarray, state)
    meta = {**meta, "checksum": tree_checksum(state)}
    where = os.path.join(os.fspath(manager.directory), str(step))
    try:
        manager.save(
            step,
            args=ocp.args.Composite(
                **{STATE: ocp.args.StandardSave(state), META: ocp.args.JsonSave(meta)}
            ),
            force=True,
        )
        manager.wait_until_finished()
    except OSError as e:
        if e.filename is None:
            e.filename = where
        raise
    except ValueError as e:
        code = _OS_ERROR_CODE.search(str(e))
        if code is None:
            raise
        raise OSError(int(code[1]), os.strerror(int(code[1])), where) from e


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
    problems: list[str] = []
    for step in sorted(manager.all_steps(), reverse=True):
        restored, problem = restore_step(manager, step, template)
        if restored is not None:
            return restored, problems
        problems.append(f"checkpoint {step}: {problem}")
    return None, problems


def restore_step(
    manager: ocp.CheckpointManager, step: int, template: Any
) -> tuple[Restored | None, str]:
    """``(restored, "")`` where ``step`` restores like ``template`` and passes its checksum,
    else ``(None, what is wrong with it)``."""
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
        return None, f"unreadable ({type(e).__name__}: {_first_line(e)})"
    problem = _check_restored(state, template, meta)
    return (None, problem) if problem else (Restored(step, state, meta), "")


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


# ------------------------------------------------------------------- a closed event loop's noise
# Orbax runs each save and restore as asyncio gathers of tensorstore reads and writes on event
# loops of its own, which it closes when a gather returns. Where one of them fails (a
# damaged step, a full disk), the gather returns at once; the others still finish in
# tensorstore's threads, and their completion callbacks call ``loop.call_soon_threadsafe`` on the
# closed loop. The ``RuntimeError: Event loop is closed`` each raises has no caller to go to:
# Python printed each as a traceback (sys.unraisablehook), dozens for one damaged checkpoint or
# full disk, around the one line that says what happened. Those operations' results are not
# wanted (the step is unusable either way) and cannot be waited for from outside orbax, so
# exactly these errors are dropped; every other unraisable exception reaches the previous hook.


def _is_closed_loop_callback(unraisable: Any) -> bool:
    """Whether an unraisable exception is a callback's ``call_soon_threadsafe`` on a closed
    event loop."""
    e, tb = unraisable.exc_value, unraisable.exc_traceback
    if not (isinstance(e, RuntimeError) and str(e) == "Event loop is closed"):
        return False
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "call_soon_threadsafe":
            return True
        tb = tb.tb_next
    return False


def _ignore_closed_loop_callbacks() -> None:
    """Drop `_is_closed_loop_callback` exceptions from now on (installed once, when a manager is
    opened: the callbacks come from other threads, even before the failed call returns)."""
    previous = sys.unraisablehook
    if getattr(previous, "_drops_closed_loop_callbacks", False):
        return

    def hook(unraisable):
        if not _is_closed_loop_callback(unraisable):
            previous(unraisable)

    hook._drops_closed_loop_callbacks = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook
