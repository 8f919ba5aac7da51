"""Atomic file writes and the check that an output can be written at all.

Every file the package writes goes through `atomic_write`: the data go to a temporary file
``.NAME.XXXXXXXX.tmp`` in the same folder, are flushed to disk, and the temporary file is renamed
onto ``NAME`` (``os.replace``). A write that fails (read-only file system, no space left,
permission denied, a file where a folder should be) or is killed leaves the previous file as it
was and no temporary file behind (a killed one's is removed by the next run: `train`); the
``OSError`` it raises names ``NAME``, not the temporary file, so that the command line can say
``error: NAME: REASON`` (`cli.entry.main`).

Only the standard library: plots, exports and databases use it without importing JAX or orbax.
"""

from __future__ import annotations

import errno
import functools
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

TEMP_SUFFIX = ".tmp"
PROBE_PREFIX = ".evojax-motion-probe."


def atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], object]) -> Path:
    """Call ``write(f)`` on a temporary binary file beside ``path``, fsync, ``os.replace`` it onto
    ``path`` (its folders created as needed); returns ``path``.

    On failure the temporary file is removed, ``path`` is unchanged, and an ``OSError`` names
    ``path`` (or the folder that could not be made).
    """
    path = Path(path)
    tmp = None
    try:
        make_folder(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMP_SUFFIX, dir=path.parent)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual file mode
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(e, OSError) and _names_temporary(e, f".{path.name}."):
            e.filename, e.filename2 = str(path), None  # not the temporary file's name
        raise
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """`atomic_write` of ``data``."""
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """`atomic_write` of UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def make_folder(folder: Path) -> None:
    """``folder.mkdir(parents=True, exist_ok=True)``, where a file in its place is
    ``NotADirectoryError`` naming that file (``mkdir`` says "File exists")."""
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
    folder.mkdir(parents=True, exist_ok=True)


def nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (a file too: ``x/y`` under a file ``x`` does
    not exist, ``x`` does)."""
    for p in (path, *path.parents):
        if os.path.lexists(p):
            return p
    return Path(path.anchor or ".")


def check_writable(folder: str | os.PathLike) -> Path:
    """Raise the ``OSError`` a write into ``folder`` (made if missing) would meet, before any
    work is done: the nearest existing ``folder`` or ancestor is not a folder
    (``NotADirectoryError``), or an empty temporary file cannot be created, written one byte,
    synced and removed there (read-only file system, permission denied, no space left). Leaves
    nothing behind; the error names that existing folder. Returns it.

    A disk that fills up later is still possible: `atomic_write` then fails cleanly.
    """
    existing = nearest_existing(Path(folder))
    if not existing.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(existing))
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=PROBE_PREFIX, suffix=TEMP_SUFFIX, dir=existing)
        try:
            os.write(fd, b"\0")
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as e:
        if _names_temporary(e, PROBE_PREFIX):
            e.filename, e.filename2 = str(existing), None
        raise
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
    return existing


def _names_temporary(e: OSError, prefix: str) -> bool:
    """Whether ``e`` names no file (a failed ``write``, ``fsync``) or a temporary file
    ``prefix...tmp`` (``mkstemp``, ``os.replace``)."""
    if e.filename is None:
        return True
    if not isinstance(e.filename, (str, bytes, os.PathLike)):
        return False
    name = os.path.basename(os.fsdecode(e.filename))
    return name.startswith(prefix) and name.endswith(TEMP_SUFFIX)


@functools.cache
def _umask() -> int:
    # Read once: os.umask can only be read by setting it, which briefly affects every thread.
    mask = os.umask(0)
    os.umask(mask)
    return mask
