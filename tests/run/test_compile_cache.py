"""compile_cache: a traced program is reused across processes only when nothing it depends on
changed, a damaged file is traced again, and nothing is written without a cache directory."""

import json
import os
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from evojax_motion.run import cache as compile_cache

REPO = Path(__file__).resolve().parents[2]


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


TRACES = []


def _make_fn():
    """A new function object each time: JAX's in-memory trace cache is keyed by the function."""

    def fn(p: Pair, k):
        TRACES.append(1)  # runs once per trace, never when a traced program is reused
        return Pair(a=jnp.sin(p.a) * k, b=p.b @ p.b.T), jnp.sum(p.a)

    return fn


@contextmanager
def cache_at(folder):
    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(folder) if folder else None)
    try:
        yield
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


def _args(n=3):
    p = Pair(a=np.linspace(0.0, 1.0, n, dtype=np.float32), b=np.ones((n, 2), np.float32))
    return p, np.float32(2.0)


def _compile(parts="pair", n=3):
    args = _args(n)
    return compile_cache.compile_traced(jax.jit(_make_fn()), args, parts)(*args), args


def _expected(args):
    p, k = args
    return Pair(np.sin(p.a) * k, p.b @ p.b.T), np.sum(p.a)


TOL_REL = 1e-6  # float32 sin and a 3x2 product, against numpy


def _assert_matches(out, args):
    leaves = jax.tree_util.tree_leaves
    for got, want in zip(leaves(out), leaves(_expected(args)), strict=True):
        np.testing.assert_allclose(np.asarray(got), want, rtol=TOL_REL)


def test_second_compile_reuses_the_trace_and_keys_separate_programs(tmp_path):
    TRACES.clear()
    with cache_at(tmp_path):
        out, args = _compile()
        assert len(TRACES) == 1
        files = list((tmp_path / compile_cache.TRACED_DIR).glob("*.jaxexport"))
        assert len(files) == 1
        out2, _ = _compile()  # the same program from a new function object: loaded, not traced
        assert len(TRACES) == 1
        _assert_matches(out, args)
        _assert_matches(out2, args)
        assert isinstance(out2[0], Pair)  # the result tree comes back with its NamedTuple
        _compile(n=4)  # other shapes: another program
        _compile(parts="other")  # what the caller names differs: another program
        assert len(TRACES) == 3
        assert len(list((tmp_path / compile_cache.TRACED_DIR).glob("*.jaxexport"))) == 3
        assert not list((tmp_path / compile_cache.TRACED_DIR).glob(".*.tmp"))


def test_damaged_file_is_reported_and_traced_again(tmp_path, capsys):
    TRACES.clear()
    with cache_at(tmp_path):
        _compile()
        (path,) = (tmp_path / compile_cache.TRACED_DIR).glob("*.jaxexport")
        path.write_bytes(path.read_bytes()[:200])  # truncated
        out, args = _compile()
    err = capsys.readouterr().err
    assert f"{path}: unreadable traced program" in err
    assert len(TRACES) == 2
    _assert_matches(out, args)
    header = path.read_bytes().split(b"\n", 1)[0]  # written anew, whole
    assert json.loads(header)["namedtuples"] == [f"{__name__}:Pair"]


def test_without_a_cache_directory_nothing_is_written(tmp_path):
    TRACES.clear()
    with cache_at(None):
        out, args = _compile()
        out, args = _compile()
    assert len(TRACES) == 2
    _assert_matches(out, args)
    assert not list(tmp_path.iterdir())


def test_traced_program_names_its_function_and_takes_prng_keys(tmp_path):
    """`traced_program`: one trace per signature and process, reused by a new wrapper of the same
    function; another function with the same arguments and parts is another program; typed PRNG
    keys are arguments like any other."""
    traces = []

    def noisy(key, x):
        traces.append(1)
        return x + jax.random.normal(key, x.shape)

    def shifted(key, x):
        traces.append(1)
        return x + 1.0 + jax.random.normal(key, x.shape)

    key, x = jax.random.key(7), np.zeros(3, np.float32)
    want = np.asarray(jax.random.normal(key, (3,)))
    with cache_at(tmp_path):
        call = compile_cache.traced_program(jax.jit(noisy), "parts")
        np.testing.assert_array_equal(np.asarray(call(key, x)), want)
        np.testing.assert_array_equal(np.asarray(call(key, x)), want)  # compiled once: kept
        assert len(traces) == 1
        again = compile_cache.traced_program(jax.jit(noisy), "parts")  # as a new process would
        np.testing.assert_array_equal(np.asarray(again(key, x)), want)
        assert len(traces) == 1
        other = compile_cache.traced_program(jax.jit(shifted), "parts")
        np.testing.assert_array_equal(np.asarray(other(key, x)), want + 1.0)
        assert len(traces) == 2
    assert len(list((tmp_path / compile_cache.TRACED_DIR).glob("*.jaxexport"))) == 2


