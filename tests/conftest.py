"""Shared test settings: CPU, deterministic, quicker XLA compiles, x64 on request."""

import os
import shutil
import subprocess
import sys
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One persistent XLA cache for the whole test run: the controller makes it before pytest-xdist
# starts its workers, which inherit the variable, as do the subprocesses, the notebook kernel and
# the command-line tools (`run.cache.CACHE_ENV`) the tests start. The same programs (the tiny
# config's generation step, the online query of the test database) are then compiled once, not
# once per process. Never the user's own cache: a fresh directory per test run.
_OWN_CACHE = "PYTEST_XDIST_WORKER" not in os.environ and "EVOJAX_TEST_XLA_CACHE" not in os.environ
if _OWN_CACHE:
    os.environ["EVOJAX_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="evojax-tests-xla-")
if "EVOJAX_TEST_XLA_CACHE" in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["EVOJAX_TEST_XLA_CACHE"]
    os.environ["EVOJAX_MOTION_JAX_CACHE"] = os.environ["EVOJAX_TEST_XLA_CACHE"]
    # every program, not only those that took >= 1 s to compile (as the command line does)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
# The tests' programs compile with XLA's CPU fusion emitters off, as those of
# `model.dynamics.unfused_cpu_program` always do: every test passes with its tolerances unchanged,
# and
# pytest takes ~60 % of the time (most of the suite is XLA compilation; 2 CPU cores:
# 230-234 s vs 365-394 s). For the test run only: its processes and those they start inherit
# XLA_FLAGS; a setting of the flag in the user's XLA_FLAGS wins. Spelt "=0", not "=false": the
# RNEA layout that `model.rnea.default_form` picks is then still the users' default one
# (vector on CPU), since it switches to "scalar" on "=false" only; checked below.
_FLAG = "--xla_cpu_use_fusion_emitters"


def _xla_knows(flag: str) -> bool:
    """Whether this jaxlib's XLA has ``flag`` (gone in jax 0.11; XLA exits on an unknown flag in
    XLA_FLAGS): tried in a child process (once per test run where it is known: the workers then
    inherit the flag and skip the trial)."""
    env = {**os.environ, "XLA_FLAGS": f"{flag}=0", "JAX_PLATFORMS": "cpu"}
    code = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True)
    return done.returncode == 0


_SET_FLAG = _FLAG not in os.environ.get("XLA_FLAGS", "") and _xla_knows(_FLAG)
if _SET_FLAG:
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FLAG}=0".strip()
# The tests' programs also compile at XLA's backend (LLVM) optimisation level 0, as the one-shot
# programs of `compile_options.ONE_SHOT` do: the same HLO, other machine code, results that
# differ by rounding. `make test` on 2 CPU cores: 412 s against 559-571 s at the default level.
# Two kinds of tests need the level that ships, and run at it in the subprocess of
# tests/test_isa_variants.py (with the instruction set capped): those marked `shipped_level`
# (two programs must give bit-identical results, which at level 0 they do not) and those marked
# `isa_sensitive` (their tolerances were measured at that level; the level-0 run is one more
# rounding they also pass). `EVOJAX_TEST_SHIPPED_LEVEL=1`, or the level in the user's XLA_FLAGS,
# keeps the level given.
LEVEL_FLAG = "--xla_backend_optimization_level"
SHIPPED_LEVEL_ENV = "EVOJAX_TEST_SHIPPED_LEVEL"
if LEVEL_FLAG not in os.environ.get("XLA_FLAGS", "") and os.environ.get(SHIPPED_LEVEL_ENV) != "1":
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {LEVEL_FLAG}=0".strip()
LEVEL_0 = f"{LEVEL_FLAG}=0" in os.environ.get("XLA_FLAGS", "").split()

import jax  # noqa: E402  (after the environment above)
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# Property tests draw the same examples on every run (a CI failure is then reproducible, never a
# coincidence of the draw); `HYPOTHESIS_PROFILE=explore pytest ...` draws new ones each run.
settings.register_profile("repeatable", derandomize=True, database=None)
settings.register_profile("explore")
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))

if "EVOJAX_TEST_XLA_CACHE" in os.environ:  # in case a plugin imported jax before this file
    jax.config.update("jax_compilation_cache_dir", os.environ["EVOJAX_TEST_XLA_CACHE"])

from evojax_motion.model.rnea import default_form  # noqa: E402

if _SET_FLAG and jax.default_backend() == "cpu" and default_form() != "vector":
    raise RuntimeError(
        f"tests/conftest.py: with {_FLAG}=0 the default RNEA layout on CPU is no longer the "
        "users' default ('vector'); the tests would run another layout than users get"
    )


