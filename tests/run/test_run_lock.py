"""One writer per run folder (run_lock.py): refusal naming the holder, release by the operating
system when the holder dies, no trace left when nothing was written."""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from evojax_motion.errors import UserError
from evojax_motion.run import lock as run_lock
from evojax_motion.run.lock import LOCK_FILE, hold_run_folder

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(run_lock.fcntl is None, reason="no fcntl: runs are not locked")


def _in_use(folder: Path, pid: int) -> str:
    """The refusal's pattern for a holder ``pid`` started today on this host."""
    return rf"^{re.escape(str(folder))}: in use by process {pid} \(started \d\d:\d\d:\d\d\)$"


def test_a_second_holder_is_refused_naming_the_first(tmp_path):
    run = tmp_path / "run"
    before = time.time()
    with hold_run_folder(run):
        held = json.loads((run / LOCK_FILE).read_text())
        assert held["pid"] == os.getpid() and before - 1 <= held["started"] <= time.time()
        second = pytest.raises(UserError, match=_in_use(run, os.getpid()))
        with second as refused, hold_run_folder(run):
            pytest.fail("a second holder entered")
        started = time.strftime("%H:%M:%S", time.localtime(held["started"]))
        assert str(refused.value).endswith(f"(started {started})")
        (run / "data").write_text("x")  # something the run wrote
    assert sorted(p.name for p in run.iterdir()) == ["data"]  # no lock file left
    with hold_run_folder(run):  # free again
        pass


def test_folders_made_for_nothing_are_removed_again(tmp_path):
    deep = tmp_path / "a" / "b" / "run"
    with hold_run_folder(deep):
        assert (deep / LOCK_FILE).is_file()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="boom"), hold_run_folder(deep):
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    existing = tmp_path / "mine"
    existing.mkdir()
    with hold_run_folder(existing):
        pass
    assert existing.is_dir() and list(existing.iterdir()) == []  # the user's folder stays


_HOLDER = """
import sys, time
from evojax_motion.run.lock import hold_run_folder
with hold_run_folder(sys.argv[1]):
    print("held", flush=True)
    time.sleep(600)
"""


def test_the_lock_goes_with_its_holder_killed(tmp_path):
    """A holder killed with SIGKILL leaves its lock file, but not its lock."""
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(run)], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert proc.stdout.readline() == "held\n"
        with pytest.raises(UserError, match=_in_use(run, proc.pid)), hold_run_folder(run):
            pass
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        proc.stdout.close()
    assert (run / LOCK_FILE).is_file()  # left behind: it no longer means anything
    with hold_run_folder(run):
        assert json.loads((run / LOCK_FILE).read_text())["pid"] == os.getpid()


def test_a_lock_file_removed_while_opening_it_is_opened_again(tmp_path, monkeypatch):
    """A process that opened the lock file just before its holder removed it (at the end of a
    run) must not lock that removed file: it opens the folder's lock file again."""
    run = tmp_path / "run"
    run.mkdir()
    real_open, opened = os.open, []

    def open_then_replaced(path, *args, **kwargs):
        fd = real_open(path, *args, **kwargs)
        if str(path).endswith(LOCK_FILE) and not opened:
            os.unlink(path)  # the holder's release, between our open and our flock
            os.close(real_open(path, os.O_CREAT | os.O_WRONLY, 0o644))  # the next one's file
        opened.append(fd)
        return fd

    monkeypatch.setattr(os, "open", open_then_replaced)
    with hold_run_folder(run):
        assert len(opened) == 2
        assert os.path.samestat(os.fstat(opened[1]), os.stat(run / LOCK_FILE))


def test_a_holder_that_has_not_written_its_name_is_another_process(tmp_path, monkeypatch):
    import fcntl

    run = tmp_path / "run"
    run.mkdir()
    fd = os.open(run / LOCK_FILE, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        monkeypatch.setattr(run_lock, "_HOLDER_WAIT", (2, 0.01))
        refused = pytest.raises(UserError, match=r": in use by another process$")
        with refused, hold_run_folder(run):
            pass
    finally:
        os.close(fd)


def test_a_file_system_without_locks_runs_unlocked_after_a_warning(tmp_path, monkeypatch, capsys):
    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(run_lock.fcntl, "flock", no_locks)
    run = tmp_path / "run"
    with hold_run_folder(run):
        (run / "data").write_text("x")
    err = capsys.readouterr().err
    assert err == (
        f"warning: {run}: file locks not supported here ({os.strerror(errno.ENOLCK)}); "
        "nothing stops a second run in it\n"
    )
    assert sorted(p.name for p in run.iterdir()) == ["data"]


def test_a_lock_file_does_not_make_a_folder_a_run(tmp_path):
    """A new run may start in a folder that holds only a lock file (a run killed before it
    wrote anything else leaves one)."""
    from evojax_motion.run.training import check_run_dir

    run = tmp_path / "run"
    run.mkdir()
    (run / LOCK_FILE).write_text("{}")
    assert check_run_dir(run, {"seed": 0}, resume=False) is False
    with pytest.raises(UserError, match="no run to resume"):
        check_run_dir(run, {"seed": 0}, resume=True)
