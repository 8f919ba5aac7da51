"""On-disk caches that let the next run of the same program skip its compilation.

- **Compiled programs**: JAX's persistent compilation cache, in ``$EVOJAX_MOTION_JAX_CACHE``
  (default ``~/.cache/evojax-motion/jax``; ``off`` disables it). The command line turns it on
  (`enable_compile_cache`); in Python, ``jax.config.update("jax_compilation_cache_dir", ...)``.
- **Traced programs** (`compile_traced`): JAX finds a compiled program in its cache by the lowered
  program, so every process still traces and lowers the function first. For the generation step
  that is seconds (thousands of scalar dynamics operations through vmap and autodiff) next to a
  generation of about two on a 2-core CPU. `compile_traced` keeps the lowered program as well
  (``jax.export``, in ``traced/`` of the compilation cache directory, only while that cache is
  on) under a key of everything that determines it: this package's source, the versions of JAX
  and jaxlib, the backend and device count, the x64 and matmul-precision settings, the argument
  shapes and dtypes, and what the caller names (config sections, the robot model's compiled
  bytes). A file that cannot be read back is reported, removed and written anew.
  `traced_program` wraps a jitted function so that every call compiles through `compile_traced`
  (once per argument signature): the run's setup programs (demonstrations, costs, conditions)
  use it as the generation step does.
- **Results** (`result_path`): what the package computes from a config alone and would compute
  again, bit for bit, in the next process (the synthesised demonstrations: seconds of execution
  that no compilation cache removes), in ``results/`` of the same directory, under the same kind
  of key (so a new package source, JAX or backend computes them anew).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import hashlib
import importlib
import json
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import jax
import jaxlib.version
import numpy as np

CACHE_ENV = "EVOJAX_MOTION_JAX_CACHE"  # a directory, or "off"
TRACED_DIR = "traced"  # under the compilation cache directory
RESULTS_DIR = "results"  # ditto
_SUFFIX = ".jaxexport"


def enable_compile_cache() -> None:
    """Keep XLA's compiled programs (and `compile_traced`'s traced ones) on disk.

    ``$EVOJAX_MOTION_JAX_CACHE`` (default ``~/.cache/evojax-motion/jax``; ``off`` disables). A
    directory that cannot be made (read-only home), or a jaxlib that cannot load it safely
    (`compile_cache_loads_safely`), leaves the caches off.
    """
    where = os.environ.get(CACHE_ENV, str(Path.home() / ".cache" / "evojax-motion" / "jax"))
    if where.lower() == "off" or not compile_cache_loads_safely():
        return
    try:
        Path(where).mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    jax.config.update("jax_compilation_cache_dir", where)
    # JAX keeps only programs that took >= 1 s to compile by default; a run's setup compiles a
    # dozen that take 0.02-0.2 s each (0.5 s together on 2 CPU cores), paid again every run.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


# jaxlib releases before this one may crash loading a cached CPU program: 0.9.2 on an AVX-512 CPU
# logs "Target machine feature +prefer-no-scatter is not supported on the host machine" and
# segfaults in the second run of any command; 0.10.2 loads the same cache.
FIRST_SAFE_CPU_CACHE_JAXLIB = (0, 10)


def compile_cache_loads_safely() -> bool:
    """Whether this jaxlib and backend load programs from the persistent compilation cache
    safely (`FIRST_SAFE_CPU_CACHE_JAXLIB` on CPU; accelerators always): where not,
    `enable_compile_cache` leaves the caches off and every run compiles anew."""
    if jax.default_backend() != "cpu":
        return True
    return tuple(jaxlib.version.__version_info__[:2]) >= FIRST_SAFE_CPU_CACHE_JAXLIB


def traced_cache_dir() -> Path | None:
    """``<compilation cache>/traced``, or None when JAX's persistent cache is off."""
    return _cache_subdir(TRACED_DIR)


def _cache_subdir(name: str) -> Path | None:
    where = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
    return Path(where) / name if where else None


def result_path(parts: Any, suffix: str = ".npz") -> Path | None:
    """Where a result that ``parts`` (JSON-able: what it is and what it depends on, e.g. config
    sections and a model digest) determines is kept: ``<compilation cache>/results/<key>``, the
    key as `program_key`'s (package source, JAX versions, backend, settings, ``parts``); None
    when JAX's persistent cache is off. The caller reads, validates and writes the file."""
    folder = _cache_subdir(RESULTS_DIR)
    return None if folder is None else folder / f"{program_key(parts, ())}{suffix}"


