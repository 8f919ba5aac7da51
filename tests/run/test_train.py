"""The training run (train.py, checkpoint.py, plots.py) on the tiny config: metrics, invariants,
costs against C MuJoCo, resume after SIGKILL or a full disk, damaged checkpoints, one run per
folder, refusals of bad input."""

from __future__ import annotations

import errno
import glob
import itertools
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from evojax_motion.errors import UserError
from evojax_motion.run import checkpoint as ck
from evojax_motion.run.training import check_run_dir

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "configs" / "tiny.yaml"

# ------------------------------------------------------------------------------- checkpoints


def _tree(seed: int, step: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "db": {"q": rng.normal(size=(9, 6, 2)).astype(np.float32), "valid": rng.random(9) > 0.5},
        "generation": np.asarray(step, np.int32),
    }


def _flip_bytes(step_dir: Path) -> None:
    """Flip one byte in the middle of the step's largest array file (silent corruption)."""
    files = [Path(f) for f in glob.glob(f"{step_dir}/state/**/d/*", recursive=True)]
    f = max(files, key=lambda p: p.stat().st_size)
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))


@pytest.fixture
def manager(tmp_path):
    with ck.open_manager(tmp_path / "ckpt", max_to_keep=3) as m:
        yield m


def test_checkpoint_roundtrip_and_damaged_latest(tmp_path, manager):
    for step in range(4):
        ck.save_checkpoint(manager, step, _tree(step, step), {"metrics": [{"generation": step}]})
    assert manager.all_steps() == [1, 2, 3]
    template = _tree(0, 0)

    restored, problems = ck.restore_latest(manager, template)
    assert restored.step == 3 and problems == []
    for a, b in zip(np.asarray(restored.state["db"]["q"]).ravel(), _tree(3, 3)["db"]["q"].ravel()):
        assert a == b
    assert restored.meta["metrics"] == [{"generation": 3}]

    _flip_bytes(tmp_path / "ckpt" / "3")  # complete but damaged afterwards
    restored, problems = ck.restore_latest(manager, template)
    assert restored.step == 2
    assert len(problems) == 1 and problems[0].startswith("checkpoint 3: ")

    for f in glob.glob(f"{tmp_path}/ckpt/2/state/**/d/*", recursive=True):
        Path(f).write_bytes(b"")  # truncated files: the restore itself fails
    restored, problems = ck.restore_latest(manager, template)
    assert restored.step == 1
    assert any("checkpoint 2: unreadable" in p for p in problems)

    # a template of another shape is refused rather than silently restored
    bad = _tree(0, 0)
    bad["db"]["q"] = np.zeros((9, 7, 2), np.float32)
    restored, problems = ck.restore_latest(manager, bad)
    assert restored is None and len(problems) == 3


def test_only_callbacks_on_a_closed_event_loop_are_silenced(monkeypatch):
    """A failed orbax save or restore leaves tensorstore callbacks aimed at the event loop orbax
    has closed: their ``RuntimeError: Event loop is closed`` (unraisable, printed as a traceback
    each) is dropped once a manager is open; any other unraisable exception is not."""
    import asyncio
    import types

    def unraisable(call):
        try:
            call()
        except RuntimeError as e:
            return types.SimpleNamespace(
                exc_type=type(e), exc_value=e, exc_traceback=e.__traceback__, err_msg=None,
                object=None,
            )  # fmt: skip
        raise AssertionError("no error")

    loop = asyncio.new_event_loop()
    loop.close()

    def other():
        raise RuntimeError("Event loop is closed")  # the same words, not from a closed loop

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    ck._ignore_closed_loop_callbacks()
    ck._ignore_closed_loop_callbacks()  # once only
    closed, elsewhere = unraisable(lambda: loop.call_soon_threadsafe(print)), unraisable(other)
    sys.unraisablehook(closed)
    sys.unraisablehook(elsewhere)
    assert seen == [elsewhere]


def test_checksum_detects_changed_data(manager):
    """Data that reads back fine but differs from what was saved fails the checksum."""
    ck.save_checkpoint(manager, 0, _tree(0, 0), {})
    tree = _tree(1, 1)
    meta = {"checksum": ck.tree_checksum(_tree(2, 1))}  # as if the arrays changed on disk
    manager.save(
        1,
        args=ck.ocp.args.Composite(
            state=ck.ocp.args.StandardSave(tree), meta=ck.ocp.args.JsonSave(meta)
        ),
    )
    restored, problems = ck.restore_latest(manager, _tree(0, 0))
    assert restored.step == 0
    assert problems == ["checkpoint 1: checksum mismatch (the data changed after it was written)"]


def test_atomic_write_leaves_no_temporary(tmp_path):
    from evojax_motion.run.atomic import atomic_write_text

    path = atomic_write_text(tmp_path / "a.txt", "one")
    atomic_write_text(path, "two")
    assert path.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


# ---------------------------------------------------------------------------- run directory


