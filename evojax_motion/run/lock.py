"""One writer per run folder: a `train` holds an exclusive lock on ``RUN/.lock`` while it runs.

A second `train` (or ``train --resume``) of the same folder is refused with one line,
``RUN: in use by process 1234 (started 12:01:03)`` (`UserError`, exit status 2): two runs in one
folder would save the same checkpoint steps and delete each other's. The lock is
``fcntl.flock``: the operating system drops it when its holder ends in any way (``kill -9``
included), so a killed run resumes as before; the file itself only names the holder (process
id, host, start time) and is removed when the run ends.

Commands that only read a run folder (``generate --db RUN``, ``report RUN``) take no lock: every
file of a run is replaced atomically (`atomic`), so they read a whole old or a whole new file, and
``report`` writes only into ``RUN/report`` (or ``--out``), which `train` never touches.

Where the file system has no ``flock`` (some network file systems) or the platform none
(Windows), the run goes on unlocked after a warning.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from evojax_motion.errors import UserError
from evojax_motion.run.atomic import make_folder, nearest_existing

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

LOCK_FILE = ".lock"
# flock() refused by the file system itself: run unlocked rather than not at all
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}
_HOLDER_WAIT = (20, 0.05)  # polls x seconds for a holder that has not yet written its name


@contextlib.contextmanager
def hold_run_folder(folder: str | os.PathLike) -> Iterator[None]:
    """Hold ``folder``'s lock for the ``with`` block, making ``folder`` (and missing parents)
    first. Raises `UserError` where another process holds it; ``OSError`` naming ``folder``
    where it cannot be made or written. On leaving, the lock file is removed, and the folders
    made here are removed again if nothing else was written into them."""
    folder = Path(folder)
    made = _missing(folder)
    try:
        make_folder(folder)
        fd = _acquire(folder)
    except BaseException:
        _remove_empty(made)
        raise
    try:
        yield
    finally:
        if fd is not None:
            _release(folder, fd)
        _remove_empty(made)


def _acquire(folder: Path) -> int | None:
    """The open, locked lock file's descriptor (None: no locks here, after a warning)."""
    if fcntl is None:
        return None
    path = folder / LOCK_FILE
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            e.filename, e.filename2 = str(folder), None
            raise
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise UserError(f"{folder}: in use by {holder}") from None
        except OSError as e:
            if e.errno not in _NO_LOCKS:
                os.close(fd)
                raise
            _release(folder, fd)  # the file would mean nothing
            why = f"file locks not supported here ({e.strerror})"
            print(f"warning: {folder}: {why}; nothing stops a second run in it", file=sys.stderr)
            return None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # its holder removed the file after it was opened here: open it again
    try:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
    except BaseException as e:
        _release(folder, fd)
        if isinstance(e, OSError):
            e.filename, e.filename2 = str(folder), None  # e.g. no space left for the name
        raise
    return fd


def _release(folder: Path, fd: int) -> None:
    # Removed while still held: a process that opened the old file meanwhile sees, once it holds
    # that file, that it is no longer the folder's lock file, and opens the new one (`_acquire`).
    with contextlib.suppress(OSError):
        os.unlink(folder / LOCK_FILE)
    os.close(fd)


def _holder(fd: int) -> str:
    """``process PID [on HOST] (started TIME)`` from the lock file, else ``another process``."""
    polls, pause = _HOLDER_WAIT
    data = b""
    for _ in range(polls):  # the holder writes its name just after taking the lock
        data = os.pread(fd, 4096, 0)
        if data:
            break
        time.sleep(pause)
    try:
        info = json.loads(data)
        pid, host, started = int(info["pid"]), str(info["host"]), float(info["started"])
    except (ValueError, KeyError, TypeError):
        return "another process"
    where = "" if host == socket.gethostname() else f" on {host}"
    start = time.localtime(started)
    fmt = "%H:%M:%S" if start[:3] == time.localtime()[:3] else "%Y-%m-%d %H:%M:%S"
    return f"process {pid}{where} (started {time.strftime(fmt, start)})"


def _missing(folder: Path) -> list[Path]:
    """``folder`` and its ancestors that do not exist yet, deepest first."""
    top = nearest_existing(folder)
    return [p for p in (folder, *folder.parents) if p != top and top in p.parents]


def _remove_empty(folders: list[Path]) -> None:
    for p in folders:  # deepest first; one that is not empty keeps it and its parents
        try:
            p.rmdir()
        except OSError:
            return
