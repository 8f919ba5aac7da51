"""Bad input, fuzzed (issue #9, item 2): hypothesis-generated configs and command lines.

Every mistake (a wrong type, a negative or zero size, an unknown key, a missing or broken file,
NaN in a demonstration, a database of another robot, a non-finite target, a bad option) must give
exactly one line ``error: ...`` on stderr that names the field or file, exit status 2, no
traceback, and leave every file as it was (nothing created, nothing overwritten).

The CLI's ``main(argv)`` runs in-process. No example may reach an XLA compile: every one fails
validation first (an example that compiled would be a valid input and fail the exit-status check).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import shutil
import tempfile
import typing
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evojax_motion.cli.entry import main
from evojax_motion.run.compilation import EarlyCompile
from evojax_motion.settings import Config, config_to_dict, load_config

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "tiny.yaml"
ADL = REPO / "evojax_motion" / "data" / "ue_adl_sample"
FUZZ = dict(
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    database=None,  # the examples are derived from a fixed seed: the same in CI as here
    derandomize=True,
)
N_CONFIG, N_CLI = 300, 300  # examples: 600 in all


# ------------------------------------------------------------------------------ input files


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A folder of good and broken input files; checked unchanged by every example."""
    from online_support import synthetic_database

    from evojax_motion.model.robot import load_robot
    from evojax_motion.motion.database import DatabaseMeta, save_database

    d = tmp_path_factory.mktemp("inputs")

    def meta(robot):
        names = tuple(robot.joint_names)
        return DatabaseMeta(robot.name, robot.mjcf, names, robot.site_name, True, "test")

    mahru, arm6 = load_robot("mahru_arm"), load_robot("arm6")
    db = synthetic_database(mahru, 20, 24, seed=0)
    save_database(d / "good.npz", db, meta(mahru))
    q = db.q.copy()
    q[3, 5, 2] = np.nan
    save_database(d / "nan.npz", db._replace(q=q), meta(mahru))  # NaN in a demonstration
    cond = db.condition.copy()
    cond[7, 1] = np.inf
    save_database(d / "inf.npz", db._replace(condition=cond), meta(mahru))
    save_database(d / "arm6.npz", synthetic_database(arm6, 20, 24, seed=0), meta(arm6))
    (d / "garbage.npz").write_bytes(b"not a zip file")
    (d / "empty.npz").write_bytes(b"")
    np.savez(d / "pickle.npz", q=np.array([object()], dtype=object))  # needs allow_pickle
    np.savez(d / "foreign.npz", x=np.zeros(3))  # an .npz, but not a database
    (d / "garbage.xml").write_text("<mujoco><worldbody><body>")
    (d / "bad.yaml").write_text("evolution: [1, 2\n")
    (d / "binary.yaml").write_bytes(b"\xff\xfe\x00\x81 not utf-8")
    (d / "list.yaml").write_text("- 1\n- 2\n")
    (d / "python.yaml").write_text("!!python/object/apply:os.system ['echo owned']\n")
    (d / "traj.csv").write_text("an existing output\n")
    run = d / "other_run"  # a run folder of another config
    run.mkdir()
    other = config_to_dict(load_config(TINY, ["seed=123"]))
    (run / "config.yaml").write_text(yaml.safe_dump(other))
    (run / "metrics.jsonl").write_text("")
    (d / "no_run").mkdir()
    (d / "no_run" / "notes.txt").write_text("not a run\n")
    mixed = d / "arm6_run"  # a mahru_arm run folder whose final database is of arm6
    mixed.mkdir()
    (mixed / "config.yaml").write_text(TINY.read_text())
    (mixed / "robot.xml").write_text(mahru.mjcf)
    shutil.copy(d / "arm6.npz", mixed / "db_final.npz")
    (d / "dup.yaml").write_text("seed: 0\nevolution:\n  conditions: 6\n\nevolution: {}\n")
    (d / "dup_inner.yaml").write_text("seed: 0\nevolution:\n  conditions: 6\n  conditions: 7\n")
    (d / "empty.yaml").write_text("")
    (d / "comments.yaml").write_text("# nothing but a comment\n\n")
    return d


