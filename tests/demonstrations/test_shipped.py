"""The shipped synthetic demonstrations (`demonstrations.shipped`): one per synthetic config in
``configs/``, none stale, none orphaned, and what a run of those configs reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evojax_motion.demonstrations.shipped import SHIPPED_DIR, shipped_path
from evojax_motion.motion.database import load_database
from evojax_motion.run.workflow import demonstrations, make_robot_dynamics, synthesise
from evojax_motion.settings import load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SYNTHETIC = sorted(p.name for p in CONFIGS.glob("*.yaml") if load_config(p).demos_file is None)
# A fresh synthesis against the shipped file. Measured between this file's CPU and the same
# synthesis under XLA_FLAGS=--xla_cpu_max_isa=SSE4_2 / AVX2 (the paper config; tiny's are
# smaller): q 1.8e-6 rad, condition 2.4e-7 m, duration 3.4e-6 s, cost 3.7e-5 relative; the
# same trials are kept. Five times those:
TOL_Q_RAD = 1e-5
TOL_CONDITION_M = 1.2e-6
TOL_DURATION_S = 2e-5
TOL_COST_REL = 2e-4


def test_every_synthetic_config_has_its_file_and_no_file_is_orphaned():
    """A config whose demonstrations changed needs its file written again (module docstring)."""
    expected = set()
    for name in SYNTHETIC:
        cfg = load_config(CONFIGS / name)
        robot, _ = make_robot_dynamics(cfg)
        path = shipped_path(cfg, robot)
        assert path.is_file(), f"{name}: no shipped demonstrations ({path.name})"
        expected.add(path.name)
    assert {p.name for p in SHIPPED_DIR.glob("*.npz")} == expected


def test_a_config_that_differs_does_not_take_the_shipped_file():
    cfg = load_config(CONFIGS / "tiny.yaml", overrides=["demos.seed=1"])
    robot, _ = make_robot_dynamics(cfg)
    assert not shipped_path(cfg, robot).is_file()


def _same_synthesis(name: str) -> None:
    cfg = load_config(CONFIGS / name)
    robot, dyn = make_robot_dynamics(cfg)
    fresh, meta = synthesise(cfg, robot, dyn)
    shipped, shipped_meta = load_database(shipped_path(cfg, robot))
    assert shipped_meta == meta
    np.testing.assert_array_equal(np.asarray(shipped.valid), np.asarray(fresh.valid))
    np.testing.assert_allclose(shipped.q, fresh.q, rtol=0, atol=TOL_Q_RAD)
    np.testing.assert_allclose(shipped.condition, fresh.condition, rtol=0, atol=TOL_CONDITION_M)
    np.testing.assert_allclose(shipped.duration, fresh.duration, rtol=0, atol=TOL_DURATION_S)
    np.testing.assert_allclose(shipped.cost, fresh.cost, rtol=TOL_COST_REL)
    # and a run of the config reads exactly the shipped file
    read, _ = demonstrations(cfg, robot, dyn)
    np.testing.assert_array_equal(np.asarray(read.q), np.asarray(shipped.q))


@pytest.mark.isa_sensitive
def test_tiny_shipped_demonstrations_are_a_fresh_synthesis():
    _same_synthesis("tiny.yaml")


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in SYNTHETIC if n != "tiny.yaml"])
def test_shipped_demonstrations_are_a_fresh_synthesis(name):
    _same_synthesis(name)
