"""`compile_options`: the one-shot compiler options, where they apply and what they change."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import FULL_LEVEL, ONE_SHOT, one_shot, one_shot_jit

# Level 0 against the full level on one program: LLVM may contract or reorder float operations
# differently; the results agree to float32 rounding.
TOL_REL = 1e-6


def _program(x):
    return jnp.sum(jnp.sin(x) * jnp.exp(-x) + x**2)


def test_one_shot_applies_on_the_cpu_backend_only(monkeypatch):
    base = {"xla_cpu_use_fusion_emitters": False}
    assert one_shot(base, enabled=False) is base
    if jax.default_backend() == "cpu":
        assert one_shot(base) == {**base, **ONE_SHOT} and one_shot() == ONE_SHOT
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert one_shot(base) is base and one_shot() is None


def test_a_one_shot_program_compiles_and_agrees_with_the_full_level():
    x = np.linspace(0.0, 3.0, 1001, dtype=np.float32)
    full = float(jax.jit(_program, compiler_options=FULL_LEVEL)(x))
    factory = one_shot_jit(_program)
    assert factory() is factory()  # made once
    assert factory().lower(x).compile() is not None
    np.testing.assert_allclose(float(factory()(x)), full, rtol=TOL_REL)