def pytest_runtest_setup(item):
    """A `shipped_level` test is skipped where the programs compile at level 0 (above)."""
    if LEVEL_0 and item.get_closest_marker("shipped_level") is not None:
        pytest.skip(
            "bit-identical results of two programs hold at XLA's default optimisation level, "
            "not at level 0: run by tests/test_isa_variants.py"
        )


@pytest.fixture
def x64():
    """Run the test body with float64 enabled (accuracy checks against C MuJoCo / SciPy)."""
    with jax.enable_x64(True):
        yield


def pytest_unconfigure(config):
    """The test run's XLA cache goes with the run (the process that made it removes it)."""
    if _OWN_CACHE:
        shutil.rmtree(os.environ["EVOJAX_TEST_XLA_CACHE"], ignore_errors=True)


# ------------------------------------------------------------------ scheduling on xdist workers
# `make test` runs `pytest -n 2 --dist loadscope --no-loadscope-reorder`. Its work units are the
# test modules (a module's fixtures are built once, on one worker), except where modules build
# the same programs: those form one unit (`SHARED_GROUPS`, `pytest_xdist_make_scheduler`), so
# they run one after another on one worker and the later ones find the first one's compiles in
# the test run's XLA cache (side by side on two workers, both would compile them). The units are
# handed out heaviest first (`GROUP_SECONDS`: a unit's summed test seconds, setup included, in
# a `make test` run on 2 CPU cores with the compile flags above; test_isa_variants's estimated at
# the default level: their order is what counts; units under 5 s are left out, they go last;
# `pytest_collection_modifyitems` orders the tests so), so that no long unit starts last while
# the other worker has nothing left to do. (Not
# `--dist loadgroup` with `xdist_group` marks: pytest-xdist 3.8 puts the group into
# `item._nodeid`, which pytest 9 no longer reads, so every test would be a unit of its own and
# module fixtures would be built on both workers.)
SHARED_GROUPS = {
    # configs/tiny.yaml: test_train trains it first (setup programs, generation step, synthesised
    # demonstrations); the report of test_report's synthetic run (the tiny run's settings and
    # sizes) draws what the notebook, which trains the tiny run again, draws too; the documents'
    # commands train the tiny run and report on it, and train on the imported sample at the sizes
    # of test_import's training (`test_docs_commands.SUBSTITUTED`)
    "tiny": (
        "test_train", "test_numerical_faults", "test_demos", "test_report", "test_notebook",
        "test_import", "test_docs_commands",
    ),
    # online_support's cached query, reach checker and catcher (`functools.cache`: per process)
    "online": (
        "test_online", "test_catching", "test_export", "test_online_limits", "test_simulate",
    ),
}  # fmt: skip
GROUP_SECONDS = {
    "tiny": 213, "test_compile_optim": 178, "test_isa_variants": 70, "test_dynamics": 55,
    "online": 48, "test_distributed": 41, "test_parallel": 35, "test_evolution": 25,
    "test_bad_input": 24, "test_feasibility": 22, "test_examples": 19, "test_shipped": 14,
    "test_catch_success": 13, "test_linalg": 11, "test_basis": 9, "test_compile_interp": 9,
    "test_solvers": 9,
}  # fmt: skip
_GROUP_OF = {m: g for g, modules in SHARED_GROUPS.items() for m in modules}


def _unit(module: str) -> str:
    """The work unit of a test module (its name without ``.py``)."""
    return _GROUP_OF.get(module, module)


def pytest_collection_modifyitems(config, items):
    """Units heaviest first; a unit's modules in `SHARED_GROUPS` order; a module's tests as
    collected."""

    def rank(indexed):
        index, item = indexed
        module = item.path.stem
        unit = _unit(module)
        within = SHARED_GROUPS[unit].index(module) if unit in SHARED_GROUPS else 0
        return (-GROUP_SECONDS.get(unit, 0), unit, within, index)

    items[:] = [item for _, item in sorted(enumerate(items), key=rank)]


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadscope`` with `SHARED_GROUPS` as single units (`_unit`)."""
    from xdist.scheduler import LoadScopeScheduling

    if config.getvalue("dist") != "loadscope" or not hasattr(LoadScopeScheduling, "_split_scope"):
        return None  # (another pytest-xdist: its own loadscope, modules as units)

    class UnitScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            module = path.rsplit("/", 1)[-1].removesuffix(".py")
            return _unit(module) if module in _GROUP_OF else super()._split_scope(nodeid)

    return UnitScheduling(config, log)
