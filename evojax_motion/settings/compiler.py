"""Settings of the movement compilers (paper sec. 2): neighbour selection and the basis
(`BasisSettings`, for `compiler.basis`) and the compiler via optimisation (`OptimSettings`, for
`compiler.optimisation`), with the constants their defaults and validation use.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from evojax_motion.errors import check_setting

# The optimisation compiler's rule [rad per rad]: a BC direction binds (is met exactly) when moving
# q by 1 rad RMS along the basis changes it by more than this (rad for q, rad/s x D for qd); the
# directions below it are free, so an optimisation step of 1 rad RMS lets the end velocities drift
# by at most BC_LEAK / D. Rest-to-rest minimum-jerk bases (T = 100) sit at ~1e-6 and are free; the
# synthetic demonstrations' near-rest ends (IK, T = 100) at 0.2 .. 0.6 and bind: 7.0 free
# dimensions per condition (one per joint) at 2e-4 against 8.0 at 1e-3 (end velocities then drift
# up to 2e-3 rad/s per rad).
BC_LEAK = 2e-4
# The optimisers of `OptimSettings.method` (`compiler.optimisation`'s module docstring).
METHODS = ("newton", "bfgs", "adam", "lbfgs")
# Iteration budget of each method where ``max_iters`` is null (BFGS needs more, cheaper, ones:
# with its subspace step, 40 left a median gap to SLSQP of 0.11-0.23 % at paper scale on an
# H100, 50 gave 0.025 %; CHANGELOG.md).
DEFAULT_ITERS = {"newton": 25, "bfgs": 50, "adam": 25, "lbfgs": 25}
# BFGS's first models of the torque cost (`OptimSettings.initial_model`).
INITIAL_MODELS = ("gauss-newton", "identity")
# Default `OptimSettings.max_batch` (chosen on an H200 with the fused search gradient: chunks
# of ~3,000 problems ran 20-23 % faster than of ~4,000 at 30,000 and 100,000 conditions;
# docs/scaling.md).
MAX_BATCH = 3072


@dataclass(frozen=True)
class BasisSettings:
    """Neighbour selection of eq. 6; defaults are the paper's (sec. 4.2).

    - ``radius`` [m]: primitives whose condition lies within it are "inside" (paper: 15 cm).
    - ``neighbours``: fixed number k of primitives per basis (top-k by distance).
    - ``w_pos`` [1/m], ``w_rot``: weights of the position and orientation terms of eq. 6.
    """

    radius: float = 0.15
    neighbours: int = 10
    w_pos: float = 1.0
    w_rot: float = 0.0

    def __post_init__(self):
        check_setting(
            isinstance(self.radius, int | float) and self.radius > 0,
            "radius",
            "a number > 0 [m]",
            self.radius,
        )
        check_setting(
            isinstance(self.neighbours, int) and self.neighbours >= 2,
            "neighbours",
            "an integer >= 2",
            self.neighbours,
        )
        check_setting(
            isinstance(self.w_pos, int | float) and self.w_pos > 0,
            "w_pos",
            "a number > 0",
            self.w_pos,
        )
        check_setting(
            isinstance(self.w_rot, int | float) and self.w_rot >= 0,
            "w_rot",
            "a number >= 0",
            self.w_rot,
        )


@dataclass(frozen=True)
class OptimSettings:
    """Settings of the movement compiler via optimisation.

    - ``n_components``: principal components K of eq. 3 (paper: 4).
    - ``method``: ``"newton"`` (default), ``"bfgs"``, ``"adam"`` or ``"lbfgs"`` (`METHODS`;
      `compiler.optimisation`'s module docstring).
    - ``max_iters``: iteration budget (Newton / BFGS / L-BFGS iterations, Adam steps); null: the
      method's `DEFAULT_ITERS`.
    - ``tol``: stop when the Newton decrement ``g.B^-1.g / 2`` falls below ``tol * |f|`` (Newton,
      BFGS), or the gradient norm below ``tol * (1 + |f|)`` (L-BFGS; Adam runs its budget).
    - ``hessian_every``: Newton only; refresh the exact Hessian every so many iterations (BFGS
      updates in between).
    - ``learning_rate``: Adam's step size [rad RMS of q per step].
    - ``limit_margin`` [rad]: the penalty acts on ``[lower + margin, upper - margin]``.
    - ``limit_penalty`` [cost units / rad^2 / s]: weight of the quadratic limit penalty (the
      velocity and torque penalties' too, per (rad/s)^2 s and (N m)^2 s).
    - ``limit_headroom`` [fraction]: where the robot has velocity or torque limits
      (`model.robot.Robot.velocity_limit`, ``torque_limit``, handed to
      `compiler.optimisation.optimise_prepared`), the penalty also acts on ``|qd|`` and ``|tau|``
      above ``(1 - limit_headroom) * limit``.
      Without it 271-296 of the paper configuration's 300 offspring a generation went over the
      Mahru arm's velocity limits and were discarded (CHANGELOG.md).
    - ``interp_components``: the optimiser's problems go through the interpolation compiler's
      answer (eq. 1-2) with this many of the basis' components (paper: 3;
      `compiler.problems.interpolation_base`), its start; 0: through the minimum-norm BC
      solution of all ``n_components``. Either way the result is the best, by the penalised
      objective on all T samples, of the optimiser's and its start.
    - ``n_starts``: starts per condition (1 = the start above only); ``start_scale``: spread of
      the others [rad RMS of q] (default 0.3: at 1.0, 4 starts put 94.0 % of the paper problems
      within float64 SLSQP's cost + 0.1 % instead of 96.3 %; CHANGELOG.md); ``seed``: the fixed
      key of those starts (deterministic). More starts find better minima, at a time per
      generation that grows with them on a CPU and little on a GPU (README.md,
      `compiler.optimisation`).
    - ``max_free_per_joint``: free null-space directions kept per joint (static size of z: J times
      this). After both position BCs, K + 1 - 2 = 3 is all there can be; bases whose velocity BCs
      bind too have fewer (the synthetic demonstrations at T = 100: 1 on ~90 % of the joints, 2
      on the rest, so 2 keeps them all; 1 made the median gap 0.18 %). Fewer is cheaper: the
      Newton step's Hessian costs one Hessian-vector product per direction.
    - ``search_stride``: the optimiser's objective integrates over every ``search_stride``-th sample
      (trapezoid, `compiler.problems.search_nodes`); the result's cost is always eq. 5 on all T
      samples. Stride 4 at T = 100 (``configs/catch_ball.yaml``): 5.5x faster, median gap to SLSQP
      unchanged, p95 0.22 % instead of 0.046 % (``benchmarks/results/optimality_cpu_fast.json``).
    - ``bc_leak`` [rad per rad]: BC directions that 1 rad RMS of motion changes by less than this
      are free, the others are met exactly (`BC_LEAK`).
    - ``max_batch``: the most problems (conditions x starts) optimised at once; a larger batch is
      split into equal chunks optimised one after another (`solvers.chunking.optimise_in_chunks`).
      On an H100 a batch's time per problem doubled between 7,500 and 15,000 problems at once (most
      likely its working set leaving the GPU's cache; not proven), and with BFGS's subspace step
      chunks of ~4,000 ran 16-22 % faster than of ~7,700 at 30,000 and 100,000 conditions; with the
      fused search gradient (`compiler.search_objective.make_search_value`) on an H200, chunks of
      ~3,000 20-23 % faster than of ~4,000 (`docs/scaling.md`); null: the whole batch at once.
    - ``initial_model``: BFGS only, its first model of the torque cost: ``"gauss-newton"``
      (`compiler.search_objective.gauss_newton_model`: forward-mode Jacobians on a third of the
      nodes, ~3 optimiser passes' cost; paper configuration: 18 iterations median instead of 36, and
      p95 gap to SLSQP 1.1 % instead of 3.1 %, on the float32-rounded problems before
      `compiler.interpolation.end_slopes`; 22 iterations median since, 19 since a rejected step
      keeps the model, `solvers.quasi_newton.StructuredBFGS`) or ``"identity"`` (a multiple of it,
      no derivatives).
    """

    n_components: int = 4
    method: str = "newton"
    max_iters: int | None = None
    tol: float = 1e-6
    learning_rate: float = 0.1
    limit_margin: float = 0.02
    limit_penalty: float = 1e4
    limit_headroom: float = 0.05
    max_free_per_joint: int = 3
    search_stride: int = 1
    hessian_every: int = 1
    interp_components: int = 3
    n_starts: int = 1
    start_scale: float = 0.3
    seed: int = 0
    bc_leak: float = BC_LEAK
    max_batch: int | None = MAX_BATCH
    initial_model: str = "gauss-newton"

    def __post_init__(self):
        check_setting(
            isinstance(self.n_components, int) and self.n_components >= 1,
            "n_components",
            "an integer >= 1",
            self.n_components,
        )
        check_setting(self.method in METHODS, "method", f"one of {METHODS}", self.method)
        check_setting(
            self.max_iters is None or (isinstance(self.max_iters, int) and self.max_iters >= 1),
            "max_iters",
            "an integer >= 1 or null",
            self.max_iters,
        )
        check_setting(0 <= self.tol < 1, "tol", "a number in [0, 1)", self.tol)
        check_setting(self.learning_rate > 0, "learning_rate", "a number > 0", self.learning_rate)
        check_setting(
            0 <= self.limit_margin < 0.5,
            "limit_margin",
            "a number in [0, 0.5) rad",
            self.limit_margin,
        )
        check_setting(self.limit_penalty >= 0, "limit_penalty", "a number >= 0", self.limit_penalty)
        check_setting(
            0 <= self.limit_headroom < 1,
            "limit_headroom",
            "a fraction in [0, 1)",
            self.limit_headroom,
        )
        check_setting(
            isinstance(self.max_free_per_joint, int)
            and 1 <= self.max_free_per_joint <= self.n_components,
            "max_free_per_joint",
            f"an integer in [1, n_components = {self.n_components}]",
            self.max_free_per_joint,
        )
        check_setting(
            isinstance(self.search_stride, int) and self.search_stride >= 1,
            "search_stride",
            "an integer >= 1",
            self.search_stride,
        )
        check_setting(
            isinstance(self.hessian_every, int) and self.hessian_every >= 1,
            "hessian_every",
            "an integer >= 1",
            self.hessian_every,
        )
        check_setting(
            isinstance(self.interp_components, int)
            and 0 <= self.interp_components <= self.n_components,
            "interp_components",
            f"an integer in [0, n_components = {self.n_components}]",
            self.interp_components,
        )
        check_setting(
            isinstance(self.n_starts, int) and self.n_starts >= 1,
            "n_starts",
            "an integer >= 1",
            self.n_starts,
        )
        check_setting(self.start_scale >= 0, "start_scale", "a number >= 0", self.start_scale)
        check_setting(isinstance(self.seed, int), "seed", "an integer", self.seed)
        check_setting(0 < self.bc_leak < 1, "bc_leak", "a number in (0, 1)", self.bc_leak)
        check_setting(
            self.max_batch is None or (isinstance(self.max_batch, int) and self.max_batch >= 1),
            "max_batch",
            "an integer >= 1 or null",
            self.max_batch,
        )
        check_setting(
            self.initial_model in INITIAL_MODELS,
            "initial_model",
            f"one of {INITIAL_MODELS}",
            self.initial_model,
        )

    def resolved(self) -> OptimSettings:
        """These settings with ``max_iters`` made concrete (`DEFAULT_ITERS` where it is null)."""
        if self.max_iters is not None:
            return self
        return dataclasses.replace(self, max_iters=DEFAULT_ITERS[self.method])
