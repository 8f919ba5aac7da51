"""What a new training run compiles, and compiles early (`run.training.run_training`).

The generation step as one program or as two compiled side by side (`compile_generation_step`,
`StagedStep`); the setup's programs, the time grid, cost and condition draw of generation 0
(`setup_programs`); and `EarlyCompile`, which compiles both in background threads from the sizes
known before the demonstrations exist (`expected_sizes`, `expected_inputs`), so that their
compile overlaps the demonstrations' synthesis. Also where the generations' inputs live between
generations (`generation_inputs`).
"""

from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from evojax_motion.errors import UserError

if TYPE_CHECKING:
    from evojax_motion.motion.objective import CostProgram
    from evojax_motion.settings import Config

# Nice value added to the thread that precompiles the setup's programs (`EarlyCompile`): the
# step's compile is a new run's critical path, the setup's programs are needed only after the
# demonstrations. 2 CPU cores, paper config, cold, 3 alternating rounds: 31.4 / 30.4 / 30.4 s to
# the first generation against 31.5 / 32.4 / 33.1 s (CHANGELOG.md).
PRECOMPILE_NICE = 10


class SetupPrograms(NamedTuple):
    """`run.training.initial_state`'s programs for demonstrations of known ``sizes``
    (`setup_programs`)."""

    sizes: tuple[int, int, int]  # (demonstrations, samples, joints)
    grid: Any  # timegrid.TimeGrid of the samples
    costs: CostProgram
    conditions: Any  # conditions.ConditionPrograms

    def precompile(self) -> None:
        """Compile them for ``sizes``, before the demonstrations exist."""
        n, t, j = self.sizes
        self.costs.precompile(t, j)
        self.conditions.precompile(n, t, j)


def setup_programs(cfg: Config, robot, dyn, sizes: tuple[int, ...]) -> SetupPrograms:
    """The time grid, `CostProgram` and condition draw (`evolution.conditions.condition_programs`)
    of a run of ``cfg`` with ``sizes = (demonstrations, samples, joints)``."""
    from evojax_motion.evolution.conditions import condition_programs
    from evojax_motion.motion.objective import CostProgram
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run.workflow import cache_parts

    n, t, j = (int(x) for x in sizes)
    parts = cache_parts(cfg, robot, dyn)
    grid = make_time_grid(t)
    costs = CostProgram(dyn, grid, max(n, cfg.evolution.conditions), parts)
    draw = condition_programs(dyn, robot, cfg.evolution, cfg.basis, grid, parts)
    return SetupPrograms((n, t, j), grid, costs, draw)


def wait_for_step(early: EarlyCompile | None) -> tuple:
    """``(early.step(), seconds waited for it)``; ``(None, 0.0)`` without ``early``. Its compile
    may still be running when the demonstrations and conditions are done: that wait is compile
    time the setup did not hide (``compile_seconds`` of the summary)."""
    if early is None:
        return None, 0.0
    t0 = time.perf_counter()
    step = early.step()
    return step, time.perf_counter() - t0


def one_device(cfg: Config) -> bool:
    """Whether ``cfg``'s generation step runs on one device (`compile_generation_step`: two
    programs) rather than sharded over several (`evolution.sharding.sharded_generation_step`)."""
    from evojax_motion.evolution.sharding import resolve_devices

    return len(resolve_devices(cfg.parallel.devices)) == 1


def generation_inputs(cfg: Config, db, conditions):
    """``(db, conditions)`` as the generation step takes them from the first generation on: put
    once, whole, on every device of the step (`evolution.sharding.replicate`), where they stay
    between generations, since the step returns its database placed so. With numpy inputs
    every call copied them from the host and changed their layout there: ~2 ms a generation at
    1,000 conditions on an H100, 0.25 s at 100,000 on an H200 (CHANGELOG.md)."""
    from evojax_motion.evolution.sharding import replicate

    return replicate((db, conditions), cfg.parallel.devices)


class StagedStep:
    """``step(db, conditions, generation) -> (db, GenerationStats)``: the generation step as its
    two compiled stages (`evolution.step.generation_stages`), ``finish`` on ``prepare``'s result.
    ``cost_analysis()`` is the two programs' together, as of one compiled step; each program's
    own (``as_text()``, a trace's kernels) is that of ``prepare`` or ``finish``."""

    def __init__(self, prepare, finish):
        self.prepare, self.finish = prepare, finish

    def __call__(self, db, conditions, generation):
        return self.finish(db, conditions, generation, self.prepare(db, conditions))

    def cost_analysis(self) -> dict:
        """The two programs' XLA cost analyses, summed key by key."""
        total: dict = {}
        for stage in (self.prepare, self.finish):
            cost = stage.cost_analysis()
            for k, v in (cost[0] if isinstance(cost, list) else cost or {}).items():
                total[k] = total.get(k, 0.0) + v
        return total


