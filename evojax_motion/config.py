"""Run configuration: frozen dataclasses loaded from YAML and validated at load time.

Each pipeline stage owns its settings dataclass (``DemoSettings`` in ``demos``, ``BasisSettings`` in
``basis``, ``OptimSettings`` in ``compile_optim``, ``EvolutionSettings`` in ``evolution``,
``TrainSettings`` in ``train``); ``Config`` assembles them. A section's ``__post_init__`` raises
``ValueError("<field>: expected ...")``; the loader turns every problem into a ``UserError`` that
names the file and the dotted key (``configs/x.yaml: evolution.generations: expected ...``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_type_hints

import yaml

from evojax_motion.basis import BasisSettings
from evojax_motion.compile_optim import OptimSettings
from evojax_motion.demos import DemoSettings
from evojax_motion.errors import UserError
from evojax_motion.evolution import EvolutionSettings
from evojax_motion.parallel import ParallelSettings
from evojax_motion.train import TrainSettings

DYNAMICS_BACKENDS = ("rnea", "mjx")
# Every integer of a config is a size, an index or a seed that ends up in an int32 (array shapes,
# the generation counter, PRNG seeds); a larger one is refused here rather than overflowing later.
INT_MIN, INT_MAX = -(2**31), 2**31 - 1


@dataclass(frozen=True)
class RobotConfig:
    """Which robot: a shipped name, or an MJCF path with its controlled joints and end effector.

    ``joints``: None = the hinge and slide joints from the root to the end effector.
    ``end_effector``: a site or body name (``site``: the older name for a site). ``None``: the
    model's only site. ``end_effector_offset``: [m] in its frame. ``velocity_limits``: [rad/s]
    a mapping joint: limit, or one per joint. Checked by `robot.load_robot`.
    """

    name: str = "mahru_arm"
    mjcf: str | None = None
    joints: tuple[str, ...] | None = None
    site: str | None = None
    end_effector: str | None = None
    end_effector_offset: tuple[float, ...] | None = None
    velocity_limits: tuple[float, ...] | dict[str, float] | None = None


@dataclass(frozen=True)
class Config:
    """A whole run. ``dynamics``: inverse-dynamics backend, ``rnea`` (fast) or ``mjx``."""

    seed: int = 0
    robot: RobotConfig = field(default_factory=RobotConfig)
    dynamics: str = "rnea"
    demos: DemoSettings = field(default_factory=DemoSettings)
    demos_file: str | None = None
    basis: BasisSettings = field(default_factory=BasisSettings)
    compiler: OptimSettings = field(default_factory=OptimSettings)
    evolution: EvolutionSettings = field(default_factory=EvolutionSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    parallel: ParallelSettings = field(default_factory=ParallelSettings)

    def __post_init__(self):
        if self.dynamics not in DYNAMICS_BACKENDS:
            raise ValueError(
                f"dynamics: expected one of {DYNAMICS_BACKENDS}, got {self.dynamics!r}"
            )


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp)).replace("NoneType", "null")


def _coerce(value: Any, tp, key: str):
    """Check ``value`` against the annotation ``tp``; return it converted (lists -> tuples)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except UserError as e:
                errors.append(str(e))
        raise UserError(errors[0] if errors else f"{key}: unexpected null")
    if origin is tuple:
        item = typing.get_args(tp)[0]
        if not isinstance(value, (list, tuple)):
            raise UserError(f"{key}: expected a list of {_type_name(item)}, got {value!r}")
        return tuple(_coerce(v, item, f"{key}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise UserError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{key}: expected an integer, got {value!r}")
        if not INT_MIN <= value <= INT_MAX:
            raise UserError(f"{key}: expected an integer within int32 range, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"{key}: expected a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float range
            number = math.inf
        if not math.isfinite(number):
            raise UserError(f"{key}: expected a finite number, got {value!r}")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise UserError(f"{key}: expected a string, got {value!r}")
        return value
    return value


def _build(cls, data: Any, prefix: str = ""):
    """Instantiate dataclass ``cls`` from a mapping, naming ``prefix.key`` in every error."""
    where = prefix or "config"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise UserError(f"{where}: expected a mapping of keys, got {data!r}")
    hints = get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in data.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; known keys: {', '.join(names)}"
            raise UserError(f"{dotted}: unknown key{hint}")
        kwargs[key] = _coerce(value, hints[key], dotted)
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise UserError(f"{prefix + '.' if prefix else ''}{e}") from None


def _apply_override(data: dict, item: str) -> None:
    """Apply ``a.b.c=value`` (value parsed as YAML) to the nested mapping ``data`` in place."""
    if "=" not in item:
        raise UserError(f"--set {item}: expected KEY=VALUE, e.g. evolution.generations=20")
    key, raw = item.split("=", 1)
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        raise UserError(f"--set {item}: value is not valid YAML") from None
    parts = key.strip().split(".")
    node = data
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise UserError(f"--set {key}: {part} is not a section")
        node = child
    node[parts[-1]] = value


def config_from_dict(data: dict, overrides: typing.Sequence[str] = (), source: str = "") -> Config:
    """Validated ``Config`` from a plain mapping plus ``KEY=VALUE`` overrides."""
    data = yaml.safe_load(yaml.safe_dump(data or {}))  # deep copy, plain types only
    for item in overrides:
        _apply_override(data, item)
    try:
        return _build(Config, data)
    except UserError as e:
        raise UserError(f"{source}: {e}" if source else str(e)) from None


def load_config(path: str | os.PathLike, overrides: typing.Sequence[str] = ()) -> Config:
    """Read YAML ``path`` (safe loader), apply overrides, validate. Raises ``UserError``."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: config file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: unreadable config file ({type(e).__name__})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UserError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if data is not None and not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping of sections at the top level")
    return config_from_dict(data or {}, overrides, source=str(path))


def config_to_dict(cfg) -> dict:
    """Plain nested dict of a config (tuples become lists), for YAML and comparisons."""
    return yaml.safe_load(yaml.safe_dump(_plain(dataclasses.asdict(cfg)), sort_keys=False))


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def config_to_yaml(cfg) -> str:
    """The resolved config as YAML text that ``load_config`` reads back to an equal ``Config``."""
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
