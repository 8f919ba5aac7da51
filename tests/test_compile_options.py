"""`compile_options`: the one-shot compiler options, where they apply and what they change."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion import compile_options
from evojax_motion.compile_options import (
    FULL_LEVEL,
    ONE_SHOT,
    ONE_SHOT_GPU,
    accepted,
    compiler_accepts,
    one_shot,
    one_shot_jit,
    short_run,
)

# Level 0 against the full level on one program: LLVM may contract or reorder float operations
# differently; the results agree to float32 rounding.
TOL_REL = 1e-6


def _program(x):
    return jnp.sum(jnp.sin(x) * jnp.exp(-x) + x**2)


def test_one_shot_options_follow_the_backend(monkeypatch):
    base = {"xla_cpu_use_fusion_emitters": False}
    assert one_shot(base, enabled=False) is base
    assert short_run(base, enabled=False) is base
    if jax.default_backend() == "cpu":
        assert one_shot(base) == {**base, **ONE_SHOT} and one_shot() == ONE_SHOT
        assert short_run(base) is base  # a short run's step keeps the CPU's full level
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert one_shot(base) == {**base, **ONE_SHOT_GPU} and one_shot() == ONE_SHOT_GPU
    assert short_run(base) == {**base, **ONE_SHOT_GPU}
    monkeypatch.setattr(jax, "default_backend", lambda: "tpu")
    assert one_shot(base) is base and one_shot() is None and short_run() is None


def test_options_the_compiler_lacks_are_dropped(monkeypatch):
    """A compiler option that XLA no longer has fails a jit's compile: `accepted` keeps only
    those the compiler takes (asked by compiling a probe, `compiler_accepts`), and the GPU
    options pass through it."""
    assert compiler_accepts()
    assert not compiler_accepts(xla_no_such_compile_option=False)
    both = {**ONE_SHOT, "xla_no_such_compile_option": False}
    assert accepted(both) == ONE_SHOT
    assert accepted(ONE_SHOT) == ONE_SHOT
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(
        compile_options, "compiler_accepts", lambda **o: "xla_gpu_enable_triton_gemm" not in o
    )
    lacking = {k: v for k, v in ONE_SHOT_GPU.items() if k != "xla_gpu_enable_triton_gemm"}
    assert short_run() == lacking and one_shot() == lacking


def test_a_one_shot_program_compiles_and_agrees_with_the_full_level():
    x = np.linspace(0.0, 3.0, 1001, dtype=np.float32)
    full = float(jax.jit(_program, compiler_options=FULL_LEVEL)(x))
    factory = one_shot_jit(_program)
    assert factory() is factory()  # made once
    assert factory().lower(x).compile() is not None
    np.testing.assert_allclose(float(factory()(x)), full, rtol=TOL_REL)