def test_check_run_dir_refusals(tmp_path):
    cfg = {"seed": 0, "evolution": {"conditions": 4}}
    assert check_run_dir(tmp_path / "new", cfg, resume=False) is False
    with pytest.raises(UserError, match="no run to resume"):
        check_run_dir(tmp_path / "new", cfg, resume=True)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\nevolution:\n  conditions: 4\n")
    assert check_run_dir(run, cfg, resume=True) is True
    with pytest.raises(UserError, match="pass --resume"):
        check_run_dir(run, cfg, resume=False)
    other = {"seed": 1, "evolution": {"conditions": 4}}
    for resume in (False, True):
        with pytest.raises(UserError, match=r"another config: seed \(0 there, 1 here\)"):
            check_run_dir(run, other, resume=resume)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x").write_text("x")
    with pytest.raises(UserError, match="not empty"):
        check_run_dir(tmp_path / "junk", cfg, resume=False)
    with pytest.raises(UserError, match="no run to resume"):
        check_run_dir(tmp_path / "junk", cfg, resume=True)
    with pytest.raises(UserError, match="found a file"):
        check_run_dir(tmp_path / "junk" / "x", cfg, resume=False)


def test_a_demonstrations_file_is_read_for_the_configs_robot(tmp_path):
    """``demos_file`` recorded for the same arm without velocity limits, a config that gives
    them: the demonstrations come with the config's model (the databases a run writes keep it,
    and the queries on them check those limits); a file of another end effector is refused,
    naming it."""
    import dataclasses

    from evojax_motion.model.robot import robot_from_mjcf_text
    from evojax_motion.motion.database import DatabaseMeta, make_database, save_database
    from evojax_motion.run.workflow import make_robot, read_demonstrations_file
    from evojax_motion.settings import config_from_dict, config_to_dict, load_config

    plain = make_robot(load_config(TINY))
    rng = np.random.default_rng(0)
    q = plain.rest + rng.normal(0, 0.01, (4, 8, plain.n_joints))
    db = make_database(q, np.ones(4), rng.normal(0, 0.1, (4, 3)), cost=np.ones(4))
    meta = DatabaseMeta.of_robot(plain, synthetic=False, description="recorded")
    save_database(tmp_path / "demos.npz", db, meta)
    limits = {name: 0.5 + i for i, name in enumerate(plain.joint_names)}
    sets = [f"demos_file={tmp_path / 'demos.npz'}", f"robot.velocity_limits={limits}"]
    cfg = config_from_dict(config_to_dict(load_config(TINY)), sets)
    robot = make_robot(cfg)
    got, got_meta = read_demonstrations_file(cfg, robot)
    np.testing.assert_array_equal(got.q, db.q)
    assert got_meta.mjcf == robot.mjcf and got_meta.description == "recorded"
    again = robot_from_mjcf_text(
        got_meta.robot_name, got_meta.mjcf, got_meta.joint_names, got_meta.site_name
    )
    np.testing.assert_allclose(again.velocity_limit, list(limits.values()))

    other = dataclasses.replace(meta, site_name="elsewhere")
    save_database(tmp_path / "demos.npz", db, other)
    with pytest.raises(UserError, match=r"demos\.npz: its hand positions are of end effector"):
        read_demonstrations_file(cfg, robot)


def test_compile_wait_counts_the_early_compile_still_running():
    """``compile_seconds`` of a run's summary counts the wait for the step compiled in the
    background (`run.compilation.wait_for_step`): a compile that ends 0.3 s after the
    demonstrations and conditions is 0.3 s not hidden (earlier summaries read 0.0 s there)."""
    import time

    from evojax_motion.run.compilation import wait_for_step

    class Early:
        def step(self):
            time.sleep(0.3)
            return "compiled"

    step, waited = wait_for_step(Early())
    assert step == "compiled" and 0.3 <= waited < 5.0
    assert wait_for_step(None) == (None, 0.0)


# ------------------------------------------------------------------- the tiny run, end to end

