"""`xla_fusion`: XLA:CPU's multi-output fusion for the programs that ask for it, and only them;
the optimiser's objective on unstacked torques equals the stacked one."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from evojax_motion import xla_fusion
from evojax_motion.dynamics import make_dynamics, unfused_cpu_program
from evojax_motion.robot import load_robot

# Objective on unstacked vs stacked torques, relative: float32 rounding of a sum's order.
TOL_TERMS = 1e-6


@pytest.fixture(scope="module")
def robot():
    return load_robot("mahru_arm")


def _siblings(x):
    return jnp.sin(x) * 2.0, jnp.cos(x) + 1.0  # two loops reading the same input


def _multi_output_fusions(options: dict) -> int:
    text = jax.jit(_siblings, compiler_options=options).lower(jnp.ones((64, 64))).compile()
    entry = text.as_text()[text.as_text().index("ENTRY") :]
    return len(re.findall(r"= \(f32\[64,64\][^)]*, f32\[64,64\][^)]*\) fusion\(", entry))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="an XLA:CPU pass")
def test_only_programs_that_ask_get_multi_output_fusion():
    assert xla_fusion.enable(), "the shim should install on the pinned JAX"
    assert _multi_output_fusions(xla_fusion.options()) == 1
    assert _multi_output_fusions({}) == 0  # the default pipeline, in the same process


def test_patch_adds_one_map_entry_to_the_options():
    from jax._src.lib import xla_client

    base = xla_client.CompileOptions()
    patched = xla_fusion.with_multi_output_fusion(base).SerializeAsString()
    assert patched.count(xla_fusion.OPTION) == 1
    assert xla_fusion.OPTION not in base.SerializeAsString()
    # XLA re-serialises what it parsed: the patch is a sub-message, not trailing garbage
    again = xla_client.CompileOptions.ParseFromString(patched).SerializeAsString()
    assert again == patched


def test_without_the_shim_programs_compile_as_before(monkeypatch, robot):
    """Where the shim is unavailable (another JAX) the fast path asks for nothing it lacks."""
    monkeypatch.setattr(xla_fusion, "enable", lambda: False)
    dyn, options = unfused_cpu_program(make_dynamics(robot), torques=True)
    if options is not None:
        assert xla_fusion.MARKER not in options
    assert dyn.torques is None


def test_unstacked_torques_equal_the_inverse(robot):
    """`Dynamics.torques` is the scalar RNEA's inverse, unstacked, for joint lists."""
    dyn = make_dynamics(robot, "rnea", form="scalar", torques=True)
    rng = np.random.default_rng(0)
    j = robot.n_joints
    q, qd, qdd = (list(jnp.asarray(rng.standard_normal((j, 5)), jnp.float32)) for _ in range(3))
    stacked = jax.vmap(dyn.inverse)(q, qd, qdd)
    terms = jax.vmap(dyn.torques)(q, qd, qdd)
    np.testing.assert_array_equal(np.stack(terms, -1), np.asarray(stacked))
    assert make_dynamics(robot, "rnea", form="vector", torques=True).torques is None
    assert make_dynamics(robot, "rnea", form="scalar").torques is None
    # the optimiser's squares, both ways
    sq = np.asarray(sum(t * t for t in terms))
    np.testing.assert_allclose(sq, np.sum(np.asarray(stacked) ** 2, -1), rtol=TOL_TERMS)
