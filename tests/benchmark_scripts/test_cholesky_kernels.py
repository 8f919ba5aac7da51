"""benchmarks/cholesky_kernels.py: its Pallas kernel solves what the optimiser's solve solves
(Pallas' interpreter on CPU), so that the benchmark compares like with like."""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.cholesky_kernels import pallas_cholesky_solve, spd_systems
from evojax_motion.linalg.cholesky import cholesky_solve

SOLVE_RTOL = 1e-4  # float32 solves of condition ~1e3 systems, relative to the largest entry


def test_pallas_kernel_matches_float64_and_the_optimisers_solve():
    a, b = spd_systems(37, 6)  # 37: a partial last block of 32
    a[5] = -a[5]  # not positive definite: flagged, like the optimiser's solve flags it
    x, ok = pallas_cholesky_solve(jnp.asarray(a), jnp.asarray(b), block=32, warps=1)
    x_ref, ok_ref = cholesky_solve(jnp.asarray(a), jnp.asarray(b))
    np.testing.assert_array_equal(np.asarray(ok), np.arange(37) != 5)
    np.testing.assert_array_equal(np.asarray(ok), np.asarray(ok_ref))
    good = np.arange(37) != 5
    exact = np.linalg.solve(np.float64(a[good]), np.float64(b[good])[..., None])[..., 0]
    scale = np.max(np.abs(exact))
    np.testing.assert_allclose(np.asarray(x)[good], exact, rtol=0, atol=SOLVE_RTOL * scale)
    np.testing.assert_allclose(np.asarray(x)[good], np.asarray(x_ref)[good], rtol=0,
                               atol=SOLVE_RTOL * scale)  # fmt: skip