TOL_COST_REL = 0.01  # stored eq. 5 costs vs C MuJoCo mj_inverse (float32 JAX vs float64 C)
DB_KEYS = ("q", "duration", "condition", "cost", "origin", "valid", "generation")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One uninterrupted run of configs/tiny.yaml: ``(out_dir, summary, cfg)``."""
    from evojax_motion.run.training import run_training
    from evojax_motion.settings import load_config

    cfg = load_config(TINY)
    out = tmp_path_factory.mktemp("tiny") / "run"
    summary = run_training(cfg, out, progress=False)
    return out, summary, cfg


@pytest.mark.slow
def test_initial_state_reuses_its_traced_programs_and_matches_expected_inputs(
    tmp_path, monkeypatch
):
    """A second setup of the same config reads the first one's demonstrations back (a kept
    result) and compiles every other setup program (costs, the condition draw's three stages)
    from the first one's traced programs, tracing none (a key with anything unstable in it would
    retrace, silently slower), and gives the same state.
    The generation step is compiled early for `expected_inputs`; were they not shaped and typed
    as what `initial_state` returns (with the neighbour search's candidate lists where there are
    many conditions), every run would compile it twice, silently."""
    import jax

    from evojax_motion.evolution import step as evolution
    from evojax_motion.motion.database import humans_only, save_database
    from evojax_motion.run import cache as compile_cache
    from evojax_motion.run.cache import signature
    from evojax_motion.run.compilation import expected_inputs
    from evojax_motion.run.training import initial_state
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import config_from_dict, config_to_dict, load_config

    assert compile_cache.traced_cache_dir() is not None  # conftest's test-run cache
    cfg = load_config(TINY)
    robot, dyn = make_robot_dynamics(cfg)
    db, conditions, meta, *_ = initial_state(cfg, robot, dyn)
    calls = {"compile_traced": 0, "export": 0}

    def counted(name, fn):
        def wrapper(*a, **k):
            calls[name] += 1
            return fn(*a, **k)

        return wrapper

    monkeypatch.setattr(
        compile_cache, "compile_traced", counted("compile_traced", compile_cache.compile_traced)
    )
    monkeypatch.setattr(jax.export, "export", counted("export", jax.export.export))
    again, conditions_again, *_ = initial_state(cfg, robot, dyn)
    monkeypatch.undo()
    assert calls == {"compile_traced": 4, "export": 0}  # the demonstrations: a kept result
    for a, b in zip(jax.tree_util.tree_leaves((db, conditions)),
                    jax.tree_util.tree_leaves((again, conditions_again)), strict=True):  # fmt: skip
        np.testing.assert_array_equal(a, b)
    actual = signature((db, conditions))
    assert signature(expected_inputs(cfg, robot)) == actual

    # recorded data: the same demonstrations from a file (evolved slots empty: not read back)
    save_database(tmp_path / "demos.npz", humans_only(db), meta)
    from_file = config_from_dict(config_to_dict(cfg), [f"demos_file={tmp_path / 'demos.npz'}"])
    assert signature(expected_inputs(from_file, robot)) == actual
    missing = config_from_dict(config_to_dict(cfg), [f"demos_file={tmp_path / 'none.npz'}"])
    assert expected_inputs(missing, robot) is None  # initial_state reports the missing file

    # a new run compiles the setup's programs from the expected sizes, in the background:
    # they must be the very programs `initial_state` then calls (no second signature)
    from evojax_motion.run.compilation import expected_sizes, setup_programs

    setup = setup_programs(cfg, robot, dyn, expected_sizes(cfg, robot))
    setup.precompile()
    initial_state(cfg, robot, dyn, setup)
    programs = [setup.costs._batch, *setup.conditions[:3]]
    assert [len(p._compiled) for p in programs] == [1, 1, 1, 1]

    # many conditions: the neighbour search's candidate lists are inputs of the step too
    monkeypatch.setattr(evolution, "SEARCH_CANDIDATES_MIN_CONDITIONS", 1)
    _, listed, *_ = initial_state(cfg, robot, dyn)
    assert listed.candidates is not None
    assert signature(expected_inputs(cfg, robot)) == signature((db, listed)) != actual


# Staged against one-program step: the same trajectories; the float32 eq. 5 costs may be summed in
# another order (tiny config: 2.6e-6 relative; paper scale, 8 generations: bit-identical).
STAGED_COST_RTOL = 1e-5


@pytest.mark.shipped_level
def test_staged_step_matches_the_one_program_step_and_reuses_its_traces(monkeypatch):
    """`run.compilation.compile_generation_step` on one device: its two stages compiled side by
    side give the one-program step's generations (database and statistics, 2 generations), its cost
    analysis is the two programs' together, and a second compile traces neither stage again
    (the traced programs are kept)."""
    import jax

    from evojax_motion.evolution.step import make_generation_step
    from evojax_motion.motion.database import count_human
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run import cache as compile_cache
    from evojax_motion.run.compilation import StagedStep, compile_generation_step
    from evojax_motion.run.training import initial_state
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import load_config

    assert compile_cache.traced_cache_dir() is not None  # conftest's test-run cache
    # The tiny config as trained (its method, Adam): the two stages are the tiny run's programs,
    # held by the test run's XLA cache, so only the one-program step compiles here (with BFGS,
    # whose Gauss-Newton model crosses from the first stage to the second, both stages compile
    # too: 51 s of XLA compile in the test run against 6.4 s, 3.6 s of it the shared stages).
    cfg = load_config(TINY)
    robot, dyn = make_robot_dynamics(cfg)
    db, conditions, *_ = initial_state(cfg, robot, dyn)
    staged = compile_generation_step(cfg, robot, dyn, db, conditions)
    assert isinstance(staged, StagedStep)
    one = make_generation_step(
        dyn, make_time_grid(db.q.shape[1]), robot.lower, robot.upper, count_human(db),
        cfg.basis, cfg.compiler, cfg.evolution,
        torque_limit=robot.torque_limit, velocity_limit=robot.velocity_limit,
    )  # fmt: skip
    db_b = db
    for g in (1, 2):  # each from the same database: a cost's last bit can decide a survivor
        db_a, stats_a = staged(db_b, conditions, np.int32(g))
        db_b, stats_b = one(db_b, conditions, np.int32(g))
        for a, b in zip(db_a._replace(cost=0), db_b._replace(cost=0), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip((db_a.cost, *stats_a), (db_b.cost, *stats_b), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=STAGED_COST_RTOL)
    assert int(stats_a.n_valid) > 0  # the generations did fill slots

    flops = [s.cost_analysis()["flops"] for s in (staged.prepare, staged.finish)]
    assert staged.cost_analysis()["flops"] == pytest.approx(sum(flops))
    assert min(flops) > 0

    exports = []
    monkeypatch.setattr(jax.export, "export", lambda *a, **k: exports.append(a))
    again = compile_generation_step(cfg, robot, dyn, db, conditions)
    assert exports == []
    first = staged(db, conditions, np.int32(1))[0]
    np.testing.assert_array_equal(again(db, conditions, np.int32(1))[0].q, first.q)


class _Stop(Exception):
    """Raised by a stand-in to end a call once its arguments are recorded."""


def test_only_train_compiles_its_step_as_a_short_run(tmp_path, monkeypatch):
    """A short run's step compiles with `compile_options.short_run` (on GPUs, no autotuning):
    `train` passes `model.dynamics.is_short_run` of its config to `compile_generation_step`
    (the early compile and the foreground one), whose default, the full compile that the
    generation benchmarks measure, does not follow the config."""
    from evojax_motion.evolution import sharding
    from evojax_motion.model.dynamics import is_short_run
    from evojax_motion.run import compilation
    from evojax_motion.run import training as train
    from evojax_motion.run.workflow import make_robot_dynamics
    from evojax_motion.settings import load_config

    cfg = load_config(TINY, ["train.plots=false"])
    assert is_short_run(cfg.evolution.generations, cfg.evolution.conditions)
    robot, dyn = make_robot_dynamics(cfg)
    stages: list = []

    def stages_stand_in(*args, **kwargs):
        stages.append(kwargs["short_run"])
        raise _Stop

    monkeypatch.setattr(sharding, "one_device_stages", stages_stand_in)
    db, conditions = compilation.expected_inputs(cfg, robot)
    for kwargs, expected in (({}, False), ({"short_run": True}, True)):
        with pytest.raises(_Stop):
            compilation.compile_generation_step(cfg, robot, dyn, db, conditions, **kwargs)
        assert stages.pop() is expected

    calls: list = []

    def step_stand_in(*args, **kwargs):
        calls.append(kwargs.get("short_run"))
        raise _Stop

    monkeypatch.setattr(compilation, "compile_generation_step", step_stand_in)
    with pytest.raises(_Stop):
        train.run_training(cfg, tmp_path / "run", progress=False)
    assert calls == [True, True]  # the early compile (its failure is left to the foreground)


def test_a_short_run_takes_gpu_memory_as_it_needs_it(tmp_path, monkeypatch):
    """`run.memory.gpu_memory_on_demand`: a short run turns JAX's GPU memory reservation off
    (it reads the variable when its backend starts, so `train` sets it before anything starts
    one); a long run and a user's own setting are left alone."""
    from evojax_motion.cli.entry import main
    from evojax_motion.run import cache
    from evojax_motion.run import training as train
    from evojax_motion.run.memory import PREALLOCATE_ENV, gpu_memory_on_demand
    from evojax_motion.settings import load_config

    monkeypatch.delenv(PREALLOCATE_ENV, raising=False)
    long_run = load_config(TINY, ["evolution.generations=100000"])
    assert not gpu_memory_on_demand(long_run) and PREALLOCATE_ENV not in os.environ
    monkeypatch.setenv(PREALLOCATE_ENV, "true")
    assert not gpu_memory_on_demand(load_config(TINY, [])) and os.environ[PREALLOCATE_ENV] == "true"
    monkeypatch.delenv(PREALLOCATE_ENV)
    seen: list = []  # the variable when `train` turns on the cache, which starts the backend
    monkeypatch.setattr(
        cache, "enable_compile_cache", lambda: seen.append(os.getenv(PREALLOCATE_ENV))
    )
    monkeypatch.setattr(train, "run_training", lambda *args, **kwargs: None)
    assert main(["train", str(TINY), "--out", str(tmp_path / "run")]) == 0
    assert seen == ["false"]


