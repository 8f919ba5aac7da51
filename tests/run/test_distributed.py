"""``train --distributed`` (run/processes.py, run/training.py): 2 processes x 2 forced CPU devices
joined over gloo evolve the database that one process evolves on 4 devices; process 1 writes
nothing into the run folder; a run whose process 1 was SIGKILLed resumes to the same database;
user mistakes end every process with one line and status 2.

Every process runs `_DRIVER`: the command line, with an audit hook (``sys.addaudithook``) that
records each file operation of the process that could change the run folder (an open for
writing, a rename, a mkdir, a removal) and, on request, a SIGKILL of the process just after it
saved a given checkpoint. Orbax's array files are written by tensorstore, out of the hook's
sight; orbax makes them on process 0 only, whose own operations show that the hook sees the
run's writes (`test_two_processes_evolve_the_database_of_one_process_with_four_devices`).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from multiprocess_support import REPO, cpu_devices_env, process_envs

TINY = REPO / "configs" / "tiny.yaml"
ARGS = ["train", str(TINY), "--quiet"]
N_PROCESSES, DEVICES_PER_PROCESS = 2, 2
KILL_AFTER_CHECKPOINT = 2  # of configs/tiny.yaml's 4 generations, a checkpoint after each
TIMEOUT_S = 600
# Generation statistics are means over all conditions, combined across devices by all-reduces
# whose summation order is the collectives' own (in one process, or over gloo), so they may
# differ in their last float32 bits (a few ulp, 1.2e-7 each); counts are exact.
STATS_RTOL = 1e-6
DB_KEYS = ("q", "duration", "condition", "cost", "origin", "valid", "generation")

_DRIVER = """
import json, os, signal, sys

writes_log, kill_after, out, *argv = sys.argv[1:]
out = os.path.realpath(out)
log = open(writes_log, "w", buffering=1)  # opened before the hook: not recorded
CHANGES = {"os.rename", "os.mkdir", "os.remove", "os.rmdir", "shutil.rmtree", "os.truncate",
           "os.link", "os.symlink", "os.chmod", "os.utime"}  # os.replace raises os.rename
WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND


def in_run_folder(path):
    try:
        path = os.path.realpath(os.fsdecode(path))
    except TypeError:  # a file descriptor
        return False
    return path == out or path.startswith(out + os.sep)


def hook(event, args):
    if event == "open":
        path, mode, flags = args
        writes = isinstance(mode, str) and any(c in mode for c in "wax+")
        writes = writes or isinstance(flags, int) and bool(flags & WRITE_FLAGS)
        paths = [path] if writes else []
    else:
        paths = [a for a in args[:2] if isinstance(a, (str, bytes, os.PathLike))]
        paths = paths if event in CHANGES else []
    for path in paths:
        if in_run_folder(path):
            log.write(json.dumps([event, os.fsdecode(path)]) + "\\n")


sys.addaudithook(hook)
if int(kill_after) >= 0:
    from evojax_motion.run import checkpoint

    save = checkpoint.save_checkpoint

    def save_then_die(manager, step, *args, **kwargs):
        save(manager, step, *args, **kwargs)
        if step == int(kill_after):
            os.kill(os.getpid(), signal.SIGKILL)

    checkpoint.save_checkpoint = save_then_die

from evojax_motion.cli.entry import main