def test_precompiled_program_is_the_one_called_even_from_another_thread(tmp_path):
    """`TracedProgram.precompile` from shapes (in a `Background` thread, as `train` does) makes
    the program a later call with arrays of those shapes runs: one trace, one compile, the right
    result, ``out_info`` shaped like it; a call racing the precompile waits for it."""
    x, n = np.arange(4, dtype=np.float32), np.asarray(3, np.int32)
    for folder in (tmp_path, None):  # kept on disk, or not (no cache directory)
        traces = []

        def double(x, n, traces=traces):  # a new function: JAX's own trace cache knows none
            traces.append(1)
            return 2.0 * x + n

        with cache_at(folder):
            program = compile_cache.traced_program(jax.jit(double), "parts")
            specs = (jax.ShapeDtypeStruct((4,), np.float32), jax.ShapeDtypeStruct((), np.int32))
            background = compile_cache.Background(program.precompile, *specs)
            np.testing.assert_array_equal(np.asarray(program(x, n)), 2.0 * x + 3)  # may wait
            compiled = background.result()
            assert compiled.out_info.shape == (4,) and compiled.out_info.dtype == np.float32
            np.testing.assert_array_equal(np.asarray(program(x, n)), 2.0 * x + 3)
            assert len(traces) == 1


def test_key_changes_with_parts_shapes_precision_and_x64():
    args = _args()
    key = compile_cache.program_key("p", args)
    assert compile_cache.program_key("p", args) == key
    assert compile_cache.program_key("q", args) != key
    assert compile_cache.program_key("p", _args(4)) != key
    with jax.default_matmul_precision("highest"):
        assert compile_cache.program_key("p", args) != key
    with jax.enable_x64(True):
        assert compile_cache.program_key("p", args) != key


@pytest.mark.slow
def test_model_digest_is_stable_across_processes():
    """The key must not change between two processes that load the same robot model."""
    code = (
        "from evojax_motion.model.robot import load_robot; from evojax_motion.run.cache import "
        "model_digest; print(model_digest(load_robot('mahru_arm').mj_model))"
    )
    digests = {
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO
        ).stdout.strip()
        for _ in range(2)
    }
    assert len(digests) == 1 and len(digests.pop()) == 64


def test_background_runs_under_the_callers_settings_and_reraises():
    """JAX keeps x64 and the matmul precision per thread: the worker must see the caller's."""

    def settings():
        return jax.config.jax_default_matmul_precision, jnp.zeros(1).dtype

    with jax.default_matmul_precision("highest"), jax.enable_x64(True):
        assert compile_cache.Background(settings).result() == ("highest", jnp.float64)
    assert compile_cache.Background(settings).result()[1] == jnp.float32

    failing = compile_cache.Background(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        failing.result()


def test_a_program_that_cannot_be_saved_still_compiles(tmp_path, capsys, monkeypatch):
    """Serialization needs flatbuffers: without it the run goes on, warned, with nothing saved."""

    def no_flatbuffers(self, *a, **k):
        raise ImportError("Please install 'flatbuffers'")

    monkeypatch.setattr(jax.export.Exported, "serialize", no_flatbuffers)
    with cache_at(tmp_path):
        out, args = _compile()
    _assert_matches(out, args)
    assert "traced program not saved (Please install 'flatbuffers')" in capsys.readouterr().err
    assert not list((tmp_path / compile_cache.TRACED_DIR).glob("*"))


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="no per-thread priorities here")
def test_background_nice_lowers_only_its_own_thread():
    """``Background(..., nice=n)`` (the setup's precompile in `train`): its thread runs with the
    nice value raised by n, the caller's thread keeps its own."""

    def own():
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    base = own()
    assert compile_cache.Background(own, nice=5).result() == min(base + 5, 19)
    assert compile_cache.Background(own).result() == base
    assert own() == base


@pytest.mark.parametrize(("release", "expected_on"), [((0, 9, 2), False), ((0, 10, 2), True)])
def test_cache_stays_off_where_jaxlib_cannot_load_it(monkeypatch, tmp_path, release, expected_on):
    """On CPU a jaxlib before `FIRST_SAFE_CPU_CACHE_JAXLIB` (0.9.2 segfaults loading a cached
    program on AVX-512 hosts) gets no persistent cache; a later one gets the directory asked for."""
    if jax.default_backend() != "cpu":
        pytest.skip("the gate is for the CPU backend")
    import jaxlib.version

    monkeypatch.setattr(jaxlib.version, "__version_info__", release)
    monkeypatch.setenv(compile_cache.CACHE_ENV, str(tmp_path / "cache"))
    before = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
    try:
        compile_cache.enable_compile_cache()
        now = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
        assert (now == str(tmp_path / "cache")) == expected_on
        assert (tmp_path / "cache").exists() == expected_on
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