def _snapshot(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("workdir")


@pytest.fixture(scope="module", autouse=True)
def _no_compile_cache():
    """generate/catch/report would point JAX's compile cache at ~/.cache: keep it off."""
    old = os.environ.get("EVOJAX_MOTION_JAX_CACHE")
    os.environ["EVOJAX_MOTION_JAX_CACHE"] = "off"
    yield
    if old is None:
        del os.environ["EVOJAX_MOTION_JAX_CACHE"]
    else:
        os.environ["EVOJAX_MOTION_JAX_CACHE"] = old


STARTED: list = []  # background compiles started since the last `check_refused` began


@pytest.fixture(scope="module", autouse=True)
def _record_background_compiles():
    """A run refused over its inputs must not have started background compiles
    (`run.compilation.EarlyCompile`): it would wait for them before saying what was wrong."""
    original = EarlyCompile.start

    def start(self):
        original(self)
        if self._threads:
            STARTED.append(self)

    EarlyCompile.start = start
    yield
    EarlyCompile.start = original


def _fill(text: str, d: Path, s: Path) -> str:
    return text.replace("{D}", str(d)).replace("{S}", str(s))


def check_refused(argv: list[str], names: list[str], inputs: Path, workdir: Path) -> str:
    """Run ``evojax-motion argv`` in a fresh folder ``S``: exit 2, one ``error:`` line naming one
    of ``names``, no traceback, no file created or changed in ``S`` or in the inputs. Returns
    that line."""
    s = Path(tempfile.mkdtemp(dir=workdir))
    argv = [_fill(a, inputs, s) for a in argv]
    names = [_fill(n, inputs, s) for n in names]
    before_inputs = _snapshot(inputs)
    STARTED.clear()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(argv)
        except SystemExit as e:  # argparse must not exit on its own (help, errors)
            status = f"SystemExit({e.code})"
    text = err.getvalue()
    lines = text.splitlines()
    where = f"argv={argv}\nstderr={text!r}\nstdout={out.getvalue()[-500:]!r}"
    assert status == 2, where
    assert not STARTED, f"started compiling before refusing: {where}"
    assert len(lines) == 1 and lines[0].startswith("error: "), where
    assert "Traceback" not in text + out.getvalue(), where
    assert any(n in lines[0] for n in names), f"names none of {names}: {where}"
    assert list(s.iterdir()) == [], f"wrote {list(s.rglob('*'))}: {where}"
    assert _snapshot(inputs) == before_inputs, where
    s.rmdir()
    return lines[0]


# --------------------------------------------------------------------------------- configs


def _fields(cls=Config, prefix=""):
    """``(dotted key, type)`` of every setting of a config (sections expanded one level)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp) and not prefix:
            yield f.name, tp
            yield from _fields(tp, f"{f.name}.")
        else:
            yield prefix + f.name, tp


FIELDS = dict(_fields())
# sizes and other settings that must be > 0 (zero and negatives are mistakes) or >= 0
POSITIVE = [
    "demos.count", "demos.samples", "demos.ik_iters", "demos.max_rounds", "demos.fitts_a",
    "demos.fitts_b", "demos.target_width", "demos.max_speed_fraction", "demos.catch_tolerance",
    "demos.oversample", "basis.radius", "basis.neighbours", "basis.w_pos",
    "compiler.n_components", "compiler.max_iters", "compiler.learning_rate", "compiler.bc_leak",
    "compiler.max_free_per_joint", "compiler.hessian_every", "compiler.n_starts",
    "compiler.max_batch", "evolution.conditions", "evolution.generations",
    "evolution.min_neighbours",
    "evolution.candidates_per_condition", "evolution.ik_tolerance", "evolution.duration",
    "evolution.bc_tolerance", "evolution.bc_velocity_tolerance", "train.max_to_keep",
    "train.checkpoint_every", "parallel.devices",
]  # fmt: skip
NON_NEGATIVE = [
    "demos.duration_noise", "demos.asymmetry_std", "demos.curvature_std",
    "demos.limit_margin_deg", "basis.w_rot", "compiler.tol", "compiler.limit_margin",
    "compiler.limit_penalty", "compiler.limit_headroom", "compiler.start_scale",
    "train.plot_condition",
]  # fmt: skip


def _base(tp):
    """The type of a setting without ``None`` (``int | None`` -> ``int``)."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return args[0] if typing.get_origin(tp) in (typing.Union, __import__("types").UnionType) else tp


_words = st.text("abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=10)
_junk_text = st.text("abcxyz 0123456789.-_", min_size=1, max_size=8)  # strings, even "12"
_huge = st.one_of(st.integers(2**31, 2**80), st.integers(-(2**80), -(2**31) - 1))


def _wrong_type(tp) -> st.SearchStrategy:
    """Values that are not of the setting's type (``None`` only where it is not allowed)."""
    base = _base(tp)
    nullable = base is not tp
    lists = st.lists(st.integers(0, 9), min_size=1, max_size=3)
    common = [_junk_text, lists, st.dictionaries(_words, st.integers(0, 9), min_size=1)]
    if not nullable:
        common.append(st.none())
    if dataclasses.is_dataclass(base):
        return st.one_of(st.integers(), _junk_text, lists)
    if base is bool:
        return st.one_of(*common, st.integers(), st.floats(allow_nan=False))
    if base is int:
        non_integral = st.floats(allow_nan=True).filter(lambda x: not float(x).is_integer())
        return st.one_of(*common, st.booleans(), non_integral, _huge)
    if base is float:
        non_finite = st.sampled_from([float("nan"), float("inf"), float("-inf"), 10**400])
        return st.one_of(*common, st.booleans(), non_finite)
    if base is str:
        return st.one_of(st.integers(), st.floats(allow_nan=False), lists, st.booleans())
    # tuples (joint lists, per-joint numbers): a scalar, or items of the wrong kind
    item = typing.get_args(base)[0]
    wrong_item = (
        st.lists(st.integers(), min_size=1, max_size=3)
        if item is str
        else st.lists(_junk_text, min_size=1, max_size=3)
    )
    return st.one_of(st.integers(), st.booleans(), wrong_item)


def _negative_or_zero(key: str) -> st.SearchStrategy:
    number = st.integers if _base(FIELDS[key]) is int else st.floats
    if key in NON_NEGATIVE:
        return number(max_value=-1) if number is st.integers else st.floats(max_value=-1e-6)
    return number(max_value=0) if number is st.integers else st.floats(-1e30, 0.0)


@st.composite
def config_mistakes(draw):
    """``(overrides {dotted: value} | None, config text | None, names)``: one mistake."""
    kind = draw(
        st.sampled_from(
            ["wrong_type", "size", "unknown_key", "missing_file", "bad_file", "bad_config", "cross"]
        )
    )
    if kind == "wrong_type":
        key = draw(st.sampled_from(sorted(FIELDS)))
        return {key: draw(_wrong_type(FIELDS[key]))}, None, [key]
    if kind == "cross":  # each value is fine alone, not with the rest of configs/tiny.yaml
        import jax

        key, value = draw(
            st.one_of(
                st.tuples(st.just("compiler.n_components"), st.integers(24, 60)),  # >= T = 24
                st.tuples(st.just("train.plot_condition"), st.integers(6, 100)),  # >= conditions
                st.tuples(st.just("parallel.devices"), st.integers(len(jax.devices()) + 1, 99)),
            )
        )
        return {key: value}, None, [key]
    if kind == "size":
        key = draw(st.sampled_from(POSITIVE + NON_NEGATIVE))
        return {key: draw(_negative_or_zero(key))}, None, [key]
    if kind == "unknown_key":
        section = draw(st.sampled_from(["", *[k for k, t in FIELDS.items() if "." not in k
                                               and dataclasses.is_dataclass(t)]]))  # fmt: skip
        known = (
            {k.split(".")[-1] for k in FIELDS if k.startswith(section)}
            if section
            else {k for k in FIELDS if "." not in k}
        )
        name = draw(_words.filter(lambda w: w not in known))
        key = f"{section}.{name}" if section else name
        return {key: draw(st.integers(0, 5))}, None, [f"{key}: unknown key"]
    if kind == "missing_file":
        key = draw(st.sampled_from(["demos_file", "robot.mjcf"]))
        path = "{D}/missing/" + draw(_words) + (".npz" if key == "demos_file" else ".xml")
        return {key: path}, None, [path]
    if kind == "bad_file":
        key = draw(st.sampled_from(["demos_file", "robot.mjcf"]))
        names = ["nan", "inf", "arm6", "garbage", "empty", "pickle", "foreign"]
        if key == "robot.mjcf":
            names = ["garbage.xml", "garbage.npz", "list.yaml"]
        else:
            names = [f"{n}.npz" for n in names]
        path = "{D}/" + draw(st.sampled_from(names))
        return {key: path}, None, [path]
    name = draw(st.sampled_from(["bad", "binary", "list", "python", "missing"]))
    return None, f"{{D}}/{name}.yaml", [f"{{D}}/{name}.yaml"]


def _set(key: str, value) -> str:
    """``--set key=value`` with the value in YAML flow style (its type survives the parse)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6).strip()
    return f"{key}={text.removesuffix('...').strip()}"


def _nested(overrides: dict) -> dict:
    data = yaml.safe_load(TINY.read_text())
    for dotted, value in overrides.items():
        node = data
        *parents, last = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    return data


@settings(max_examples=N_CONFIG, **FUZZ)
@given(mistake=config_mistakes(), via=st.sampled_from(["file", "set", "demos"]))
def test_fuzzed_configs_are_refused(inputs, workdir, mistake, via):
    """A config with one mistake, as a YAML file or as ``--set`` overrides, for ``train`` and
    ``demos``: refused before anything is computed or written."""
    overrides, config_path, names = mistake
    s = "{S}"
    if overrides is None:
        argv_cfg, extra = config_path, []
    elif via == "file":
        filled = {k: _fill(v, inputs, workdir) if isinstance(v, str) else v
                  for k, v in overrides.items()}  # fmt: skip
        text = yaml.safe_dump(_nested(filled))
        path = Path(tempfile.mkdtemp(dir=workdir)) / "cfg.yaml"
        path.write_text(text)
        argv_cfg, extra = str(path), []
    else:
        argv_cfg = str(TINY)
        extra = [a for k, v in overrides.items() for a in ("--set", _set(k, v))]
    if via == "demos" and not any(k in CROSS for k in overrides or {}):
        argv = ["demos", "--config", argv_cfg, "--out", f"{s}/demos.npz", *extra]
    else:
        argv = ["train", argv_cfg, "--out", f"{s}/run", "--quiet", *extra]
    check_refused(argv, names, inputs, workdir)


# --------------------------------------------------------------------------- command lines

_num = st.floats(-2.0, 2.0, allow_nan=False).map(lambda x: f"{x:.3f}")
_bad_num = st.sampled_from(["nan", "inf", "-inf", "NaN"])
_not_num = _words.filter(lambda w: w.lower() not in ("nan", "inf", "infinity"))
_good_target = ["0.3", "-0.2", "1.1"]
_good_ball = ["1.5", "-0.2", "1.2", "-3.0", "0.0", "2.0"]
_bad_db = st.sampled_from(
    [
        ("{D}/nan.npz", "{D}/nan.npz"),
        ("{D}/inf.npz", "{D}/inf.npz"),
        ("{D}/garbage.npz", "{D}/garbage.npz"),
        ("{D}/empty.npz", "{D}/empty.npz"),
        ("{D}/pickle.npz", "{D}/pickle.npz"),
        ("{D}/foreign.npz", "{D}/foreign.npz"),
        ("{D}/no_run", "{D}/no_run"),
        ("{S}/missing.npz", "{S}/missing.npz"),
    ]
)


def _vector(n: int, good: list[str]) -> st.SearchStrategy:
    """``(tokens, names)``: n numbers with one mistake (a word, NaN/inf, a wrong count)."""

    @st.composite
    def build(draw):
        kind = draw(st.sampled_from(["word", "nonfinite", "count"]))
        tokens = list(good)
        i = draw(st.integers(0, n - 1))
        if kind == "word":
            tokens[i] = draw(_not_num)
        elif kind == "nonfinite":
            tokens[i] = draw(_bad_num)
        else:
            size = draw(st.sampled_from([k for k in range(0, n + 3) if k != n and k > 0]))
            tokens = draw(st.lists(_num, min_size=size, max_size=size))
        return tokens

    return build()


@st.composite
def generate_mistakes(draw):
    out = "{S}/traj." + draw(st.sampled_from(["csv", "npz", "json"]))
    db, target = "{D}/good.npz", list(_good_target)
    extra: list[str] = []
    kind = draw(st.sampled_from(["target", "db", "duration", "start", "out", "format"]))
    names = {
        "target": ["--target", "target", "unrecognized arguments"],
        "duration": ["--duration", "duration"],
        "start": ["--start", "start posture"],
        "format": ["--format"],
    }.get(kind, [])
    if kind == "target":
        target = draw(_vector(3, _good_target))
    elif kind == "db":
        db, name = draw(_bad_db)
        names = [name]
    elif kind == "duration":
        bad = st.one_of(_bad_num, _not_num, st.floats(-10, 0).map(str), st.just("61"))
        extra = ["--duration", draw(bad)]
    elif kind == "start":
        j = draw(st.sampled_from([1, 3, 6, 8]))
        values = draw(st.lists(_num, min_size=j, max_size=j))
        choice = draw(st.sampled_from(["count", "nonfinite", "limits"]))
        if choice == "nonfinite":
            values = [*["0.0"] * 6, draw(_bad_num)]
        elif choice == "limits":
            values = ["0.0"] * 7
            values[draw(st.integers(0, 6))] = draw(st.sampled_from(["7", "-7", "100"]))
        extra = ["--start", *values]
    elif kind == "out":
        choice = draw(st.sampled_from(["suffix", "exists"]))
        if choice == "suffix":
            out = "{S}/traj." + draw(_words.filter(lambda w: w not in ("csv", "npz", "json")))
            names = [out]
        else:
            out = "{D}/traj.csv"  # exists, no --force: kept as it is
            names = [out]
    else:
        extra = ["--format", draw(_words.filter(lambda w: w not in ("csv", "npz", "json")))]
    argv = ["generate", "--db", db, "--target", *target, "--out", out, *extra]
    return argv, names


@st.composite
def catch_mistakes(draw):
    ball, db, extra = list(_good_ball), "{D}/good.npz", []
    kind = draw(st.sampled_from(["ball", "db", "drag", "horizon", "reaction", "speed"]))
    names = [f"--{kind}", kind]
    if kind == "ball":
        ball = draw(_vector(6, _good_ball))
        names.append("unrecognized arguments")
    elif kind == "speed":
        ball = [*_good_ball[:3], draw(st.sampled_from(["150", "-101", "1e5"])), "0", "0"]
        names = ["--ball"]
    elif kind == "db":
        db, name = draw(_bad_db)
        names = [name]
    elif kind == "drag":
        extra = ["--drag", draw(st.one_of(_bad_num, st.sampled_from(["-0.1", "1", "5"])))]
    elif kind == "horizon":
        bad = st.one_of(_bad_num, st.sampled_from(["0", "-1", "10.5", "1e308"]), _not_num)
        extra = ["--horizon", draw(bad)]
    else:
        extra = ["--reaction", draw(st.one_of(_bad_num, st.sampled_from(["-0.1", "-5"])))]
    argv = ["catch", "--db", db, "--ball", *ball, "--out", "{S}/catch.csv", *extra]
    return argv, names


_IMPORT_BAD = {
    "--samples": ["0", "-3", "7", "x"],
    "--max-gap": ["-1", "-20", "x"],
    "--cutoff-hz": ["-1", "nan"],
    "--onset-threshold": ["0", "1", "-0.5", "nan"],
    "--max-rms": ["0", "-1", "nan"],
    "--min-duration": ["-1", "nan"],
    "--limit-margin-deg": ["-1", "nan"],
    "--rate": ["0", "-30", "nan"],
    "--unit-scale": ["0", "-1", "nan"],
    "--chunk": ["0", "-1"],
    "--ik-iters": ["0", "-2"],
    "--angle-unit": ["grad", "turns"],
    "--format": ["vicon", "csv", "mp4"],
    "--keypoints": ["garbage", "a=b=c"],
    "--weights": ["shoulder=x", "x"],
    "--marker-model": ["{S}/missing_model.yaml", "nope"],
    "--robot": ["nope", "{S}/missing_robot.xml", "{D}/garbage.xml"],
}


@st.composite
def import_mistakes(draw):
    kind = draw(st.sampled_from([*_IMPORT_BAD, "path", "out"]))
    fmt, out, paths, extra = "vicon-csv", "{S}/imported.npz", [str(ADL)], []
    if kind == "path":
        paths = ["{S}/" + draw(_words) + ".csv"]
        names = paths
    elif kind == "out":
        out = draw(st.sampled_from(["{D}/good.npz", "{S}/imported.csv"]))
        names = [out]
    else:
        value = draw(st.sampled_from(_IMPORT_BAD[kind]))
        if kind == "--format":
            fmt = value
        else:
            extra = [kind, value]
        names = [kind, kind.lstrip("-")] + ([value] if kind == "--robot" else [])
    argv = ["import", "--format", fmt, "--robot", "mahru_arm", "--out", out, *extra, *paths]
    return argv, names


@st.composite
def report_mistakes(draw):
    kind = draw(st.sampled_from(["run", "snapshots", "gif-frames", "renderer", "condition"]))
    run, extra = "{D}/other_run", []
    if kind == "run":
        run = draw(st.sampled_from(["{S}/missing_run", "{D}/no_run", "{D}/good.npz"]))
        names = [run]
    elif kind == "renderer":
        extra = ["--renderer", draw(_words.filter(lambda w: w not in ("auto", "mujoco", "stick")))]
        names = ["--renderer"]
    elif kind == "condition":
        extra = ["--condition", draw(st.one_of(_not_num, st.just("1.5")))]
        names = ["--condition"]
    else:
        value = draw(st.one_of(st.integers(-5, 1).map(str), _not_num))
        extra = [f"--{kind}", value]
        names = [f"--{kind}"]
    if kind in ("snapshots", "gif-frames") and not extra[1].lstrip("-").isdigit():
        names = [f"--{kind}"]
    if kind in ("snapshots", "gif-frames", "renderer", "condition"):
        run = "{D}/no_run"  # the option is refused before the folder is looked at ...
        names = [*names, run]  # ... or the folder is: either names what is wrong
    return ["report", run, "--out", "{S}/report", *extra], names


@st.composite
def train_mistakes(draw):
    kind = draw(st.sampled_from(["out_file", "other_run", "not_empty", "resume", "missing"]))
    if kind == "out_file":
        return ["train", str(TINY), "--out", "{D}/good.npz"], ["{D}/good.npz"]
    if kind == "other_run":
        resume = draw(st.sampled_from([[], ["--resume"]]))
        return ["train", str(TINY), "--out", "{D}/other_run", *resume], ["{D}/other_run"]
    if kind == "not_empty":
        return ["train", str(TINY), "--out", "{D}/no_run"], ["{D}/no_run"]
    if kind == "resume":
        return ["train", str(TINY), "--out", "{S}/new_run", "--resume"], ["{S}/new_run"]
    path = "{S}/" + draw(_words) + ".yaml"
    return ["train", path, "--out", "{S}/run"], [path]


CROSS = ("compiler.n_components", "train.plot_condition", "parallel.devices")
SUBCOMMANDS = ("train", "generate", "catch", "demos", "import", "report")


@st.composite
def parser_mistakes(draw):
    """Unknown subcommands and options, missing required arguments."""
    kind = draw(st.sampled_from(["command", "option", "missing"]))
    sub = draw(st.sampled_from(SUBCOMMANDS))
    if kind == "command":
        word = draw(_words.filter(lambda w: w not in SUBCOMMANDS))
        return [word], ["command", word]
    if kind == "option":
        return [sub, f"--{draw(_words)}x", "{S}/x"], ["--", "arguments"]
    return [sub], ["required", sub]


@settings(max_examples=N_CLI, **FUZZ)
@given(
    case=st.one_of(
        generate_mistakes(),
        catch_mistakes(),
        import_mistakes(),
        report_mistakes(),
        train_mistakes(),
        parser_mistakes(),
    )
)
def test_fuzzed_command_lines_are_refused(inputs, workdir, case):
    argv, names = case
    check_refused(argv, names, inputs, workdir)


@pytest.mark.parametrize("value", ["-inf", "-Infinity", "-nan"])
def test_negative_non_finite_values_are_named_by_their_option(inputs, workdir, value):
    """A found case: argparse took "-inf" for an option ("unrecognized arguments"); the option's
    own check must name it."""
    argv = ["generate", "--db", "{D}/good.npz", "--target", *_good_target, "--out",
            "{S}/traj.csv", "--start", *["0.0"] * 6, value]  # fmt: skip
    check_refused(argv, ["--start", "start posture"], inputs, workdir)


def test_fuzz_covers_at_least_200_cases():
    assert N_CONFIG + N_CLI >= 200


# ------------------------------------------------ sizes checked first, nothing accepted silently

_TRAIN = ["train", str(TINY), "--out", "{S}/run", "--quiet"]
_DEMOS = ["demos", "--config", str(TINY), "--out", "{S}/demos.npz"]
_GENERATE = ["generate", "--target", *_good_target, "--out", "{S}/traj.csv", "--db"]
_CATCH = ["catch", "--ball", *_good_ball, "--out", "{S}/catch.csv", "--db"]
_TRIALS = [str(ADL / "ADL004" / f"ADL004AR{i}.csv") for i in range(1, 6)]
_MIXED = "arm6_run/db_final.npz: a database of robot 'arm6'"
_ROBOT_XML = "arm6_run/robot.xml beside it is robot 'mahru_arm'"
_TOO_BIG = "memory"

# case: (argv, texts the error line must hold, texts it must not hold)
REFUSALS: dict[str, tuple[list[str], list[str], list[str]]] = {
    # sizes that cannot fit: the estimate, the memory there is and the setting to lower
    "train T=100000": (
        [*_TRAIN, "--set", "demos.samples=100000"], [_TOO_BIG, "lower demos.samples"], []
    ),
    "train 1e8 demos": (
        [*_TRAIN, "--set", "demos.count=100000000"], [_TOO_BIG, "lower demos.count"], []
    ),
    "train 1e9 conditions": (
        [*_TRAIN, "--set", "evolution.conditions=1000000000"],
        ["evolution.conditions", _TOO_BIG, "lower evolution.conditions"], [],
    ),
    "demos T=100000": (
        [*_DEMOS, "--set", "demos.samples=100000"], [_TOO_BIG, "lower demos.samples"], []
    ),
    "demos 1e8 demos": (
        [*_DEMOS, "--set", "demos.count=100000000"], [_TOO_BIG, "lower demos.count"], []
    ),
    "import capacity below trials": (
        ["import", "--format", "vicon-csv", "--out", "{S}/x.npz", "--capacity", "2", *_TRIALS],
        ["--capacity: expected >= the 5 trials found, got 2"], [],
    ),
    # --set errors name the --set argument, not the config file
    "set not an int": (
        [*_TRAIN, "--set", "demos.count=abc"],
        ["--set demos.count=abc: demos.count: expected an integer"], [str(TINY)],
    ),
    "set float for an int": (
        [*_DEMOS, "--set", "demos.count=1e8"],
        ["--set demos.count=1e8: demos.count: expected an integer", "write 100000000"], [str(TINY)],
    ),
    "set nested unknown key": (
        [*_TRAIN, "--set", "demos.region.nope=1"],
        ["--set demos.region.nope=1: demos.region.nope: unknown key", "known keys: frame"], [],
    ),
    "set duplicate key": (
        [*_TRAIN, "--set", "demos={count: 5, count: 6}"],
        ["--set demos={count: 5, count: 6}: duplicate key 'demos.count'"], [],
    ),
    "set combination": (
        [*_TRAIN, "--set", "compiler.n_components=2"],
        ["--set compiler.n_components=2: compiler.max_free_per_joint"], [str(TINY)],
    ),
    "duration beyond a minute": (
        [*_TRAIN, "--set", "evolution.duration=1e9"], ["evolution.duration: expected null or"], []
    ),
    "nan velocity limit": (
        [*_TRAIN, "--set", "robot.velocity_limits={elbow: .nan}"],
        ["robot.velocity_limits.elbow: expected a finite number"], [],
    ),
    # config files
    "duplicate key": (
        ["train", "{D}/dup.yaml", "--out", "{S}/run"],
        ["{D}/dup.yaml: duplicate key 'evolution' at lines 2 and 5"], [],
    ),
    "duplicate nested key": (
        ["demos", "--config", "{D}/dup_inner.yaml", "--out", "{S}/d.npz"],
        ["{D}/dup_inner.yaml: duplicate key 'evolution.conditions' at lines 3 and 4"], [],
    ),
    "empty file": (["train", "{D}/empty.yaml", "--out", "{S}/run"], ["{D}/empty.yaml: empty"], []),
    "comments only": (
        ["demos", "--config", "{D}/comments.yaml", "--out", "{S}/d.npz"],
        ["{D}/comments.yaml: empty config file"], [],
    ),
    # a run folder whose final database is of another robot than its robot.xml
    "generate mixed run": ([*_GENERATE, "{D}/arm6_run"], [_MIXED, _ROBOT_XML], []),
    "generate mixed npz": ([*_GENERATE, "{D}/arm6_run/db_final.npz"], [_MIXED, _ROBOT_XML], []),
    "catch mixed run": ([*_CATCH, "{D}/arm6_run"], [_MIXED, _ROBOT_XML], []),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_refused_in_one_line(inputs, workdir, case):
    """Exit 2, one ``error:`` line that names the field or file (every text of the case), no
    traceback, nothing written (`check_refused`)."""
    argv, must, must_not = REFUSALS[case]
    must = [_fill(t, inputs, workdir) for t in must]
    line = check_refused(argv, must, inputs, workdir)
    for text in must:
        assert text in line, line
    for text in must_not:
        assert text not in line, line


def test_capacity_is_checked_before_the_ik(monkeypatch, inputs, workdir):
    """``--capacity`` below the trials found is refused before any trial is read or solved."""
    from evojax_motion.demonstrations.mocap import importer

    def fail(*args, **kwargs):
        raise AssertionError("the trials were prepared before --capacity was checked")

    monkeypatch.setattr(importer, "_prepare_markers", fail)
    argv = REFUSALS["import capacity below trials"][0]
    check_refused(argv, ["--capacity"], inputs, workdir)


_REFUSE_SCRIPT = """
import json, resource, sys, time
from evojax_motion.cli.entry import main
from evojax_motion.model.robot import load_robot
import jax
jax.devices()
load_robot("mahru_arm")  # the robot a refused run loads anyway
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
status = main(sys.argv[1:])
seconds = time.perf_counter() - t0
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"status": status, "seconds": seconds, "grew_kib": after - before}))
"""
REFUSE_SECONDS = 15.0  # loading the robot and its dynamics: ~1 s on 2 busy CPU cores
REFUSE_GROWTH_KIB = 100 * 1024  # peak resident memory the refusal may add


@pytest.mark.parametrize(
    "setting", ["demos.samples=100000", "demos.count=100000000", "evolution.conditions=1000000000"]
)
def test_absurd_sizes_are_refused_at_once_without_allocating(tmp_path, setting):
    """In a fresh process (its peak resident memory is its own): refused in seconds, and the
    process's peak grew by less than `REFUSE_GROWTH_KIB` (the arrays were never made)."""
    import json
    import subprocess
    import sys

    argv = ["train", str(TINY), "--out", str(tmp_path / "run"), "--quiet", "--set", setting]
    env = {**os.environ, "EVOJAX_MOTION_JAX_CACHE": "off", "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-c", _REFUSE_SCRIPT, *argv], capture_output=True, text=True, env=env,
        timeout=600, cwd=REPO,
    )  # fmt: skip
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["status"] == 2, done.stderr
    assert result["seconds"] < REFUSE_SECONDS, result
    assert result["grew_kib"] < REFUSE_GROWTH_KIB, result
    assert setting.split("=")[0] in done.stderr
    assert not (tmp_path / "run").exists()