def _db(path):
    from evojax_motion.motion.database import load_database

    return load_database(path)[0]


def _metrics(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_tiny_run_outputs_and_invariants(tiny_run):
    from evojax_motion.run.training import METRIC_FIELDS

    out, summary, cfg = tiny_run
    g_total = cfg.evolution.generations
    rows = _metrics(out)
    assert [r["generation"] for r in rows] == list(range(1, g_total + 1))
    assert all(tuple(r) == METRIC_FIELDS for r in rows)

    # db_cost_mean never increases over a fixed set of filled slots (a slot filled for the first
    # time may be dearer than the mean; per slot, costs never increase: checked below)
    costs = [r["db_cost_mean"] for r in rows]
    pairs = [(a, b) for a, b in itertools.pairwise(rows) if a["n_valid"] == b["n_valid"]]
    assert len(pairs) >= g_total - 2, [r["n_valid"] for r in rows]
    assert all(b["db_cost_mean"] <= a["db_cost_mean"] for a, b in pairs), costs
    assert [r["n_valid"] for r in rows] == sorted(r["n_valid"] for r in rows)
    assert all(r["n_replaced"] <= cfg.evolution.conditions for r in rows)

    # summary: the reduction gen 1 -> last and the human deviation, as in the metrics
    assert summary["generations"] == g_total
    assert summary["db_cost_gen1"] == costs[0] and summary["db_cost_last"] == costs[-1]
    assert summary["db_cost_reduction_pct"] == pytest.approx(
        100 * (costs[0] - costs[-1]) / costs[0], abs=1e-3
    )
    assert summary["human_deviation_deg"] == rows[-1]["human_deviation_deg"] > 0
    assert json.loads((out / "summary.json").read_text())["db_final"] == str(out / "db_final.npz")

    # the human originals never change: bit for bit, initial vs final
    first, gen1, final = (
        _db(out / "db_initial.npz"),
        _db(out / "db_gen1.npz"),
        _db(out / "db_final.npz"),
    )
    n_human = int((first.origin == 0).sum())
    assert n_human == cfg.demos.count
    for key in DB_KEYS:
        a, b = getattr(first, key)[:n_human], getattr(final, key)[:n_human]
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), key
    # per slot: final cost <= generation-1 cost; generation index within 1..G
    ev = slice(n_human, None)
    kept = gen1.valid[ev]
    assert kept.any() and final.valid[ev][kept].all()
    assert (final.cost[ev][kept] <= gen1.cost[ev][kept]).all()
    gen = final.generation[ev][final.valid[ev]]
    assert ((gen >= 1) & (gen <= g_total)).all() and gen.max() > 1  # later offspring survive
    assert (first.generation == 0).all() and not first.valid[ev].any()

    # files of the run
    for name in ("config.yaml", "robot.xml", "plots/costs.png", "plots/joint_angles.png"):
        assert (out / name).is_file(), name
    assert (out / "plots/costs.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.rglob(".*.tmp")), "temporary files left behind"
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == [
        g_total - 1,
        g_total,
    ]


@pytest.mark.slow
def test_stored_costs_match_mujoco(tiny_run):
    """Eq. 5 costs in db_final.npz vs torques from C MuJoCo's mj_inverse on the stored
    trajectories (timegrid derivatives in float64, trapezoid weights)."""
    import mujoco

    from evojax_motion.model.robot import load_robot, mj_inverse_torques
    from evojax_motion.motion.timegrid import make_time_grid

    out, _, cfg = tiny_run
    db = _db(out / "db_final.npz")
    robot = load_robot(cfg.robot.name)
    model = robot.mj_model
    data = mujoco.MjData(model)
    grid = make_time_grid(db.q.shape[1], np.float64)
    checked = 0
    for i in np.flatnonzero(db.valid):
        q = db.q[i].astype(np.float64)
        dur = float(db.duration[i])
        qd, qdd = (grid.d1 @ q) / dur, (grid.d2 @ q) / dur**2
        tau = mj_inverse_torques(robot, q, qd, qdd, data)
        cost = 0.5 * dur * np.sum(grid.w * np.sum(tau**2, axis=1))
        assert db.cost[i] == pytest.approx(cost, rel=TOL_COST_REL), (i, db.origin[i])
        checked += 1
    assert checked == db.valid.sum() > cfg.demos.count  # humans and evolved slots alike


# A fork server of `evojax-motion` runs: for each request (a JSON line on stdin: index,
# before|after, count file, log file, CLI args) it forks a process that runs the CLI and SIGKILLs
# itself at one of the run's file-system operations (the moments at which what is on disk
# changes), and answers the process's exit status (-9: killed). Index -1: no kill; the number of
# operations is written to the count file at the end. Every run is a process of its own, as from
# the shell; the server only imports what a run imports once, not in each of them (seconds each).
_KILL_DRIVER = """
import json, os, shutil, signal, sys, traceback

cache = os.environ["JAX_COMPILATION_CACHE_DIR"]  # XLA's cache files are not the run's
index, when, seen = -1, "none", 0


def hook(real):
    def op(*args, **kwargs):
        global seen
        if args and str(args[0]).startswith(cache):
            return real(*args, **kwargs)
        mine, seen = seen, seen + 1  # numbered on entry (os.makedirs calls os.mkdir)
        if mine == index and when == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        try:
            return real(*args, **kwargs)
        finally:  # also after one that failed (mkdir of an existing folder)
            if mine == index and when == "after":
                os.kill(os.getpid(), signal.SIGKILL)

    return op


for name in ("replace", "rename", "fsync", "mkdir", "makedirs", "unlink", "remove", "rmdir"):
    setattr(os, name, hook(getattr(os, name)))
shutil.rmtree = hook(shutil.rmtree)

from evojax_motion.cli.entry import main

# what a run imports (the JAX backend starts in each forked run: nothing runs here)
import jax.numpy, orbax.checkpoint, yaml  # noqa: E401
import evojax_motion.run.checkpoint  # noqa: E401
import evojax_motion.run.compilation, evojax_motion.run.training  # noqa: E401
import evojax_motion.run.workflow  # noqa: E401

for line in sys.stdin:
    index, when, count_file, log, *argv = json.loads(line)
    pid = os.fork()
    if pid == 0:
        seen = 0
        out = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(out, 1)
        os.dup2(out, 2)
        status = 1
        try:
            status = main(argv)
            with open(count_file, "w") as f:
                f.write(str(seen))
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
    _, wait_status = os.waitpid(pid, 0)
    print(os.waitstatus_to_exitcode(wait_status), flush=True)
"""
N_KILLS = 10


def _check_visible_files(out: Path) -> None:
    """What a killed run leaves is complete: every file it shows reads back (atomic writes)."""
    import yaml

    from evojax_motion.motion.database import load_database

    if (out / "config.yaml").exists():
        assert isinstance(yaml.safe_load((out / "config.yaml").read_text()), dict)
    if (out / "metrics.jsonl").exists():
        _metrics(out)
    for name in ("db_initial.npz", "db_gen1.npz", "db_final.npz"):
        if (out / name).exists():
            load_database(out / name)


KILL_ARGS = ["train", str(TINY), "--quiet", "--set", "train.plots=false"]


class _KillServer:
    """`_KILL_DRIVER` in a subprocess. It inherits the test run's XLA cache (conftest), so its
    runs reuse the fixtures' compiles."""

    def __init__(self, folder: Path):
        driver = folder / "driver.py"
        driver.write_text(_KILL_DRIVER)
        env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO))
        self.errors = folder / "driver.err"  # the server's own (each run has its log file)
        with self.errors.open("w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, str(driver)],
                env=env,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )

    def launch(self, out: Path, index: int, when: str) -> tuple[int, Path, str]:
        """A run of ``KILL_ARGS --out out``: ``(exit status, count file, its stdout + stderr)``."""
        count, log = out.with_name(f"{out.name}.count"), out.with_name(f"{out.name}.log")
        request = [index, when, str(count), str(log), *KILL_ARGS, "--out", str(out)]
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], 600)
        line = self.proc.stdout.readline() if ready else ""
        if not line:  # the server died or the run hangs
            self.proc.kill()
            pytest.fail(f"kill server: no answer\n{self.errors.read_text()[-3000:]}")
        return int(line), count, log.read_text() if log.exists() else ""

    def close(self) -> None:
        self.proc.stdin.close()  # the server's loop ends
        self.proc.wait(timeout=60)
        self.proc.stdout.close()


