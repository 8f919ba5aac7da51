"""The memory a run will need, estimated from its settings before any work is done.

`estimate_run` (``train``) and `estimate_demos` (``demos``) count the values of the large arrays
a config implies, part by part (`Part`), each times a factor in bytes per value for its copies and
temporaries (`FACTORS`, measured). Some parts are held for the whole run (the database, the time
grid, the condition set); the others belong to one phase (the synthesis of the demonstrations,
their costs, the condition draw, the generation step), and the phases run one after another, so
the estimate is the process's fixed share (`BASE_BYTES`: Python, JAX, MuJoCo, XLA compiling the
generation step) + the held parts + the largest phase.

`check_estimate` compares it with the memory there is (host RAM, `host_memory`; where JAX
reports an accelerator's memory, `device_memory`, the device parts against that) and refuses,
before anything is computed or written, with one line that gives the estimate, the memory
available and the setting to lower. ``EVOJAX_MOTION_MEMORY_CHECK=off`` skips the refusal.

Symbols: n demonstrations, T samples, J joints, B bodies of the robot's model, P = ceil(n x
``demos.oversample``) synthesis trials per round, m conditions (per device with
``parallel.devices``), c = m x ``candidates_per_condition``, k neighbours, K components, Z = J x
``max_free_per_joint``, b = min(m x ``n_starts``, ``max_batch``) problems optimised at once, L =
`compiler.basis.NEIGHBOUR_BLOCK_ENTRIES` distances per block of the neighbour search.

- held: time grid ``T^2`` (`timegrid`'s (T, T) operators: float64, float32, program constants);
  database ``(n + m) T J`` (host copies: numpy, checkpoints, files; and a device copy in and
  out of the step); condition set ``m (T J + 5 k)`` (the human-only reference, candidate lists).
- synthesis (`demos`): ``P T (J + B)``; costs (`motion.objective.CostProgram`): ``n T (J + B)``.
- condition draw (`conditions`): ``min(c, L / n) n + m k T J``.
- generation step (`evolution`): neighbour search ``min(m, L / (n + m)) (n + m)``, bases
  ``m (k + 2 K + 6) T J`` (neighbours, PCA, the reduced problems), optimiser ``b T (J Z + B)``.

Calibration (`FACTORS`, `BASE_BYTES`): peak resident memory (``/usr/bin/time``, the kernel's
``ru_maxrss``) of ``train CONFIG --set evolution.generations=1`` on a 2-core CPU with JAX's
compilation cache off. ``configs/tiny.yaml``: 1.24 GiB as it is and 1.21 GiB at T = 400 (the
compile dominates), 1.90 GiB at T = 2,000 (the time grid), 1.31 and 2.07 GiB at 4,000 and
20,000 demonstrations (the synthesis, while the step compiles beside it), 1.66 and 2.28 GiB at
3,000 and 12,000 conditions (the neighbour search); ``configs/catch_ball.yaml``: 0.98 GiB. On
one H100 (same runs, JAX's peak ``memory_stats``): the GPU's peak 0.14 GiB for the tiny run, 0.14,
2.24 and 14.1 GiB for ``configs/catch_ball.yaml`` at 300, 10,000 and 100,000 conditions; the
host's 3.7-4.1 GiB, and 7.2 GiB at 100,000 conditions. The estimate is 0.85-1.3 times each CPU
peak, 0.84-1.26 times each GPU peak and 0.77-1.07 times each host peak beside the GPU;
``tests/test_bad_input.py`` checks a tiny run on the CPU.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from evojax_motion.errors import UserError

if TYPE_CHECKING:
    from evojax_motion.model.robot import Robot
    from evojax_motion.settings import Config

GIB = 2**30
# Held by a run's process whatever its sizes: Python, JAX and MuJoCo (0.26 GiB after import), and
# XLA compiling the programs (a tiny run's peak: 1.21-1.24 GiB; the paper configuration's 0.98).
BASE_BYTES = int(1.2 * GIB)
# The same beside an accelerator, its libraries loaded (CUDA: 3.7-4.1 GiB on an H100's host).
HOST_BASE_BYTES = 4 * GIB
# An accelerator's own share: XLA's workspace and the programs' constants (an H100: 0.14 GiB at
# 300 conditions, where the arrays take a few MiB).
DEVICE_BASE_BYTES = 128 * 2**20
# Bytes per value of each part at its peak, its copies and temporaries included (module docstring).
FACTORS = {
    "time grid": 160.0,
    "database": 24.0,
    "database on device": 8.0,
    "condition set": 8.0,
    "synthesis": 100.0,
    "costs": 40.0,
    "condition draw": 12.0,
    "neighbour search": 8.0,
    "bases": 5.0,
    "optimiser": 8.0,
}
CHECK_ENV = "EVOJAX_MOTION_MEMORY_CHECK"  # "off": never refuse


@dataclass(frozen=True)
class Part:
    """One part of an estimate: ``values`` it holds, the setting that sizes it (what to lower),
    the ``phase`` it belongs to (None: held for the whole run), and whether it lives on the
    accelerator (on a CPU everything is host memory)."""

    name: str
    values: float
    setting: str
    phase: str | None = None
    on_device: bool = True

    @property
    def bytes(self) -> float:
        return self.values * FACTORS[self.name]


def _peak(parts: list[Part]) -> tuple[float, list[Part]]:
    """``(bytes, the parts that make them)``: the held parts and the largest phase."""
    held = [p for p in parts if p.phase is None]
    phases: dict[str, list[Part]] = {}
    for p in parts:
        if p.phase is not None:
            phases.setdefault(p.phase, []).append(p)
    top = max(phases.values(), key=lambda ps: sum(p.bytes for p in ps), default=[])
    chosen = held + top
    return sum(p.bytes for p in chosen), chosen


@dataclass(frozen=True)
class Estimate:
    """The memory of a run, from its `Part` s (module docstring)."""

    parts: tuple[Part, ...]

    def total(self) -> float:
        """Bytes of one memory holding everything (a CPU)."""
        return BASE_BYTES + _peak(list(self.parts))[0]

    def host(self) -> float:
        """Bytes of host memory beside an accelerator."""
        return HOST_BASE_BYTES + _peak([p for p in self.parts if not p.on_device])[0]

    def device(self) -> float:
        """Bytes of each accelerator's memory."""
        return DEVICE_BASE_BYTES + _peak([p for p in self.parts if p.on_device])[0]

    def largest(self, on_device: bool | None = None) -> Part:
        """The largest part of the peak (of the host's or the device's, or of both)."""
        parts = [p for p in self.parts if on_device is None or p.on_device == on_device]
        return max(_peak(parts)[1], key=lambda p: p.bytes)