@functools.cache
def source_digest() -> str:
    """sha256 of this package's Python source (every ``.py`` file, by relative path)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def model_digest(mj_model) -> str:
    """sha256 of a compiled MuJoCo model (its binary ``.mjb`` form): every constant of it."""
    import mujoco

    buf = np.empty(mujoco.mj_sizeModel(mj_model), np.uint8)
    mujoco.mj_saveModel(mj_model, None, buf)
    return hashlib.sha256(buf.tobytes()).hexdigest()


def signature(tree) -> tuple:
    """What a traced program depends on in its arguments: the tree structure and each leaf's
    shape, dtype and weak type (JSON-able; equal signatures trace to the same program)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    avals = [
        [list(np.shape(x)), _dtype_name(x), bool(getattr(x, "weak_type", False))] for x in leaves
    ]
    return str(treedef), avals


def _dtype_name(x) -> str:
    """``x``'s dtype: its own where it has one (PRNG key arrays have no NumPy dtype), else
    NumPy's for a Python scalar."""
    return str(x.dtype) if hasattr(x, "dtype") else str(np.result_type(x))


def program_key(parts: Any, args: tuple) -> str:
    """The cache key of the program ``parts`` names, traced for ``args`` (see the module doc)."""
    import jaxlib

    devices = jax.devices()
    record = {
        "parts": parts,
        "source": source_digest(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "backend": [jax.default_backend(), devices[0].device_kind, len(devices)],
        "x64": bool(jax.config.jax_enable_x64),  # type: ignore[attr-defined]
        "matmul_precision": str(jax.config.jax_default_matmul_precision),  # type: ignore[attr-defined]
        "args": signature(args),
    }
    text = json.dumps(record, sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()


def lower_traced(jitted, args: tuple, parts: Any, compiler_options: dict | None = None):
    """``jitted.lower(*args)``, reusing the traced program of an earlier process.

    ``jitted``: a ``jax.jit`` function; ``args``: arrays or ``jax.ShapeDtypeStruct``; ``parts``: a
    JSON-able description of everything its closure depends on that the module doc's key does
    not cover (e.g. config sections, a model digest), or None where the caller cannot name it
    (nothing is then kept on disk); ``compiler_options``: those of ``jitted``'s jit (they are
    not part of a traced program). Without a compilation cache directory (or ``parts``):
    ``jitted.lower(*args)``. With one, the program is exported once (``jax.export``) and always
    lowered from the export, so the persistent cache finds the same program in every process.
    """
    folder = None if parts is None else traced_cache_dir()
    if folder is None:
        return jitted.lower(*args)
    path = folder / f"{program_key(parts, args)}{_SUFFIX}"
    exported = _load(path)
    if exported is None:
        exported = jax.export.export(jitted)(*args)
        _save(path, exported)
    return jax.jit(exported.call, compiler_options=compiler_options).lower(*args)


def compile_traced(
    jitted, args: tuple, parts: Any, compiler_options: dict | None = None, on_traced=None
):
    """``jitted.lower(*args).compile()`` through `lower_traced` (same arguments).
    ``on_traced()``: called between tracing and compiling (Python tracing holds the GIL, XLA's
    compile does not: the cue for another thread to trace meanwhile)."""
    lowered = lower_traced(jitted, args, parts, compiler_options)
    if on_traced is not None:
        on_traced()
    return lowered.compile()


class TracedProgram:
    """``program(*args)``: ``jitted(*args)`` compiled by `compile_traced` (with ``parts`` and
    ``compiler_options``) once per argument `signature` and kept for later calls. Arguments are
    passed as the compiled program takes them (no static arguments, same dtypes and weak types
    as the first call of that signature). ``parts`` None: nothing is kept on disk (the caller
    cannot name what the closure depends on); the compiled programs are still kept.

    `precompile` compiles for arguments given as shapes (``jax.ShapeDtypeStruct``) before the
    data exist, e.g. in a `Background` thread; a call of the same signature meanwhile waits for
    that compile instead of starting its own.
    """

    def __init__(self, jitted, parts: Any, compiler_options: dict | None = None):
        self._jitted, self._options = jitted, compiler_options
        name = f"{jitted.__module__}:{jitted.__qualname__}"  # two programs, same arguments
        self._parts = None if parts is None else {"program": name, "parts": parts}  # None: not kept
        self._compiled: dict[str, concurrent.futures.Future] = {}
        self._lock = threading.Lock()

    def precompile(self, *args):
        """The compiled program for ``args`` (arrays or ``jax.ShapeDtypeStruct``); its
        ``out_info`` gives the result's shapes."""
        sig = repr(signature(args))
        with self._lock:
            future = self._compiled.get(sig)
            mine = future is None
            if mine:
                future = self._compiled[sig] = concurrent.futures.Future()
        assert future is not None  # taken from or put into the table under the lock
        if not mine:
            try:
                return future.result()
            except BaseException:  # the other thread's compile failed: this one tries again
                return self.precompile(*args)
        try:
            compiled = compile_traced(self._jitted, args, self._parts, self._options)
        except BaseException as e:
            with self._lock:  # a later call compiles again (and reports the error itself)
                del self._compiled[sig]
            future.set_exception(e)
            raise
        future.set_result(compiled)
        return compiled

    def __call__(self, *args):
        return self.precompile(*args)(*args)


def traced_program(jitted, parts: Any, compiler_options: dict | None = None) -> TracedProgram:
    """`TracedProgram` of ``jitted``."""
    return TracedProgram(jitted, parts, compiler_options)


class Background:
    """``fn(*args)`` in a thread (XLA compiles without holding the GIL, so a compile proceeds
    on another core while this thread prepares the data); `result` waits for it and returns its
    value or raises its exception. The thread runs under the caller's x64 and matmul-precision
    settings (JAX keeps those per thread). A compile cannot be cancelled: a caller that fails
    meanwhile should `wait` before it exits (exiting under a running XLA compile is unsafe).
    ``nice``: added to the thread's nice value (Linux), for work off the critical path; threads
    it starts inherit it."""

    def __init__(self, fn, *args, nice: int = 0):
        self._out: tuple = (None, None)
        x64 = bool(jax.config.jax_enable_x64)  # type: ignore[attr-defined]
        precision = jax.config.jax_default_matmul_precision  # type: ignore[attr-defined]

        def run():
            if nice:
                _lower_priority(nice)
            try:
                with jax.enable_x64(x64), jax.default_matmul_precision(precision):
                    self._out = (fn(*args), None)
            except BaseException as e:  # handed to the caller of `result`
                self._out = (None, e)

        self._thread = threading.Thread(target=run, name="evojax-compile", daemon=False)
        self._thread.start()

    def wait(self) -> None:
        self._thread.join()

    def result(self):
        self._thread.join()
        value, error = self._out
        if error is not None:
            raise error
        return value


def _lower_priority(nice: int) -> None:
    """Raise this thread's nice value by ``nice`` (Linux: per thread; elsewhere nothing)."""
    with contextlib.suppress(AttributeError, OSError):
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)


def _load(path: Path):
    """The exported program in ``path``, or None (missing; unreadable: reported and removed)."""
    if not path.is_file():
        return None
    try:
        header, body = path.read_bytes().split(b"\n", 1)
        for name in json.loads(header)["namedtuples"]:
            module, _, qualname = name.partition(":")
            obj: Any = importlib.import_module(module)
            for attr in qualname.split("."):
                obj = getattr(obj, attr)
            _register(obj)
        return jax.export.deserialize(bytearray(body))
    except Exception as e:  # any damage: trace again (the program is the same)
        print(f"warning: {path}: unreadable traced program ({e}); tracing again", file=sys.stderr)
        path.unlink(missing_ok=True)
        return None


def _save(path: Path, exported) -> None:
    """Write atomically (a temporary file, then a rename); a read-only cache is skipped.

    A JSON header line names the NamedTuple types of the argument and result trees (JAX
    serializes those only when registered; `_load` registers them before deserializing).
    """
    types = _namedtuple_types(exported.in_tree) | _namedtuple_types(exported.out_tree)
    names = sorted(f"{t.__module__}:{t.__qualname__}" for t in types)
    try:
        for typ in types:
            _register(typ)
        body = bytes(exported.serialize())
    except Exception as e:  # e.g. no flatbuffers: run on, untraced next time too
        print(f"warning: {path}: traced program not saved ({e})", file=sys.stderr)
        return
    data = json.dumps({"namedtuples": names}).encode() + b"\n" + body
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as e:
        print(f"warning: {path}: traced program not saved ({e})", file=sys.stderr)
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


def _namedtuple_types(treedef) -> set[type]:
    found, stack = set(), [treedef]
    while stack:
        node = stack.pop()
        data = node.node_data()
        if data is not None and issubclass(data[0], tuple) and hasattr(data[0], "_fields"):
            found.add(data[0])
        stack.extend(node.children())
    return found


_REGISTERED: set[type] = set()


def _register(typ: type) -> None:
    if typ not in _REGISTERED:
        jax.export.register_namedtuple_serialization(
            typ, serialized_name=f"{typ.__module__}.{typ.__qualname__}"
        )
        _REGISTERED.add(typ)