def _assert_same_run(ref_out: Path, out: Path) -> None:
    """Final databases equal bit for bit; metrics equal apart from the wall-clock times."""
    ref, got = _db(ref_out / "db_final.npz"), _db(out / "db_final.npz")
    for key in DB_KEYS:
        assert getattr(ref, key).tobytes() == getattr(got, key).tobytes(), (out, key)

    def rows(folder):
        clock = ("seconds", "finished_at")
        return [{k: v for k, v in r.items() if k not in clock} for r in _metrics(folder)]

    assert rows(out) == rows(ref_out), out


@pytest.fixture(scope="module")
def kill_driver(tmp_path_factory):
    """``(kill server, number of file-system operations of an uninterrupted run, its folder)``:
    configs/tiny.yaml run to the end in another process by `_KILL_DRIVER` (no kill)."""
    folder = tmp_path_factory.mktemp("kills")
    server = _KillServer(folder)
    status, count, log = server.launch(folder / "whole", -1, "none")
    assert status == 0, log[-3000:]
    yield server, int(count.read_text()), folder / "whole"
    server.close()


@pytest.mark.slow
def test_same_config_and_seed_give_a_bit_identical_database(tiny_run, kill_driver):
    """Determinism on one device (CPU): the same config and seed, run in another process, give
    the same final database bit for bit and the same metrics."""
    _assert_same_run(tiny_run[0], kill_driver[2])


