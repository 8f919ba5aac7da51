"""Run configuration: frozen dataclasses loaded from YAML and validated at load time.

Each section's settings dataclass lives beside this module, one file per stage
(``settings.demonstrations.DemoSettings``, ``settings.compiler.BasisSettings`` and
``OptimSettings``, ``settings.evolution.EvolutionSettings`` and ``ParallelSettings``,
``settings.run.TrainSettings``); ``Config`` assembles them. A section's ``__post_init__`` raises
``ValueError("<field>: expected ...")``; the loader turns every problem into a ``UserError`` that
names the file and the dotted key (``configs/x.yaml: evolution.generations: expected ...``), or the
``--set`` argument that set it (``--set demos.count=abc: demos.count: expected ...``).

The YAML reader (`load_yaml`) is PyYAML's safe loader, stricter in two ways: a key written twice in
one mapping is an error naming the key and both lines (PyYAML keeps the last one silently), and
numbers are read as YAML 1.2 writes them (``1e8`` is a number, not the string "1e8"). An integer
setting refuses a number written with a decimal point or an exponent (``1e8``, ``100.0``), saying
how to write it.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_type_hints

import yaml

from evojax_motion.errors import UserError, read_user_file
from evojax_motion.settings.compiler import BasisSettings, OptimSettings
from evojax_motion.settings.demonstrations import DemoSettings
from evojax_motion.settings.evolution import EvolutionSettings, ParallelSettings
from evojax_motion.settings.online import MAX_DURATION
from evojax_motion.settings.run import TrainSettings

DYNAMICS_BACKENDS = ("rnea", "mjx")
# Every integer of a config is a size, an index or a seed that ends up in an int32 (array shapes,
# the generation counter, PRNG seeds); a larger one is refused here rather than overflowing later.
INT_MIN, INT_MAX = -(2**31), 2**31 - 1


class _Loader(yaml.SafeLoader):
    """`yaml.SafeLoader` that also reads YAML 1.2 numbers: ``1e8``, ``2E-3`` (YAML 1.1, PyYAML's
    default, reads a float only with a dot and a signed exponent: ``1.0e+8``)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


class DuplicateKeyError(yaml.YAMLError):
    """A mapping of a YAML document holds one key twice."""

    def __init__(self, key: str, first: int, second: int):
        lines = f"line {first} twice" if first == second else f"lines {first} and {second}"
        super().__init__(f"duplicate key {key!r} at {lines}")
        self.key, self.first, self.second = key, first, second


def _check_duplicates(node: yaml.Node, prefix: str, seen_nodes: set[int]) -> None:
    """Raise `DuplicateKeyError` (dotted key, both 1-based lines) for the first mapping of the
    composed document ``node`` that holds a key twice. Merge keys (``<<``) are not compared."""
    if id(node) in seen_nodes:  # an alias of a node already checked (or a recursive one)
        return
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        lines: dict[tuple[str, str], int] = {}
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            name = str(key_node.value) if isinstance(key_node, yaml.ScalarNode) else None
            dotted = f"{prefix}.{name}" if prefix and name is not None else (name or prefix)
            if name is not None:
                line = key_node.start_mark.line + 1
                if (key_node.tag, name) in lines:
                    raise DuplicateKeyError(dotted, lines[key_node.tag, name], line)
                lines[key_node.tag, name] = line
            _check_duplicates(value_node, dotted, seen_nodes)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _check_duplicates(item, f"{prefix}[{i}]", seen_nodes)


