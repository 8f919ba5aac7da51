"""One training run as several processes (``train --distributed``): who writes, what they share.

Multi-controller JAX (docs/scaling.md): every process runs the same `run.training.run_training`,
computes every generation (the sharded step's collectives need all of them) and makes the same
checkpoint calls, which orbax synchronises and whose files its primary process, process 0, writes.
Process 0 alone takes the run folder's lock and writes the run's other files; the others print
nothing but errors (`quiet_unless_primary`). Orbax reads checkpoints on every process, so the run
folder must be on a file system that all processes see.

A process that goes on where another stopped waits in the next collective until JAX's heartbeat
timeout ends it, minutes later, with a crash report. So whatever only some processes may meet
(the lock, a run folder that looks different from another host) is settled together: each
process's outcome is gathered (`gather_text`) and the first process's error raised on every one
(`together`, `check_same`). With one process all of this is a plain call: no collective is
compiled.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np

from evojax_motion.errors import UserError

T = TypeVar("T")
TEXT_BYTES = 512  # of each process's text in `gather_text` (an error line, a digest)


def process_index() -> int:
    """This process's index (0 in a one-process run)."""
    import jax

    return jax.process_index()


def is_primary() -> bool:
    """Whether this process writes the run's files (process 0)."""
    return process_index() == 0


def gather_text(text: str) -> list[str]:
    """Every process's ``text`` (its first `TEXT_BYTES` UTF-8 bytes), in process order. A
    collective: every process calls it at the same point. ``[text]`` in a one-process run."""
    import jax

    if jax.process_count() == 1:
        return [text]
    from jax.experimental import multihost_utils

    buf = np.zeros(TEXT_BYTES, np.uint8)
    raw = text.encode()[:TEXT_BYTES]
    buf[: len(raw)] = np.frombuffer(raw, np.uint8)
    rows = np.asarray(multihost_utils.process_allgather(buf)).reshape(-1, TEXT_BYTES)
    return [bytes(r).rstrip(b"\0").decode(errors="replace") for r in rows]


def together(fn: Callable[[], T]) -> T:
    """``fn()`` on every process; where it raises `UserError` or ``OSError`` on any, every process
    raises: this process its own error, the others `UserError` with the first failing process's
    message (``process i: ...`` after i > 0)."""
    error: Exception | None = None
    try:
        result = fn()
    except (UserError, OSError) as e:
        error = e
    # a flag first: an error's message may be empty
    outcomes = gather_text("" if error is None else f"!{error}")
    failed = [(i, text[1:]) for i, text in enumerate(outcomes) if text]
    if error is not None:
        raise error
    if failed:
        i, message = failed[0]
        raise UserError(message if i == 0 else f"process {i}: {message}")
    return result


def first_different(text: str) -> int | None:
    """The first process whose ``text`` differs from process 0's (compared by SHA-256), or None
    where all agree. A collective."""
    digests = gather_text(hashlib.sha256(text.encode()).hexdigest())
    return next((i for i, d in enumerate(digests) if d != digests[0]), None)


def check_same(text: str, what: str) -> None:
    """`UserError` on every process unless every process passes the same ``text``; ``what``
    names it in the message."""
    other = first_different(text)
    if other is not None:
        raise UserError(f"--distributed: process {other} has another {what} than process 0")


def check_devices(devices: int | None) -> None:
    """`UserError` where a run of several processes would shard over some of their devices
    only (``parallel.devices``): the mesh must hold a device of every process."""
    import jax

    n = jax.device_count()
    if jax.process_count() > 1 and devices not in (None, n):
        raise UserError(
            f"parallel.devices: a run of {jax.process_count()} processes shards over all their "
            f"{n} devices: expected null or {n}, got {devices}"
        )


@contextlib.contextmanager
def quiet_unless_primary() -> Iterator[None]:
    """Outside process 0, what the block prints (progress, warnings, the summary) is dropped:
    every process would say the same. Errors leaving the block are still reported."""
    if is_primary():
        yield
        return
    with (
        open(os.devnull, "w") as sink,
        contextlib.redirect_stdout(sink),
        contextlib.redirect_stderr(sink),
    ):
        yield