@pytest.mark.slow
def test_sigkill_at_10_random_moments_then_resume_is_bit_identical(tiny_run, kill_driver, tmp_path):
    """10 runs of configs/tiny.yaml, each SIGKILLed at a seeded random moment (one in each
    tenth of the run's file-system operations, just before or just after it), then resumed
    (or restarted, when the kill came before the run folder held a config): every resume
    completes without meeting a damaged checkpoint, and its final database and metrics equal
    the uninterrupted run's, bit for bit."""
    from evojax_motion.cli.entry import main

    server, n_ops, _ = kill_driver
    assert n_ops > 4 * N_KILLS, n_ops
    rng = np.random.default_rng(20)
    kills = [
        (int(rng.integers(n_ops * i // N_KILLS, n_ops * (i + 1) // N_KILLS)), str(when))
        for i, when in enumerate(rng.choice(["before", "after"], N_KILLS))
    ]
    for k, (index, when) in enumerate(kills):
        out = tmp_path / f"killed{k}"
        status, _, log = server.launch(out, index, when)
        assert status == -9, (index, when, log[-3000:])
        _check_visible_files(out)
        resume = ["--resume"] if (out / "config.yaml").is_file() else []
        assert main([*KILL_ARGS, "--out", str(out), *resume]) == 0, (index, when)
        summary = json.loads((out / "summary.json").read_text())
        assert summary["checkpoint_problems"] == [], (index, when, summary)
        _assert_same_run(tiny_run[0], out)
        assert not list(out.rglob(".*.tmp")), (index, when)


@pytest.mark.slow
def test_damaged_latest_checkpoint_falls_back(tiny_run, tmp_path, capsys, monkeypatch):
    """A resume skips a damaged step with one warning line, and without the tracebacks of
    callbacks on orbax's closed event loop (`run.checkpoint._ignore_closed_loop_callbacks`)."""
    import shutil
    import time

    from evojax_motion.run.training import run_training
    from evojax_motion.settings import load_config

    ref_out, _, cfg = tiny_run
    out = tmp_path / "run"
    shutil.copytree(ref_out, out)
    g_total = cfg.evolution.generations
    for f in glob.glob(f"{out}/checkpoints/{g_total}/state/**/d/*", recursive=True):
        Path(f).write_bytes(b"")
    (out / "db_final.npz").unlink()

    unraisable: list = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    summary = run_training(load_config(TINY), out, resume=True, progress=False)
    time.sleep(0.5)  # callbacks of the failed restore come from tensorstore's threads
    assert [str(u.exc_value) for u in unraisable] == []
    err = capsys.readouterr().err
    assert f"warning: checkpoint {g_total}: unreadable" in err
    assert summary["resumed_from"] == g_total - 1
    assert len(summary["checkpoint_problems"]) == 1
    ref, got = _db(ref_out / "db_final.npz"), _db(out / "db_final.npz")
    for key in DB_KEYS:
        assert getattr(ref, key).tobytes() == getattr(got, key).tobytes(), key


@pytest.mark.slow
def test_sparse_checkpoints_resume_to_the_same_run(tiny_run, tmp_path):
    """``train.checkpoint_every: 3`` over 4 generations: checkpoints after generations 0, 3 and
    4 only, the same database and metrics as checkpointing every generation; a run stopped after
    generation 4 but before its checkpoint resumes from 3, recomputes 4 and ends the same."""
    from evojax_motion.run.training import CHECKPOINT_DIR, run_training
    from evojax_motion.settings import load_config

    ref_out, _, _ = tiny_run
    sparse = ["train.checkpoint_every=3", "train.max_to_keep=5", "train.plots=false"]
    cfg = load_config(TINY, sparse)
    out = tmp_path / "run"
    run_training(cfg, out, progress=False)

    def steps():
        return sorted(int(p.name) for p in (out / CHECKPOINT_DIR).iterdir() if p.name.isdigit())

    assert steps() == [0, 3, 4]
    _assert_same_run(ref_out, out)
    import shutil

    shutil.rmtree(out / CHECKPOINT_DIR / "4")
    (out / "db_final.npz").unlink()
    summary = run_training(cfg, out, resume=True, progress=False)
    assert summary["resumed_from"] == 3
    assert summary["checkpoint_problems"] == []
    assert steps() == [0, 3, 4]
    _assert_same_run(ref_out, out)


@pytest.mark.slow
def test_an_error_queueing_the_next_generation_comes_after_the_files_of_the_last(
    tiny_run, tmp_path, monkeypatch
):
    """`train` queues generation g + 1 before writing generation g's files; where queueing it
    fails, generation g's metrics and checkpoint are written first, then the error is raised,
    and a resume continues from g to the uninterrupted run's results."""
    from evojax_motion.run import compilation
    from evojax_motion.run import training as train
    from evojax_motion.settings import load_config

    real = compilation.compile_generation_step

    def failing_at_3(*args, **kwargs):
        step = real(*args, **kwargs)

        def call(db, conditions, generation):
            if int(generation) == 3:
                raise RuntimeError("queueing generation 3 failed")
            return step(db, conditions, generation)

        return call

    monkeypatch.setattr(compilation, "compile_generation_step", failing_at_3)
    cfg = load_config(TINY, ["train.plots=false"])
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="generation 3"):
        train.run_training(cfg, out, progress=False)
    assert [r["generation"] for r in _metrics(out)] == [1, 2]
    assert (out / train.CHECKPOINT_DIR / "2").is_dir()
    monkeypatch.setattr(compilation, "compile_generation_step", real)
    summary = train.run_training(cfg, out, resume=True, progress=False)
    assert summary["resumed_from"] == 2
    _assert_same_run(tiny_run[0], out)


def _every_checkpoint_restores(out: Path, cfg) -> list[int]:
    """The run's checkpoint steps, after checking that each restores as the run's state, with
    its generation, and passes its checksum."""
    from evojax_motion.motion.database import load_database
    from evojax_motion.run.training import CHECKPOINT_DIR, checkpoint_template

    template = checkpoint_template(cfg, load_database(out / "db_initial.npz")[0])
    with ck.open_manager(out / CHECKPOINT_DIR, cfg.train.max_to_keep) as manager:
        steps = sorted(manager.all_steps())
        for step in steps:
            restored, problem = ck.restore_step(manager, step, template)
            assert restored is not None, (out, step, problem)
            assert int(restored.state["generation"]) == step
    return steps


def _lock_holder(out: Path) -> int | None:
    from evojax_motion.run.lock import LOCK_FILE

    try:
        return int(json.loads((out / LOCK_FILE).read_text())["pid"])
    except (OSError, ValueError, KeyError):  # not there, or not yet written
        return None


@pytest.mark.slow
def test_a_second_train_of_a_run_folder_in_use_is_refused(tiny_run, tmp_path):
    """Two `train` processes on one folder: while the first runs (stopped with SIGSTOP for the
    time being, so that it is surely still running), a second one, and a `train --resume`,
    exit with status 2 and one line naming the first's process; the first then finishes with
    every checkpoint intact and the results of a run alone."""
    from evojax_motion.run.lock import LOCK_FILE

    ref_out, _, cfg = tiny_run
    out = tmp_path / "run"
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO))
    cli = [sys.executable, "-m", "evojax_motion.cli", *KILL_ARGS, "--out", str(out)]
    log = tmp_path / "first.log"
    with log.open("w") as f:
        first = subprocess.Popen(cli, env=env, stdout=f, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 600
        while _lock_holder(out) != first.pid:
            assert first.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.05)
        first.send_signal(signal.SIGSTOP)
        try:
            refusal = rf"error: {re.escape(str(out))}: in use by process {first.pid} "
            refusal += r"\(started \d\d:\d\d:\d\d\)\n"
            for extra in ([], ["--resume"]):
                second = subprocess.run(
                    [*cli, *extra], env=env, capture_output=True, text=True, timeout=600
                )
                assert second.returncode == 2, (extra, second.stderr[-3000:])
                assert re.fullmatch(refusal, second.stderr), (extra, second.stderr[-3000:])
        finally:
            first.send_signal(signal.SIGCONT)
        assert first.wait(timeout=600) == 0, log.read_text()[-3000:]
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    _assert_same_run(ref_out, out)
    assert _every_checkpoint_restores(out, cfg) == _every_checkpoint_restores(ref_out, cfg)
    assert not (out / LOCK_FILE).exists()


