"""XLA:CPU's multi-output fusion for the programs that ask for it, not the whole process.

XLA:CPU emits elementwise code as loops, one output array per loop, and copies a producer into
every loop that reads it. The scalar RNEA (`dynamics_rnea`) is one large elementwise graph with
7 torques out (21 cotangents per node in its gradient), so each output's loop recomputed the
shared recursion: the paper-scale gradient compiled to 22 loops of 519-2,915 fused instructions,
14 sines and cosines each. XLA's multi-output fusion pass merges loops that read the same inputs,
and the merged loop computes the shared part once. On 2 CPU cores it made the paper-scale
generation 8-14 % faster and its compile 30 % shorter (`benchmarks/changes.md`, ninth session).

The pass is off by default and is switched on by a backend option,
``xla_backend_extra_options["xla_cpu_use_multi_output_fusion"]``. That option is a map, which
``jax.jit``'s ``compiler_options`` cannot set (they take scalar `DebugOptions` fields only), and
``XLA_FLAGS`` would switch it on for every program of the process: in the test suite, with the
flag set, programs with long unrolled elementwise code (the Jacobi eigensolver, the optimiser's
fixed-trip loop in chunks) compiled for over 10 minutes instead of seconds. So `enable` adds a
small shim to JAX's compile-option builder (``jax._src.compiler.get_compile_options``): a program
jitted with ``compiler_options`` holding `MARKER` gets the option added to its serialized
``CompileOptionsProto`` (field numbers ``executable_build_options = 3`` > ``debug_options = 3``
> ``xla_backend_extra_options = 500``, stable in XLA's protos), and the marker is removed before
XLA sees the options. The shim checks itself once; where it cannot be installed or does not
round-trip (another JAX), `options` returns no marker and programs compile as before.
"""

from __future__ import annotations

import functools
from typing import Any

MARKER = "evojax_motion_multi_output_fusion"
OPTION = b"xla_cpu_use_multi_output_fusion"


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field: key, length, payload."""

    def varint(value: int) -> bytes:
        out = bytearray()
        while True:
            byte, value = value & 0x7F, value >> 7
            out.append(byte | (0x80 if value else 0))
            if not value:
                return bytes(out)

    return varint(number << 3 | 2) + varint(len(payload)) + payload


# CompileOptionsProto.executable_build_options (3) > ExecutableBuildOptionsProto.debug_options (3)
# > DebugOptions.xla_backend_extra_options (500): one map entry {key: OPTION, value: ""}. Appended
# to a serialized message, protobuf merges it in (sub-messages merge, map entries are added).
_PATCH = _field(3, _field(3, _field(500, _field(1, OPTION) + _field(2, b""))))


def with_multi_output_fusion(compile_options: Any) -> Any:
    """A copy of an ``xla_client.CompileOptions`` with the multi-output fusion option set."""
    from jax._src.lib import xla_client

    return xla_client.CompileOptions.ParseFromString(compile_options.SerializeAsString() + _PATCH)


@functools.cache
def enable() -> bool:
    """Install the shim (once per process); whether programs can ask for the pass."""
    try:
        from jax._src import compiler
        from jax._src.lib import xla_client

        # Self-check: the option survives XLA's own parse of the patched options.
        if OPTION not in with_multi_output_fusion(xla_client.CompileOptions()).SerializeAsString():
            return False
        original = compiler.get_compile_options
    except Exception:  # another JAX: no shim, default fusion
        return False

    @functools.wraps(original)
    def get_compile_options(*args, **kwargs):
        overrides = kwargs.get("env_options_overrides")
        if not overrides or MARKER not in overrides:
            return original(*args, **kwargs)
        kwargs["env_options_overrides"] = {k: v for k, v in overrides.items() if k != MARKER}
        return with_multi_output_fusion(original(*args, **kwargs))

    compiler.get_compile_options = get_compile_options
    return True


def options() -> dict:
    """``compiler_options`` entries that give a jitted program XLA:CPU's multi-output fusion:
    ``{MARKER: True}``, or nothing where the shim is not available (`enable`)."""
    return {MARKER: True} if enable() else {}
