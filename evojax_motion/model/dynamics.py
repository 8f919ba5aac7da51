"""Forward kinematics and inverse dynamics of a robot, with a choice of backend (DESIGN 1).

The torque objective of the optimisation compiler (Park et al. 2008, eq. 5) needs, at every
sample of a primitive, ``tau = M(q) qdd + C(q, qd) qd + g(q)``; the conditions and the IK need the
end-effector site pose. `make_dynamics` returns both as pure, un-jitted single-sample functions;
callers vmap over samples and conditions and jit at the top.

Backends (both return C MuJoCo's ``mj_inverse`` ``qfrc_inverse`` for the controlled dofs):
  - ``"rnea"``: recursive Newton-Euler compiled from the ``mjModel`` into a straight-line JAX
    graph (`dynamics_rnea`); hinge/slide joints, chains and trees. The fast path: its layout is
    chosen for the default JAX backend (``model.rnea.default_form``), since XLA's CPU and GPU
    compilers favour different ones.
  - ``"mjx"``: ``mujoco.mjx.inverse`` / ``mjx.kinematics`` (`dynamics_mjx`); the reference.
Joints the robot does not control are held at ``qpos0``, at rest. With armature, damping or
stiffness in the model both backends add ``armature*qdd + damping*qd + stiffness*(q - springref)``
as ``mj_inverse`` does; the shipped models have none, and disable constraints and contacts, so
the torque is the pure rigid-body one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from evojax_motion.compile_options import compiler_accepts
from evojax_motion.errors import UserError

if TYPE_CHECKING:  # annotations only: robot.py does not need to import first
    from evojax_motion.model.robot import Robot

BACKENDS = ("rnea", "mjx")


@dataclass(frozen=True, eq=False)  # eq=False: hashed by identity, usable as a jit static arg
class Dynamics:
    """A robot's kinematics and inverse dynamics as pure single-sample functions.

    inverse: ``(q (J,), qd (J,), qdd (J,)) -> tau (J,)`` [N m or N], controlled joints only;
    each input may also be a sequence of J scalars (`compiler.problems.node_states`).
    site_pose: ``q (J,) -> (pos (3,), rot (3, 3))`` of ``robot.site_name``, world frame.
    body_positions: ``q (J,) -> (nbody, 3)`` world body origins (MuJoCo ``xpos``), for key points.
    form: the RNEA's layout (`model.rnea.make_rnea`), None for MJX. The ``"scalar"`` one
    reads sequences of scalars as they are; the others stack them first.
    torques: the ``"scalar"`` layout's `inverse` with its torques a tuple of J scalars (not
    stacked; `inverse` stacks them); None for the other layouts and MJX.
    """

    robot: Robot
    backend: str
    dtype: Any
    inverse: Callable
    site_pose: Callable
    body_positions: Callable
    form: str | None = None
    torques: Callable | None = None


def make_dynamics(
    robot: Robot, backend: str = "rnea", dtype: Any = jnp.float32, form: str | None = None
) -> Dynamics:
    """Build the `Dynamics` of `robot` with `backend` in `BACKENDS`, computing in `dtype`.

    ``form``: RNEA only, its layout (`model.rnea.make_rnea`; None: the default JAX backend's).

    float64 needs jax x64 enabled both here and where the functions are traced
    (``jax.enable_x64(True)`` context or the ``jax_enable_x64`` flag).
    """
    if backend not in BACKENDS:
        raise UserError(f"dynamics: expected one of {BACKENDS}, got {backend!r}")
    dtype = np.dtype(dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise UserError(f"dtype: expected float32 or float64, got {dtype}")
    if jax.dtypes.canonicalize_dtype(dtype) != dtype:
        raise UserError("dtype: float64 needs jax x64 enabled (jax.enable_x64(True))")
    if backend == "rnea":
        from evojax_motion.model.rnea import default_form, make_rnea

        form = default_form() if form is None else form
        fns = make_rnea(robot, dtype, form)
    else:  # lazily: importing mujoco.mjx is slow and noisy
        from evojax_motion.model.mjx import make_mjx

        fns = make_mjx(robot, dtype)
    return Dynamics(
        robot=robot,
        backend=backend,
        dtype=dtype,
        inverse=fns.inverse,
        site_pose=fns.site_pose,
        body_positions=fns.body_positions,
        form=form if backend == "rnea" else None,
        torques=fns.torques,
    )


def unfused_cpu_program(dyn: Dynamics) -> tuple[Dynamics, dict | None]:
    """``(dynamics, jit compiler_options)`` for a jitted program that evaluates ``dyn`` many times.

    On the CPU backend with RNEA: the scalar layout, compiled with XLA's CPU fusion emitters off
    for that program only (`model.rnea.UNFUSED_CPU_OPTIONS`), where it runs about twice as
    fast as the default vector layout (`BENCHMARKS.md`, dynamics throughput). Every function of
    the returned ``dyn`` must be traced only into programs compiled with those options: under the
    default CPU options the scalar layout's gradients are far slower. Elsewhere, and with a jaxlib
    whose CPU compiler no longer has that option (`compiler_accepts`), ``(dyn, None)``.
    """
    from evojax_motion.model.rnea import UNFUSED_CPU_OPTIONS  # as in make_dynamics

    if _fusion_switch(dyn):
        return make_dynamics(dyn.robot, "rnea", dyn.dtype, "scalar"), dict(UNFUSED_CPU_OPTIONS)
    return dyn, None


def _fusion_switch(dyn: Dynamics) -> bool | None:
    """Whether the CPU compiler takes the fusion-emitter switch that the scalar layout needs
    there (`compiler_accepts`); None where it does not apply (another backend, MJX)."""
    from evojax_motion.model.rnea import UNFUSED_CPU_OPTIONS

    if jax.default_backend() != "cpu" or dyn.backend != "rnea":
        return None
    return compiler_accepts(**UNFUSED_CPU_OPTIONS)


def slow_cpu_layout_note(dyn: Dynamics) -> str | None:
    """A line for the user where the CPU's RNEA cannot run in its fast layout, else None.

    The scalar layout is the fast one on CPU only with XLA's CPU fusion emitters off
    (`unfused_cpu_program`). jax 0.11 and later have no switch for them; under them the scalar
    layout's gradients compile for minutes, so programs keep the vector layout, which takes ~6x
    as long a generation at paper scale (on 2 cores of one machine, jax 0.10.2: 1.65-1.71 s
    under the emitters against 0.25-0.36 s; CHANGELOG.md)."""
    if _fusion_switch(dyn) is not False:
        return None
    return (
        f"note: jax {jax.__version__} cannot switch off XLA's CPU fusion emitters, so the "
        "RNEA runs in its slower vector layout on this CPU: a generation takes ~6x as long as "
        "with jax 0.10 (README.md, 'CPU and jax versions')"
    )


def one_shot_layout(dyn: Dynamics) -> Dynamics:
    """The dynamics for a program that runs once or twice (the command line's ``generate`` and
    ``catch``, `compile_options.ONE_SHOT`), where its compile is most of the wait.

    On accelerators with the RNEA backend, the vector layout: the scalar one (their default,
    3-8x faster to run) compiles slowly. One H200, the command line cold, 3 interleaved pairs:
    `generate` 22.8-25.5 -> 11.7-12.2 s, `catch` 26.9-31.8 -> 21.2-23.1 s (CHANGELOG.md).
    Elsewhere ``dyn`` as given (on CPU the scalar layout unfused, `unfused_cpu_program`, also
    compiles the query faster).
    """
    if jax.default_backend() == "cpu" or dyn.backend != "rnea" or dyn.form == "vector":
        return dyn
    return make_dynamics(dyn.robot, "rnea", dyn.dtype, "vector")


# Training runs of at most this many generations x conditions use `one_shot_layout` on
# accelerators (`training_layout`). One H200, `train configs/catch_ball.yaml` (10 generations of
# 300 conditions) cold, 2 runs each: the step's compile 44-46 s with the scalar layout, 1.9-2.3 s
# with the vector one, which runs a generation in 0.022 s against 0.012-0.014 s; the runs took
# 71.2-72.5 s and 28.3-30.8 s. At 60,000 (200 generations of 300) the vector layout's slower
# generations cost ~2 s a run even with the scalar step in the cache; longer runs keep the
# scalar layout (and the generation benchmarks measure it). Measured at 300 conditions only, so
# larger batches (whose memory in the vector layout is not measured) keep the scalar one too.
SHORT_RUN_WORK = 60_000
SHORT_RUN_CONDITIONS = 1_000


def training_layout(dyn: Dynamics, generations: int, conditions: int) -> Dynamics:
    """The dynamics a training run of ``generations`` x ``conditions`` compiles its programs
    with: `one_shot_layout` (the vector RNEA layout on accelerators) up to `SHORT_RUN_WORK`
    and `SHORT_RUN_CONDITIONS`, where the scalar layout's compile would take longer than the
    generations it speeds up; ``dyn`` otherwise and on CPU. The traced-program cache keys by
    the layout itself (`run.workflow.cache_parts`)."""
    return one_shot_layout(dyn) if is_short_run(generations, conditions) else dyn


def training_dynamics(dyn: Dynamics, generations: int, conditions: int) -> tuple[Dynamics, bool]:
    """``(dynamics, short_run)`` of a training run of ``generations`` x ``conditions``: its
    `training_layout` and `is_short_run` (its step's compile options,
    `run.compilation.compile_generation_step`), decided together (`run.training`)."""
    return training_layout(dyn, generations, conditions), is_short_run(generations, conditions)


def is_short_run(generations: int, conditions: int) -> bool:
    """Whether a training run of ``generations`` x ``conditions`` is short: at most
    `SHORT_RUN_WORK` and `SHORT_RUN_CONDITIONS` (`training_layout`; its step also compiles
    without kernel autotuning or Triton GEMMs on GPUs, `compile_options.short_run`)."""
    return generations * conditions <= SHORT_RUN_WORK and conditions <= SHORT_RUN_CONDITIONS