# As tensorstore reports a full disk in orbax's save (from a real one)
_TENSORSTORE_ENOSPC = (
    'RESOURCE_EXHAUSTED: Error writing "db.q/0" in OCDBT database at local file "{}": Failed '
    "to write 8050 bytes to file 14: No space left on device [os_error_code='28']"
)


@pytest.mark.slow
@pytest.mark.parametrize("where", ["checkpoint", "metrics"])
def test_a_full_disk_stops_a_run_with_one_line_and_it_resumes(
    tiny_run, tmp_path, monkeypatch, capsys, where
):
    """The disk fills up at generation 3, in its checkpoint (orbax's save raises tensorstore's
    error) or in the metrics written after it (``fsync``, which names no file): `train` exits
    with status 2 and one line naming the step's folder or the file; ``--resume`` then ends in
    the uninterrupted run's results."""
    import orbax.checkpoint as ocp

    from evojax_motion.cli.entry import main

    out = tmp_path / "run"
    args = [*KILL_ARGS, "--out", str(out)]
    if where == "checkpoint":
        real_save = ocp.CheckpointManager.save

        def save(self, step, *a, **kw):
            if step == 3:
                raise ValueError(_TENSORSTORE_ENOSPC.format(self.directory))
            return real_save(self, step, *a, **kw)

        monkeypatch.setattr(ocp.CheckpointManager, "save", save)
        named, resumed_from = out / "checkpoints" / "3", 2
    else:
        if not Path("/proc/self/fd").is_dir():
            pytest.skip("needs /proc/self/fd to tell which file a descriptor is")
        real_fsync, metrics_writes = os.fsync, []

        def fsync(fd):
            if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")).startswith(".metrics.jsonl."):
                metrics_writes.append(fd)
                if len(metrics_writes) == 4:  # the empty file, then after generations 1, 2, 3
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real_fsync(fd)

        monkeypatch.setattr(os, "fsync", fsync)
        named, resumed_from = out / "metrics.jsonl", 3
    assert main(args) == 2
    err = capsys.readouterr().err  # the run's log lines, then the error
    assert err.splitlines()[-1] == f"error: {named}: {os.strerror(errno.ENOSPC)}"
    assert err.count("error:") == 1 and "Traceback" not in err
    monkeypatch.undo()
    assert main([*args, "--resume"]) == 0
    assert json.loads((out / "summary.json").read_text())["resumed_from"] == resumed_from
    _assert_same_run(tiny_run[0], out)


