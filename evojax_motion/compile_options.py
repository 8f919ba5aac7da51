"""How hard XLA optimises a program, by how often it runs.

XLA compiles every program with its full optimisation pipeline unless told otherwise. Programs
that run once per process - the synthesis of demonstrations, drawing the condition set, the human
costs, the limit counts, one ``generate`` or ``catch`` query of the command line - pay that
compile on every cold start and gain little from it. `ONE_SHOT` sets XLA's backend (LLVM)
optimisation level to 0 for them. Measured on 2 CPU cores (`benchmarks/cold_start.py`,
CHANGELOG.md): the catcher's compile 10.3 -> 3.9 s for 1.6 -> 3.4 ms a call; drawing the paper
configuration's conditions 8.1 -> 1.5 s. The generation step and the programs that answer many
queries (benchmarks, an online generator kept in a notebook) keep the full level: at level 0 a
generation on the CPU took 3.3x as long.
"""

from __future__ import annotations

ONE_SHOT: dict = {"xla_backend_optimization_level": 0}


def one_shot(options: dict | None = None, enabled: bool = True) -> dict | None:
    """``options`` (jit ``compiler_options``; None: none) with `ONE_SHOT`'s where ``enabled``,
    else unchanged."""
    return {**(options or {}), **ONE_SHOT} if enabled else options