# The run's peak is read from VmHWM, its own address space's high-water mark: ru_maxrss is kept
# across exec on Linux, so a child started by vfork (Python's subprocess) from a pytest worker
# reported the worker's peak (2.8-3.6 GiB where the run's own was 1.1 GiB).
_PEAK_SCRIPT = """
import json, re, resource, sys
from evojax_motion.cli.entry import main
status = main(sys.argv[1:])
try:
    with open("/proc/self/status") as f:
        peak = int(re.search(r"VmHWM:\\s*(\\d+) kB", f.read()).group(1))
except OSError:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"status": status, "peak_kib": peak}))
"""
ESTIMATE_WITHIN = 2.0  # the estimate is this close to the measured peak (either way)
# What tests/conftest.py sets for the test run only (a shared XLA cache, no CPU fusion emitters:
# both lower a compile's memory); a measured run goes without them, as a user's does.
_TEST_ONLY_ENV = (
    "JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
    "EVOJAX_TEST_XLA_CACHE",
)  # fmt: skip
_TEST_ONLY_FLAG = "--xla_cpu_use_fusion_emitters=0"


def _user_environment() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _TEST_ONLY_ENV}
    flags = [f for f in env.get("XLA_FLAGS", "").split() if f != _TEST_ONLY_FLAG]
    env["XLA_FLAGS"] = " ".join(flags)
    return env