def test_a_run_folder_of_an_older_version_resumes_with_new_keys_at_their_defaults(tmp_path):
    """A run's config.yaml written before a setting existed (here ``train.checkpoint_every``)
    still matches the same config with that setting at its default; at another value it is
    another config."""
    import yaml

    from evojax_motion.settings import config_to_dict, load_config
    from evojax_motion.settings.run import TrainSettings

    default = TrainSettings().checkpoint_every
    mine = config_to_dict(load_config(TINY, [f"train.checkpoint_every={default}"]))
    older = yaml.safe_load(yaml.safe_dump(mine))
    del older["train"]["checkpoint_every"]
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.yaml").write_text(yaml.safe_dump(older))
    assert check_run_dir(out, mine, resume=True) is True
    other = config_to_dict(load_config(TINY, [f"train.checkpoint_every={default + 1}"]))
    with pytest.raises(UserError, match=r"train\.checkpoint_every"):
        check_run_dir(out, other, resume=True)


# ------------------------------------------------------------------------------ bad input


def _snapshot(folder: Path) -> dict:
    return {
        str(p): (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.rglob("*") if p.is_file()
    }


@pytest.mark.parametrize(
    "args, message",
    [
        (["--set", "evolution.generatons=3"], "evolution.generatons: unknown key"),
        (["--set", "demos.count=-1"], "demos.count: expected"),
        (["--set", "demos_file=/nonexistent/demos.npz"], "database file not found"),
        (["--set", "train.plot_condition=99"], "train.plot_condition: expected <"),
        (["--resume"], "no run to resume"),
    ],
)
def test_cli_refuses_bad_input_and_writes_nothing(tmp_path, capsys, args, message):
    from evojax_motion.cli.entry import main

    out = tmp_path / "run"
    status = main(["train", str(TINY), "--out", str(out), "--quiet", *args])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not out.exists()


@pytest.mark.slow
def test_cli_refuses_another_configs_run(tiny_run, capsys):
    from evojax_motion.cli.entry import main

    out = tiny_run[0]
    before = _snapshot(out)
    for extra in ([], ["--resume"]):
        status = main(["train", str(TINY), "--out", str(out), "--set", "seed=7", *extra])
        err = capsys.readouterr().err
        assert status == 2 and "holds the run of another config: seed (0 there, 7 here)" in err
    status = main(["train", str(TINY), "--out", str(out)])  # same config, no --resume
    assert status == 2 and "pass --resume" in capsys.readouterr().err
    assert _snapshot(out) == before


@pytest.mark.parametrize(
    "field, value",
    [
        ("max_to_keep", 1),
        ("checkpoint_every", 0),
        ("checkpoint_every", True),
        ("checkpoint_every", 2.0),
        ("plot_condition", -1),
        ("plot_condition", 1.5),
    ],
)
def test_train_settings_reject_bad_values(field, value):
    from evojax_motion.settings.run import TrainSettings

    with pytest.raises(ValueError, match=rf"^{field}: expected"):
        TrainSettings(**{field: value})
