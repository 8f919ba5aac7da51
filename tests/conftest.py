"""Shared test settings: CPU, deterministic, x64 on request."""

import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One persistent XLA cache for the whole session: the controller makes it before pytest-xdist
# starts its workers, which inherit the variable, as do the subprocesses, the notebook kernel and
# the command-line tools (`compile_cache.CACHE_ENV`) the tests start. The same programs (the tiny
# config's generation step, the online query of the test database) are then compiled once, not
# once per process. Never the user's own cache: a fresh directory per session.
_OWN_CACHE = "PYTEST_XDIST_WORKER" not in os.environ and "EVOJAX_TEST_XLA_CACHE" not in os.environ
if _OWN_CACHE:
    os.environ["EVOJAX_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="evojax-tests-xla-")
if "EVOJAX_TEST_XLA_CACHE" in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["EVOJAX_TEST_XLA_CACHE"]
    os.environ["EVOJAX_MOTION_JAX_CACHE"] = os.environ["EVOJAX_TEST_XLA_CACHE"]
    # every program, not only those that took >= 1 s to compile (as the command line does)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"

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


@pytest.fixture
def x64():
    """Run the test body with float64 enabled (accuracy checks against C MuJoCo / SciPy)."""
    with jax.enable_x64(True):
        yield


def pytest_unconfigure(config):
    """The session's XLA cache goes with the session (the process that made it removes it)."""
    if _OWN_CACHE:
        shutil.rmtree(os.environ["EVOJAX_TEST_XLA_CACHE"], ignore_errors=True)
