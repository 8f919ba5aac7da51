"""The file system's refusals are user errors: for every command that writes, a read-only file
system, a full disk, a denied permission or a file where a folder should be is one line
``error: PATH: REASON`` on stderr, exit status 2, no traceback, nothing written (cli.main,
atomic.py). Refusals are injected (monkeypatched ``os`` calls for paths in one folder; as root,
``chmod`` refuses nothing); a file in the way is real. A run stopped by a full disk resumes:
tests/run/test_train.py."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from evojax_motion.cli.entry import main, os_error_line
from evojax_motion.run import atomic

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "configs" / "tiny.yaml"
TRIAL = REPO / "evojax_motion" / "data" / "ue_adl_sample" / "ADL004" / "ADL004FR1.csv"
PROC_FD = Path("/proc/self/fd")

# Every command that writes, with its output under a folder D. Inputs need not exist: the output
# is checked before any input is read (minutes of work would otherwise come first).
COMMANDS = {
    "demos": lambda d: ["demos", "--config", str(TINY), "--out", str(d / "db.npz"), "--quiet"],
    "train": lambda d: ["train", str(TINY), "--out", str(d / "run"), "--quiet"],
    "import": lambda d: [
        "import", "--format", "vicon-csv", "--robot", "mahru_arm",
        "--out", str(d / "imported.npz"), "--quiet", str(TRIAL),
    ],
    "generate": lambda d: [
        "generate", "--db", str(d.parent / "absent.npz"), "--target", "0.3", "-0.2", "0.2",
        "--out", str(d / "motion.csv"),
    ],
    "catch": lambda d: [
        "catch", "--db", str(d.parent / "absent.npz"),
        "--ball", "1.5", "-0.5", "1.0", "-3", "0.5", "2", "--out", str(d / "motion.csv"),
    ],
    "report": lambda d: [
        "report", str(d.parent / "absent_run"), "--out", str(d / "rep"), "--quiet",
    ],
    "simulate": lambda d: [
        "simulate", "--db", str(d.parent / "absent.npz"), "--target", "0.3", "-0.2", "0.2",
        "--out", str(d / "sim"),
    ],
}  # fmt: skip
# The path the error names: the folder written into, or a train's run folder (which its lock
# makes first: `run_lock`)
NAMED = {"train": lambda d: d / "run"}


def _inside(path, folder: Path) -> bool:
    try:
        return Path(os.fsdecode(path)).is_relative_to(folder)
    except TypeError:  # a descriptor, not a path
        return False


def _fd_inside(fd: int, folder: Path) -> bool:
    try:
        return _inside(os.readlink(PROC_FD / str(fd)), folder)
    except OSError:
        return False


def _refuse_creating(monkeypatch, folder: Path, code: int) -> None:
    """``os.open`` and ``os.mkdir`` in ``folder`` fail with ``code``, as the kernel's do."""
    for name in ("open", "mkdir"):
        real = getattr(os, name)

        def refused(path, *args, _real=real, **kwargs):
            if _inside(path, folder):
                raise OSError(code, os.strerror(code), os.fspath(path))
            return _real(path, *args, **kwargs)

        monkeypatch.setattr(os, name, refused)


def _fill_disk(monkeypatch, folder: Path) -> None:
    """Writes to files in ``folder`` fail with ENOSPC (naming no file, as ``write`` does): a full
    disk, where creating an empty file still works."""
    if not PROC_FD.is_dir():
        pytest.skip("needs /proc/self/fd to tell which file a descriptor is")
    for name in ("write", "pwrite", "fsync"):
        real = getattr(os, name)

        def full(fd, *args, _real=real, **kwargs):
            if _fd_inside(fd, folder):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return _real(fd, *args, **kwargs)

        monkeypatch.setattr(os, name, full)


KINDS = {
    "read-only file system": (errno.EROFS, lambda mp, d: _refuse_creating(mp, d, errno.EROFS)),
    "permission denied": (errno.EACCES, lambda mp, d: _refuse_creating(mp, d, errno.EACCES)),
    "no space left": (errno.ENOSPC, _fill_disk),
    "a file in the way": (errno.ENOTDIR, None),
}


def _listing(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None
        for p in sorted(folder.rglob("*"))
    }


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("command", COMMANDS)
def test_a_refused_write_is_one_line_and_leaves_nothing(
    tmp_path, monkeypatch, capsys, command, kind
):
    code, inject = KINDS[kind]
    dest = tmp_path / "dest"
    if inject is None:
        dest.write_text("a file, not a folder")
    else:
        dest.mkdir()
    before = _listing(tmp_path)
    if inject is not None:
        inject(monkeypatch, dest)
    status = main(COMMANDS[command](dest))
    monkeypatch.undo()  # (the listing below reads files)
    out, err = capsys.readouterr()
    named = NAMED.get(command, lambda d: d)(dest)
    assert (status, err) == (2, f"error: {named}: {os.strerror(code)}\n"), out
    assert _listing(tmp_path) == before


# ------------------------------------------------------------------ the write itself (atomic.py)


def _savez(path: Path) -> Path:
    from evojax_motion.motion.database import atomic_savez

    return atomic_savez(path, {"a": np.arange(3)})


WRITERS = {
    "text": lambda path: atomic.atomic_write_text(path, "new"),
    "npz": _savez,
}


@pytest.mark.parametrize("writer", WRITERS)
def test_a_full_disk_during_a_write_names_the_file_and_keeps_the_old_one(
    tmp_path, monkeypatch, writer
):
    """The disk fills up after the command's check (`run.atomic.check_writable`): the write fails
    naming the file (not its temporary file; ``write``/``fsync`` name none), the previous file
    is unchanged and no temporary file is left."""
    path = tmp_path / "out.file"
    path.write_bytes(b"old")
    _fill_disk(monkeypatch, tmp_path)
    with pytest.raises(OSError) as e:
        WRITERS[writer](path)
    monkeypatch.undo()
    assert os_error_line(e.value) == f"{path}: {os.strerror(errno.ENOSPC)}"
    assert [p.name for p in tmp_path.iterdir()] == ["out.file"]
    assert path.read_bytes() == b"old"


@pytest.mark.parametrize("code", [errno.EROFS, errno.EACCES])
def test_a_refused_temporary_file_names_the_file(tmp_path, monkeypatch, code):
    path = tmp_path / "out.txt"
    _refuse_creating(monkeypatch, tmp_path, code)
    with pytest.raises(OSError) as e:
        atomic.atomic_write_text(path, "x")
    monkeypatch.undo()
    assert (e.value.errno, e.value.filename) == (code, str(path))
    assert list(tmp_path.iterdir()) == []


def test_a_file_in_the_way_of_a_folder_is_named(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    for path in (blocker / "out.txt", blocker / "deeper" / "out.txt"):
        with pytest.raises(NotADirectoryError) as e:
            atomic.atomic_write_text(path, "x")
        assert e.value.filename in (str(blocker), str(blocker / "deeper")), e.value.filename
    assert [p.name for p in tmp_path.iterdir()] == ["blocker"]


def test_the_writability_check_leaves_nothing(tmp_path):
    assert atomic.check_writable(tmp_path / "new" / "deeper") == tmp_path
    assert list(tmp_path.iterdir()) == []


def test_an_error_without_a_path_is_its_reason():
    assert os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) == os.strerror(
        errno.ENOSPC
    )
    assert os_error_line(OSError("a message")) == "a message"
