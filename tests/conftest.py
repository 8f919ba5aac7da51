"""Shared test settings: CPU, deterministic, x64 on request."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import pytest


@pytest.fixture
def x64():
    """Run the test body with float64 enabled (accuracy checks against C MuJoCo / SciPy)."""
    with jax.enable_x64(True):
        yield
