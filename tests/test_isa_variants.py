"""The rounding-sensitive tests (marker ``isa_sensitive``) under another x86-64 instruction set,
and with them the tests that need the optimisation level that ships (marker ``shipped_level``).

XLA:CPU compiles for the best instruction set of the CPU it runs on, so float32 (and float64)
results differ in their last bits from one CPU to another. Most tests compare with tolerances far
above that; those marked ``isa_sensitive`` assert a quantity that such differences can move
across a threshold (a non-convex optimisation's outcome over many problems, a rank decision), and
their tolerances come from measured spreads. Here they run again in a fresh pytest process with
XLA's ``--xla_cpu_max_isa`` capped, as on an older or different CPU: a tolerance fitted to one
machine's values fails ``make test`` on this one.

The test run compiles at XLA's backend optimisation level 0 (tests/conftest.py); this process
compiles at the default level, as the tool does. The ``shipped_level`` tests (two programs that
must give bit-identical results) run only here; the ``isa_sensitive`` ones run in both.

Which capped ISA: the other kind of CPU the suite meets. Where this CPU has AVX-512, AVX2 (the
default of a CPU without it); elsewhere SSE4.2 (a narrower vector width than the default AVX2).
Each capped run costs ~50 s on 2 CPU cores (its programs compile again), so one runs by default.
``EVOJAX_TEST_ISAS``: the comma-separated ISAs to run instead (e.g. ``SSE4_2,AVX2``; empty: none).
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import LEVEL_FLAG, SHIPPED_LEVEL_ENV

REPO = Path(__file__).resolve().parents[1]
MARKERS = ("isa_sensitive", "shipped_level")
# s: one capped run of the marked tests (~50 s on 2 CPU cores otherwise idle; a fresh XLA cache:
# their programs compile again for the capped ISA, and the demonstrations are synthesised again)
TIMEOUT_S = 900
# The variables through which the parent test run hands its workers and subprocesses its XLA
# cache and xdist role: the child makes and removes its own cache (tests/conftest.py).
_PARENT_ONLY = (
    "EVOJAX_TEST_XLA_CACHE", "JAX_COMPILATION_CACHE_DIR", "EVOJAX_MOTION_JAX_CACHE",
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "PYTEST_XDIST_WORKER",
    "PYTEST_XDIST_WORKER_COUNT", "PYTEST_XDIST_TESTRUNUID", "PYTEST_CURRENT_TEST",
    "PYTEST_ADDOPTS", SHIPPED_LEVEL_ENV,
)  # fmt: skip


def cpu_flags() -> set[str] | None:
    """The CPU's feature flags (Linux ``/proc/cpuinfo``), None where unreadable."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    match = re.search(r"^flags\s*:(.*)$", text, re.MULTILINE)
    return None if match is None else set(match.group(1).split())


def default_isa(flags: set[str] | None) -> str:
    """The capped ISA to run by default on a CPU of these flags (module docstring)."""
    return "AVX2" if flags is not None and "avx512f" in flags else "SSE4_2"


ISAS = tuple(filter(None, os.environ.get("EVOJAX_TEST_ISAS", default_isa(cpu_flags())).split(",")))


def marked_modules() -> list[str]:
    """The test modules with a test of one of `MARKERS` (relative to the repository)."""
    return sorted(
        str(p.relative_to(REPO))
        for p in (REPO / "tests").rglob("test_*.py")
        if p.name != Path(__file__).name
        and any(f"pytest.mark.{m}" in p.read_text() for m in MARKERS)
    )


def capped_env(isa: str) -> dict[str, str]:
    """This process's environment with ``--xla_cpu_max_isa={isa}`` in XLA_FLAGS (replacing any
    given), at XLA's default optimisation level, without the parent test run's cache and xdist
    variables."""
    env = {k: v for k, v in os.environ.items() if k not in _PARENT_ONLY}
    dropped = ("--xla_cpu_max_isa", LEVEL_FLAG)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith(dropped)]
    env["XLA_FLAGS"] = " ".join([*flags, f"--xla_cpu_max_isa={isa}"])
    env[SHIPPED_LEVEL_ENV] = "1"
    env["JAX_PLATFORMS"] = "cpu"
    return env


@pytest.mark.slow
@pytest.mark.parametrize("isa", ISAS)
def test_marked_tests_pass_at_the_shipped_level_with_a_capped_isa(isa):
    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip(f"--xla_cpu_max_isa caps x86-64 instruction sets; this is {platform.machine()}")
    modules = marked_modules()
    assert modules, f"no test is marked {' or '.join(MARKERS)}: the markers or this scan are broken"
    cmd = [sys.executable, "-m", "pytest", "-q", "--tb=short", "-p", "no:xdist",
           "-p", "no:cacheprovider", "-m", " or ".join(MARKERS), *modules]  # fmt: skip
    try:
        done = subprocess.run(
            cmd, cwd=REPO, env=capped_env(isa), capture_output=True, text=True, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else e.stdout or ""
        msg = f"--xla_cpu_max_isa={isa}: the marked tests ran past {TIMEOUT_S} s"
        pytest.fail(f"{msg}\n{out[-4000:]}")
    assert done.returncode == 0, (
        f"--xla_cpu_max_isa={isa}: `{' '.join(cmd[2:])}` exited {done.returncode}\n"
        f"{done.stdout[-6000:]}\n{done.stderr[-2000:]}"
    )