def compile_generation_step(cfg: Config, robot, dyn, db, conditions, short_run: bool = False):
    """The run's generation step, compiled for ``db`` and ``conditions``:
    ``step(db, conditions, generation) -> (db, GenerationStats)``.

    Conditions sharded over ``cfg.parallel.devices`` (all by default). On one device, a
    `StagedStep`: its two stages compiled side by side (``prepare`` in a `Background` thread
    while ``finish`` is traced and compiled here), each through `run.cache.compile_traced`,
    so that with JAX's compilation cache on a later process skips tracing them too. Traced and
    compiled: 10.3-10.6 against 13.3-13.6 s as one program at paper scale on 2 CPU cores, 27-29
    against 40-45 s at 1,000 conditions on an H200 (CHANGELOG.md).

    ``short_run``: compiled as a short training run's step (`compile_options.short_run`: on
    GPUs, no kernel autotuning or Triton GEMMs); `run.training` passes
    `model.dynamics.is_short_run` of its config. The default, the full compile, is the one the
    generation benchmarks measure.
    """
    from evojax_motion.evolution.sharding import one_device_stages, sharded_generation_step
    from evojax_motion.motion.database import count_human
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.run.cache import Background, compile_traced, lower_traced
    from evojax_motion.run.workflow import cache_parts

    n_human = count_human(db)
    grid = make_time_grid(db.q.shape[1])
    fixed = (dyn, grid, robot.lower, robot.upper, n_human, cfg.basis, cfg.compiler, cfg.evolution)
    limits = {"torque_limit": robot.torque_limit, "velocity_limit": robot.velocity_limit}
    generation = np.asarray(1, np.int32)  # the generation index is traced
    if not one_device(cfg):
        step_fn, _ = sharded_generation_step(*fixed, devices=cfg.parallel.devices, **limits)
        return step_fn.lower(db, conditions, generation).compile()
    prepare, finish, options = one_device_stages(
        *fixed, devices=cfg.parallel.devices, short_run=short_run, **limits
    )
    parts = {"n_human": n_human, **cache_parts(cfg, robot, dyn)}
    lowered = lower_traced(prepare, (db, conditions), {"program": "prepare", **parts}, options)
    first = Background(lowered.compile)
    try:
        args = (db, conditions, generation, lowered.out_info)
        second = compile_traced(finish, args, {"program": "finish", **parts}, options)
    finally:
        first.wait()  # never leave a compile running behind an error
    return StagedStep(first.result(), second)


def expected_sizes(cfg: Config, robot) -> tuple[int, int, int] | None:
    """``(demonstrations, samples, joints)`` that `run.training.initial_state` will meet, known
    before the demonstrations are made: ``demos.count`` and ``demos.samples``, or the valid human
    rows of ``demos_file``; None when `run.training.initial_state` will refuse the file (it then
    says why: `run.workflow.read_demonstrations_file`, `run.workflow.check_samples`). A
    demonstration dropped as non-finite makes the real count smaller: compare before use."""
    from evojax_motion.run.workflow import check_samples, read_demonstrations_file

    if cfg.demos_file is None:
        n, t = cfg.demos.count, cfg.demos.samples
    else:
        try:
            file_db, _ = read_demonstrations_file(cfg, robot)
            check_samples(cfg, file_db.q.shape[1])
        except UserError:
            return None
        n, t = file_db.q.shape[0], file_db.q.shape[1]
    return n, t, len(robot.joint_names)


def expected_inputs(cfg: Config, robot, sizes: tuple[int, int, int] | None = None):
    """``(db, conditions)`` of zeros shaped and typed as `run.training.initial_state` will return
    them (``sizes``: `expected_sizes`, found here by default; None where those are unknown)."""
    from evojax_motion.evolution.conditions import conditions_from_tree, conditions_template
    from evojax_motion.evolution.step import with_search_candidates
    from evojax_motion.motion.database import make_database

    sizes = expected_sizes(cfg, robot) if sizes is None else sizes
    if sizes is None:
        return None
    n, t, j = sizes
    m = cfg.evolution.conditions
    humans = make_database(np.zeros((n, t, j)), np.ones(n), np.zeros((n, 3)), capacity=n + m)
    conditions = conditions_from_tree(conditions_template(m, t, j))
    return humans, with_search_candidates(humans, conditions, cfg.basis, placeholder=True)


class EarlyCompile:
    """What a new run will compile, compiled in background threads from the sizes known before
    the demonstrations exist (`expected_sizes`): the generation step for `expected_inputs`
    (one device, some generations) and `setup_programs`. `start` launches them; `train` calls
    it at once, or, where the demonstrations are synthesised (`run.workflow.synthesises`), when
    their synthesis is traced (so that the step's long trace does not hold the GIL back from
    it). On two cores the compiles overlap each other and the synthesis. Nothing is compiled
    for a demonstrations file that the run will refuse (no sizes): a refused run would wait
    for its compiles before saying what was wrong."""

    def __init__(self, cfg: Config, robot, dyn, short_run: bool = False):
        self._args = (cfg, robot, dyn)
        self._short_run = short_run  # `compile_generation_step`'s
        sizes = expected_sizes(cfg, robot)
        self.setup = None if sizes is None else setup_programs(cfg, robot, dyn, sizes)
        step = sizes is not None and cfg.evolution.generations > 0 and one_device(cfg)
        self._expected = expected_inputs(cfg, robot, sizes) if step else None
        self._threads: list = []

    def start(self) -> None:
        """Launch the compiles (once; nothing where the sizes are unknown)."""
        from evojax_motion.run.cache import Background, signature

        if self._threads:
            return
        if self._expected is not None:
            expected = self._expected

            def compile_step():
                try:
                    db, conditions = expected
                    step = compile_generation_step(
                        *self._args, db, conditions, short_run=self._short_run
                    )
                    return signature(expected), step
                except Exception:  # compiled again in the foreground, which reports it
                    return None

            self._threads.append(Background(compile_step))
        if self.setup is not None:
            setup = self.setup

            def precompile():
                with contextlib.suppress(Exception):  # ditto
                    setup.precompile()

            self._threads.append(Background(precompile, nice=PRECOMPILE_NICE))

    def step(self):
        """``(avals, compiled)`` of the step, or None (not compiled here, or it failed)."""
        self.start()
        return self._threads[0].result() if self._expected is not None else None

    def wait(self) -> None:
        """Until every compile has ended (before an error may end the process)."""
        for thread in self._threads:
            thread.wait()