def fmt_bytes(n: float) -> str:
    """``1.5 GiB``, ``340 MiB``, ``8.2e+04 TiB`` (binary units)."""
    for unit, size in (("TiB", 2**40), ("GiB", GIB), ("MiB", 2**20)):
        if n >= size:
            value = n / size
            return f"{value:.1e} {unit}" if value >= 1e4 else f"{value:.3g} {unit}"
    return f"{n / 2**10:.3g} KiB"


@dataclass(frozen=True)
class Sizes:
    """What an estimate is made of (symbols of the module docstring)."""

    n: int
    t: int
    j: int
    bodies: int
    trials: int = 0  # P; 0: demonstrations read from a file
    m: int = 0  # 0: the ``demos`` command
    candidates: int = 0  # c
    k: int = 0
    components: int = 0  # K
    free: int = 0  # Z
    batch: int = 0  # b
    devices: int = 1
    count_setting: str = "demos.count"  # what sets n
    batch_setting: str = "compiler.max_batch"  # what sets b


def estimate_parts(s: Sizes) -> Estimate:
    """The `Estimate` of sizes ``s``."""
    from evojax_motion.compiler.basis import NEIGHBOUR_BLOCK_ENTRIES as L

    row, per_sample = s.t * s.j, s.j + s.bodies
    rows = float(s.n + s.m) * row
    db_setting = "evolution.conditions" if s.m > s.n else s.count_setting
    parts = [
        Part("time grid", float(s.t) ** 2, "demos.samples", on_device=False),
        Part("database", rows, db_setting, on_device=False),
        Part("database on device", rows, db_setting),
        Part("costs", float(s.n) * s.t * per_sample, s.count_setting, "costs"),
    ]
    if s.trials:
        synthesis = float(s.trials) * s.t * per_sample
        parts.append(Part("synthesis", synthesis, "demos.count", "synthesis"))
    if s.m:
        m = math.ceil(s.m / s.devices)  # per device; the database is whole on each
        n_all = s.n + s.m
        conditions = "evolution.conditions"
        draw = min(s.candidates, max(1, L // max(s.n, 1))) * float(s.n) + float(s.m) * s.k * row
        search = min(m, max(1, L // n_all)) * float(n_all)
        bases = float(m) * (s.k + 2 * s.components + 6) * row
        optimiser = float(s.batch) * s.t * (s.j * s.free + s.bodies)
        step = "generation step"
        parts += [
            Part("condition set", float(m) * (row + 5 * s.k), conditions),
            Part("condition draw", draw, conditions, "condition draw"),
            Part("neighbour search", search, conditions, step),
            Part("bases", bases, conditions, step),
            Part("optimiser", optimiser, s.batch_setting, step),
        ]
    return Estimate(tuple(parts))


def run_sizes(cfg: Config, robot: Robot, devices: int = 1, demos_only: bool = False) -> Sizes:
    """The `Sizes` of ``cfg`` for ``robot`` from the settings alone (n and T of a ``demos_file``
    from its header: `motion.database.database_shape`). ``demos_only``: the ``demos`` command."""
    from evojax_motion.motion.database import database_shape

    j, bodies = len(robot.joint_names), int(robot.mj_model.nbody)
    if cfg.demos_file is not None and not demos_only:
        (n, t, _), trials, count_setting = database_shape(cfg.demos_file), 0, "demos_file"
    else:
        n, t, count_setting = cfg.demos.count, cfg.demos.samples, "demos.count"
        trials = math.ceil(n * cfg.demos.oversample)
    if demos_only:
        return Sizes(n=n, t=t, j=j, bodies=bodies, trials=trials)
    evo, opt = cfg.evolution, cfg.compiler
    problems = math.ceil(evo.conditions / devices) * opt.n_starts
    if opt.max_batch is not None and opt.max_batch < problems:
        batch, batch_setting = opt.max_batch, "compiler.max_batch"
    else:
        batch = problems
        batch_setting = "compiler.n_starts" if opt.n_starts > 1 else "evolution.conditions"
    return Sizes(
        n=n, t=t, j=j, bodies=bodies, trials=trials, m=evo.conditions,
        candidates=evo.conditions * evo.candidates_per_condition, k=cfg.basis.neighbours,
        components=opt.n_components, free=j * opt.max_free_per_joint, batch=batch,
        devices=devices, count_setting=count_setting, batch_setting=batch_setting,
    )  # fmt: skip


def host_memory() -> int | None:
    """Bytes of host memory this process may use: what it holds, plus the kernel's
    ``MemAvailable`` (else the free pages, ``os.sysconf``) or a cgroup's remaining limit where
    that is lower. None where neither can be read."""
    available = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            return None
    try:  # cgroup v2: memory.max is "max" or a number of bytes
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            available = min(available, int(limit) - used)
    except (OSError, ValueError):
        pass
    return max(available, 0) + _own_resident()


def _own_resident() -> int:
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


def device_memory(devices: list) -> int | None:
    """Bytes free on the fullest of ``devices`` as JAX's allocator reports them
    (``memory_stats()``: ``bytes_limit - bytes_in_use``); None for CPUs or where unreported."""
    free = []
    for d in devices:
        stats = None if d.platform == "cpu" else d.memory_stats()
        if not stats or "bytes_limit" not in stats:
            return None
        free.append(int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)))
    return min(free) if free else None


def _refusal(what: str, needed: float, part: Part, available: float, where: str) -> UserError:
    return UserError(
        f"{part.setting}: {what} needs about {fmt_bytes(needed)} of memory ({part.name} "
        f"{fmt_bytes(part.bytes)}), more than the {fmt_bytes(available)} {where}; lower "
        f"{part.setting} (or set {CHECK_ENV}=off to try anyway)"
    )


def check_estimate(estimate: Estimate, what: str, devices: list | None = None) -> None:
    """Refuse (`UserError`: one line naming the setting to lower) an ``estimate`` larger than the
    memory there is: all of it against host RAM where the devices are CPUs (or unknown), else
    its device part against each accelerator's free memory and its host part against host RAM.
    Nothing where ``EVOJAX_MOTION_MEMORY_CHECK=off``."""
    if os.environ.get(CHECK_ENV, "").strip().lower() in ("off", "0", "no", "false"):
        return
    host = host_memory()
    on_device = device_memory(devices) if devices else None
    if on_device is None:
        if host is not None and estimate.total() > host:
            part = estimate.largest()
            raise _refusal(what, estimate.total(), part, host, "of host memory available")
        return
    if estimate.device() > on_device:
        part = estimate.largest(on_device=True)
        kind = getattr(devices[0], "device_kind", "device") if devices else "device"
        raise _refusal(what, estimate.device(), part, on_device, f"free on each {kind}")
    if host is not None and estimate.host() > host:
        part = estimate.largest(on_device=False)
        raise _refusal(what, estimate.host(), part, host, "of host memory available")


def estimate_run(cfg: Config, robot: Robot, devices: int = 1) -> Estimate:
    """The memory of ``evojax-motion train`` for ``cfg`` on ``devices`` devices."""
    return estimate_parts(run_sizes(cfg, robot, devices))


def estimate_demos(cfg: Config, robot: Robot) -> Estimate:
    """The memory of ``evojax-motion demos`` for ``cfg``: the synthesis and its database."""
    return estimate_parts(run_sizes(cfg, robot, demos_only=True))


def check_run_memory(cfg: Config, robot: Robot) -> None:
    """`check_estimate` of `estimate_run`: ``train`` calls it before any work."""
    from evojax_motion.evolution.sharding import resolve_devices

    devices = resolve_devices(cfg.parallel.devices)
    check_estimate(estimate_run(cfg, robot, len(devices)), "this run", devices)


def check_demos_memory(cfg: Config, robot: Robot) -> None:
    """`check_estimate` of `estimate_demos`, before ``demos`` synthesises anything."""
    import jax

    check_estimate(estimate_demos(cfg, robot), "this synthesis", jax.devices()[:1])


# JAX reserves 75 % of a GPU's memory when its backend starts (``XLA_PYTHON_CLIENT_PREALLOCATE``):
# on one H200 (139 GiB) the first operation took 1.56-1.91 s with that reservation and 0.13-0.16
# s without (3 runs each, CHANGELOG.md), a wait every process pays before its first program.
PREALLOCATE_ENV = "XLA_PYTHON_CLIENT_PREALLOCATE"


def gpu_memory_on_demand(cfg: Config) -> bool:
    """For a short training run (`model.dynamics.is_short_run`), `take_gpu_memory_on_demand`;
    longer runs keep JAX's reservation, which their allocations reuse. Returns whether it set
    the variable."""
    from evojax_motion.model.dynamics import is_short_run

    short = is_short_run(cfg.evolution.generations, cfg.evolution.conditions)
    return short and take_gpu_memory_on_demand()


def take_gpu_memory_on_demand() -> bool:
    """Have JAX take GPU memory as the process needs it instead of reserving most of it at start
    (`PREALLOCATE_ENV` false), unless the environment already says. Call before anything starts
    a JAX backend (it reads the variable then). Returns whether it set the variable. No effect
    on CPU."""
    if PREALLOCATE_ENV in os.environ:
        return False
    os.environ[PREALLOCATE_ENV] = "false"
    return True