sys.exit(main(argv))
"""


class Launch:
    """Processes running `_DRIVER` on one run folder, the i-th with ``envs[i]`` and the extra
    arguments ``extras[i]``, killed after checkpoint ``kill_after[i]`` where given; `wait` gives
    ``(status, output, writes)`` per process, ``writes`` being the run-folder changes its audit
    hook recorded."""

    def __init__(self, folder: Path, out: Path, envs: list[dict], extras=None, kill_after=None):
        driver = folder / "driver.py"
        driver.write_text(_DRIVER)
        self.logs = [folder / f"{out.name}.{i}.writes" for i in range(len(envs))]
        self.outputs = [folder / f"{out.name}.{i}.log" for i in range(len(envs))]
        extras = extras or [[]] * len(envs)
        kill_after = kill_after or {}
        self.procs = []
        for i, (env, extra) in enumerate(zip(envs, extras, strict=True)):
            kill = kill_after.get(i, -1)
            argv = [str(self.logs[i]), str(kill), str(out), *ARGS, "--out", str(out), *extra]
            with self.outputs[i].open("w") as f:
                self.procs.append(
                    subprocess.Popen(
                        [sys.executable, str(driver), *argv],
                        env=env,
                        stdout=f,
                        stderr=subprocess.STDOUT,
                    )
                )

    def wait(self) -> list[tuple[int, str, list]]:
        results = []
        for proc, output, log in zip(self.procs, self.outputs, self.logs):
            try:
                status = proc.wait(timeout=TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.kill()
                raise
            writes = [json.loads(line) for line in log.read_text().splitlines()]
            results.append((status, output.read_text(), writes))
        return results

    def kill(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _distributed(folder: Path, out: Path, extra=(), kill_after=None) -> Launch:
    """`Launch` of ``train --distributed`` (and ``extra``) as 2 processes of 2 CPU devices."""
    envs = process_envs(N_PROCESSES, DEVICES_PER_PROCESS)
    extras = [["--distributed", *extra]] * N_PROCESSES
    return Launch(folder, out, envs, extras, kill_after)


def _database(path: Path):
    from evojax_motion.motion.database import load_database

    return load_database(path)[0]


def _assert_same_metrics(ref: Path, out: Path) -> None:
    """The rows of ``metrics.jsonl`` agree but for their wall-clock times: counts exactly,
    means to `STATS_RTOL`."""

    def rows(folder):
        lines = (folder / "metrics.jsonl").read_text().splitlines()
        clock = ("seconds", "finished_at")
        return [{k: v for k, v in json.loads(r).items() if k not in clock} for r in lines]

    a, b = rows(ref), rows(out)
    assert [sorted(r) for r in a] == [sorted(r) for r in b] and a
    for ra, rb in zip(a, b):
        for key, va in ra.items():
            if isinstance(va, float):
                assert rb[key] == pytest.approx(va, rel=STATS_RTOL), (out, ra["generation"], key)
            else:
                assert rb[key] == va, (out, ra["generation"], key)


def _assert_same_database(ref: Path, out: Path) -> None:
    a, b = _database(ref / "db_final.npz"), _database(out / "db_final.npz")
    for key in DB_KEYS:
        assert getattr(a, key).tobytes() == getattr(b, key).tobytes(), (out, key)


def _run_files(out: Path) -> list[str]:
    """The run folder's files, orbax's step contents aside (their names are random)."""
    return sorted(
        str(p.relative_to(out))
        for p in out.rglob("*")
        if p.is_file() and "checkpoints" not in p.relative_to(out).parts
    )


def _ok(results) -> list:
    for i, (status, output, _) in enumerate(results):
        assert status == 0, f"process {i}:\n{output[-4000:]}"
    return results


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """configs/tiny.yaml run to the end by one process with 4 CPU devices and by 2 processes
    with 2 each: ``(one-process folder, distributed folder, distributed results)``."""
    folder = tmp_path_factory.mktemp("distributed")
    one = folder / "one"
    env = cpu_devices_env(N_PROCESSES * DEVICES_PER_PROCESS)
    _ok(Launch(folder, one, [env]).wait())
    two = folder / "two"
    return one, two, _ok(_distributed(folder, two).wait())


@pytest.mark.slow
def test_two_processes_evolve_the_database_of_one_process_with_four_devices(runs):
    """Bit for bit: both runs shard the conditions over 4 devices alike, so each device runs the
    same program on the same conditions; what crosses devices is gathered (exact) or reduced
    (scalar statistics only, which stay equal here too). Process 0 writes the run's files,
    process 1 none of them."""
    one, two, results = runs
    _assert_same_database(one, two)
    _assert_same_metrics(one, two)
    assert _run_files(two) == _run_files(one)
    assert sorted((two / "checkpoints").iterdir()) != []
    (_, output0, writes0), (_, output1, writes1) = results
    written = {Path(path).name for _, path in writes0}
    for name in ("config.yaml", "metrics.jsonl", "db_final.npz", "summary.json", "costs.png"):
        assert name in written, name  # the hook sees a run's writes...
    assert writes1 == []  # ...and process 1 makes none
    assert "db_cost_last" in output0 and "db_cost_last" not in output1  # the summary: once


@pytest.mark.slow
def test_a_run_whose_process_1_was_killed_resumes_to_the_same_database(runs, tmp_path):
    """Process 1 is SIGKILLed just after checkpoint 2; process 0, which would wait in the next
    generation's collectives until JAX's heartbeat timeout, is then killed as a launcher ends the
    other tasks of a job. Both relaunched with --resume go on from checkpoint 2 and end with
    the uninterrupted run's database and metrics."""
    _, two, _ = runs
    out = tmp_path / "killed"
    launch = _distributed(tmp_path, out, kill_after={1: KILL_AFTER_CHECKPOINT})
    try:
        launch.procs[1].wait(timeout=TIMEOUT_S)
    finally:
        launch.kill()
    (status0, _, _), (status1, output1, writes1) = launch.wait()
    assert status1 == -9, output1[-4000:]
    assert status0 == -9
    assert writes1 == []
    assert (out / "checkpoints" / str(KILL_AFTER_CHECKPOINT)).is_dir()

    results = _ok(_distributed(tmp_path, out, ["--resume"]).wait())
    assert results[1][2] == []
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed_from"] == KILL_AFTER_CHECKPOINT
    assert summary["checkpoint_problems"] == []
    _assert_same_database(two, out)
    _assert_same_metrics(two, out)


@pytest.mark.slow
def test_processes_with_different_configs_all_stop_with_one_line(tmp_path):
    """Process 1 has another --set: every process says so in one line, exits with status 2, and
    the run folder is not made."""
    out = tmp_path / "run"
    extras = [["--distributed"], ["--distributed", "--set", "seed=1"]]
    launch = Launch(tmp_path, out, process_envs(N_PROCESSES, DEVICES_PER_PROCESS), extras)
    for status, output, _ in launch.wait():
        lines = [ln for ln in output.splitlines() if ln.startswith("error: ")]
        assert status == 2, output[-4000:]
        assert lines == ["error: --distributed: process 1 has another config or --resume than "
                         "process 0"], output[-4000:]  # fmt: skip
        assert "Traceback" not in output
    assert not out.exists()


def test_distributed_without_a_coordinator_is_one_line(tmp_path):
    """--distributed outside a cluster JAX detects, without the variables: status 2, one line
    naming them; nothing is written."""
    env = cpu_devices_env(1)
    for name in ("JAX_COORDINATOR_ADDRESS", "EVOJAX_NUM_PROCESSES", "EVOJAX_PROCESS_ID"):
        env.pop(name, None)
    env = {k: v for k, v in env.items() if not k.startswith(("SLURM_", "OMPI_"))}
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "evojax_motion.cli", *ARGS, "--out", str(out), "--distributed"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert res.returncode == 2, res.stderr[-4000:]
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("error: "), res.stderr
    for name in ("JAX_COORDINATOR_ADDRESS", "EVOJAX_NUM_PROCESSES", "EVOJAX_PROCESS_ID"):
        assert name in res.stderr
    assert not out.exists()