@pytest.mark.slow
def test_memory_estimate_is_near_the_measured_peak_of_a_tiny_run(tmp_path):
    """`run.memory.estimate_run` of ``configs/tiny.yaml`` (one generation) against the peak resident
    memory of that run in a fresh process (compilation cache off, as `BASE_BYTES` assumes)."""
    import json
    import subprocess
    import sys

    from evojax_motion.model.robot import load_robot
    from evojax_motion.run.memory import estimate_run

    overrides = ["evolution.generations=1"]
    argv = ["train", str(TINY), "--out", str(tmp_path / "run"), "--quiet"]
    argv += [a for o in overrides for a in ("--set", o)]
    env = {**_user_environment(), "EVOJAX_MOTION_JAX_CACHE": "off", "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-c", _PEAK_SCRIPT, *argv], capture_output=True, text=True, env=env,
        timeout=1800, cwd=REPO,
    )  # fmt: skip
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["status"] == 0, done.stderr[-2000:]
    measured = result["peak_kib"] * 1024
    cfg = load_config(TINY, overrides)
    estimate = estimate_run(cfg, load_robot(cfg.robot.name)).total()
    assert 1 / ESTIMATE_WITHIN <= estimate / measured <= ESTIMATE_WITHIN, (estimate, measured)


def test_sizes_of_a_demos_file_are_read_from_its_header(inputs):
    """The estimate of a run with ``demos_file`` takes n and T from the file's header."""
    from evojax_motion.model.robot import load_robot
    from evojax_motion.motion.database import database_shape, load_database
    from evojax_motion.run.memory import run_sizes

    path = inputs / "good.npz"
    shape = load_database(path)[0].q.shape
    assert database_shape(path) == shape
    cfg = load_config(TINY, [f"demos_file={path}"])
    sizes = run_sizes(cfg, load_robot("mahru_arm"))
    assert (sizes.n, sizes.t, sizes.j) == shape
    assert sizes.trials == 0


def test_shared_inputs_survive(inputs, workdir):
    """The module's inputs are never changed; the workdir folder holds no leftovers."""
    check_refused(["train", str(TINY), "--out", "{D}/traj.csv"], ["{D}/traj.csv"], inputs, workdir)
    assert [p for p in workdir.rglob("*") if p.is_file() and p.name != "cfg.yaml"] == []
    shutil.rmtree(workdir)
