"""How hard XLA optimises a program, by how often it runs.

XLA compiles every program with its full optimisation pipeline unless told otherwise. Programs
that run once per process - the synthesis of demonstrations, drawing the condition set, the human
costs, the limit counts, one ``generate`` or ``catch`` query of the command line - pay that
compile on every cold start and gain little from it. `ONE_SHOT` sets XLA's backend (LLVM)
optimisation level to 0 for them on the CPU backend. Measured on 2 CPU cores
(CHANGELOG.md): the catcher's compile 10.3 -> 3.9 s for 1.6 -> 3.4 ms a call; with level 0 for
every program (``XLA_FLAGS``), a cold paper-configuration ``train``'s conditions phase 8.1 -> 1.5
s (one run each, on a machine shared with other work). The generation step and the
programs that answer many queries (benchmarks, an online generator kept in a notebook) keep the
full level: at level 0 a generation on the CPU took 3.3x as long.

On GPUs XLA's backend level did not shorten the compiles that dominate there (one H200). What
does is the matrix products: XLA times candidate kernels for each (autotuning) and generates
Triton kernels for them. `ONE_SHOT_GPU` turns both off for the same one-shot programs, and
`short_run` for a short training run's generation step (`model.dynamics.is_short_run`), which
runs a few tens of times. Measured on H200s (CHANGELOG.md, separate calls on two machines):
the human costs' program compiled in 12.9 -> 1.1 s, a short run's two step programs in 11.6 /
15.5 -> 3.9 / 6.7 s, for 0.51 -> 0.80 ms and 20.6 -> 22.5 ms a call. Long runs and the
generation benchmarks keep both.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

ONE_SHOT: dict = {"xla_backend_optimization_level": 0}  # CPU
# GPUs: no kernel autotuning, and cuBLAS rather than Triton for matrix products (Triton's
# GEMM kernels are generated and compiled per program)
ONE_SHOT_GPU: dict = {"xla_gpu_autotune_level": 0, "xla_gpu_enable_triton_gemm": False}
# XLA's default level, named: for a program that runs many times in a process and must keep the
# full level where XLA_FLAGS lowers it for everything else (the test run compiles at level 0).
FULL_LEVEL: dict = {"xla_backend_optimization_level": 3}


def one_shot(options: dict | None = None, enabled: bool = True) -> dict | None:
    """jit ``compiler_options`` for a program that runs once: ``options`` (None: none) with
    `ONE_SHOT`'s where ``enabled`` and the default backend is the CPU, `ONE_SHOT_GPU`'s where
    it is a GPU, else ``options``. Reads the backend: call it when the program is made, not at
    import."""
    if enabled and jax.default_backend() == "cpu":
        return {**(options or {}), **ONE_SHOT}
    return short_run(options, enabled)  # GPUs: the same options as a short run's step


def short_run(options: dict | None = None, enabled: bool = True) -> dict | None:
    """jit ``compiler_options`` for a program that runs a few tens of times (a short training
    run's generation step): ``options`` with those of `ONE_SHOT_GPU` that the compiler accepts
    (`accepted`) where ``enabled`` and the default backend is a GPU, else ``options`` (on the
    CPU such a program keeps the full level)."""
    if not enabled or jax.default_backend() != "gpu":
        return options
    return {**(options or {}), **accepted(ONE_SHOT_GPU)}


def accepted(options: dict) -> dict:
    """The entries of ``options`` that the default backend's compiler accepts: all of them in
    one probe where it accepts them together, else each tried alone (`compiler_accepts`). XLA
    drops debug options between releases, and a jit with one it lacks fails to compile."""
    if compiler_accepts(**options):
        return options
    return {k: v for k, v in options.items() if compiler_accepts(**{k: v})}


@functools.cache
def compiler_accepts(**options: Any) -> bool:
    """Whether the default backend's compiler accepts these jit ``compiler_options``.

    Tried once per set, on a one-operation program, rather than read from a version number:
    XLA's CPU fusion emitters and their switch (`model.rnea.UNFUSED_CPU_OPTIONS`) are newer than
    jax 0.5 and gone in later releases (jax 0.11 refuses it: "No such compile option").
    """
    probe = jax.jit(lambda x: x + 1.0).lower(np.zeros((), np.float32))
    try:
        probe.compile(options)
    except jax.errors.JaxRuntimeError:
        return False
    return True


def one_shot_jit(fn: Callable, **jit_kwargs) -> Callable[[], Callable]:
    """A factory of ``jax.jit(fn, compiler_options=one_shot(), **jit_kwargs)``, made at its first
    call and kept: for module-level programs (the backend is not known at import)."""
    return functools.cache(lambda: jax.jit(fn, compiler_options=one_shot(), **jit_kwargs))