def load_yaml(text: str) -> Any:
    """The YAML document ``text`` as plain Python data, read safely (no Python objects) and
    strictly: raises `DuplicateKeyError` for a key written twice in a mapping, and
    ``yaml.YAMLError`` for text that is not YAML. ``1e8`` is a number (YAML 1.2). None for an
    empty document."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_duplicates(node, "", set())
        return loader.construct_document(node)
    finally:
        loader.dispose()


def yaml_problem(error: yaml.YAMLError) -> str:
    """One line on what is wrong with a YAML text (`load_yaml`'s errors), with its line."""
    if isinstance(error, DuplicateKeyError):
        return str(error)
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    where = f" at line {mark.line + 1}" if mark is not None else ""
    return f"not valid YAML ({problem}{where})"


@dataclass(frozen=True)
class RobotConfig:
    """Which robot: a shipped name, or an MJCF path with its controlled joints and end effector.

    ``joints``: None = the hinge and slide joints from the root to the end effector.
    ``end_effector``: a site or body name (``site``: the older name for a site). ``None``: the
    model's only site. ``end_effector_offset``: [m] in its frame. ``velocity_limits``: [rad/s]
    a mapping joint: limit, or one per joint. Checked by `model.robot.load_robot`.
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
        duration = self.evolution.duration
        if duration is not None and duration > MAX_DURATION:
            # a longer motion could not be generated from the database (`online`)
            raise ValueError(
                f"evolution.duration: expected null or a number in (0, {MAX_DURATION:g}] [s], "
                f"got {duration!r}"
            )


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp)).replace("NoneType", "null")


def _same_kind(value: Any, tp) -> bool:
    """Whether ``value`` is a mapping for a mapping type or a list for a tuple type."""
    origin = typing.get_origin(tp)
    if isinstance(value, dict):
        return origin is dict or dataclasses.is_dataclass(tp)
    return isinstance(value, (list, tuple)) and origin is tuple


def _coerce(value: Any, tp, key: str):
    """Check ``value`` against the annotation ``tp``; return it converted (lists -> tuples)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        # the arm of the value's kind first: its error is the one to report
        for arg in sorted(args, key=lambda a: not _same_kind(value, a)):
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
    if origin is dict:
        key_type, value_type = typing.get_args(tp)
        if not isinstance(value, dict):
            raise UserError(f"{key}: expected a mapping, got {value!r}")
        return {
            _coerce(k, key_type, f"{key} (a key)"): _coerce(v, value_type, f"{key}.{k}")
            for k, v in value.items()
        }
    if tp is int:
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            raise UserError(
                f"{key}: expected an integer, got {value!r} (written with a decimal point or "
                f"an exponent; write {int(value)})"
            )
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
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise UserError(f"{dotted}: unknown key{hint} (known keys: {', '.join(names)})")
        kwargs[key] = _coerce(value, hints[key], dotted)
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise UserError(f"{prefix + '.' if prefix else ''}{e}") from None


def _apply_override(data: dict, item: str) -> str:
    """Apply ``a.b.c=value`` (value parsed as YAML) to the nested mapping ``data`` in place;
    return the dotted key."""
    if "=" not in item:
        raise UserError(f"--set {item}: expected KEY=VALUE, e.g. evolution.generations=20")
    key, raw = item.split("=", 1)
    key = key.strip()
    try:
        value = load_yaml(raw)
    except DuplicateKeyError as e:
        raise UserError(f"--set {item}: duplicate key {f'{key}.{e.key}'!r}") from None
    except yaml.YAMLError as e:
        raise UserError(f"--set {item}: {yaml_problem(e)}") from None
    parts = key.split(".")
    if not all(parts):
        raise UserError(f"--set {item}: expected a dotted KEY, e.g. evolution.generations")
    node = data
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise UserError(f"--set {item}: {'.'.join(parts[: i + 1])} is not a section")
        node = child
    node[parts[-1]] = value
    return key


def _named_key(error: UserError) -> str:
    """The dotted key a config error names (its text up to the first ': ')."""
    return str(error).split(": ", 1)[0]


def _sets(key: str, field: str) -> bool:
    """Whether an override of dotted ``key`` sets (part of) the setting ``field``, or the
    reverse (``robot=...`` sets ``robot.joints``; ``demos.region.radius`` sets ``demos.region``)."""
    return key == field or field.startswith((f"{key}.", f"{key}[")) or key.startswith(f"{field}.")


def _blame(error: UserError, data: dict, applied: list[tuple[str, str]], source: str) -> str:
    """What to name for a config error: the last ``--set`` argument that set the key it names;
    else the file (``source``) where the file alone is invalid too; else the first ``--set``
    argument after which the config is invalid (a combination, e.g. ``compiler.n_components``
    below the file's ``max_free_per_joint``)."""
    field = _named_key(error)
    for key, item in reversed(applied):
        if _sets(key, field):
            return f"--set {item}"
    if not applied:
        return source
    partial = yaml.safe_load(yaml.safe_dump(data))
    try:
        _build(Config, partial)
    except UserError:
        return source
    for _, item in applied:
        _apply_override(partial, item)
        try:
            _build(Config, partial)
        except UserError:
            return f"--set {item}"
    return source


def config_from_dict(data: dict, overrides: typing.Sequence[str] = (), source: str = "") -> Config:
    """Validated ``Config`` from a plain mapping plus ``KEY=VALUE`` overrides. An error names
    the ``--set`` argument at fault (`_blame`), else ``source`` (the file), then the key."""
    data = yaml.safe_load(yaml.safe_dump(data or {}))  # deep copy, plain types only
    merged = yaml.safe_load(yaml.safe_dump(data))
    applied = [(_apply_override(merged, item), item) for item in overrides]
    try:
        return _build(Config, merged)
    except UserError as e:
        where = _blame(e, data, applied, source)
        raise UserError(f"{where}: {e}" if where else str(e)) from None


def load_config(path: str | os.PathLike, overrides: typing.Sequence[str] = ()) -> Config:
    """Read YAML ``path`` (`load_yaml`: safe, duplicate keys refused), apply overrides,
    validate. Raises ``UserError`` naming the file or the ``--set`` argument, and the key."""
    path = Path(path)
    text = read_user_file(path, "config")
    try:
        data = load_yaml(text)
    except yaml.YAMLError as e:
        raise UserError(f"{path}: {yaml_problem(e)}") from None
    if data is None:
        raise UserError(
            f"{path}: empty config file; expected a mapping of sections (seed, robot, demos, "
            "basis, compiler, evolution, train, ...), e.g. configs/tiny.yaml"
        )
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping of sections at the top level")
    return config_from_dict(data, overrides, source=str(path))


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
