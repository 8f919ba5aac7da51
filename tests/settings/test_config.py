"""Config loading: defaults, overrides, and one clear error per kind of mistake."""

import pytest

from evojax_motion.errors import UserError
from evojax_motion.settings import (
    Config,
    config_from_dict,
    config_to_yaml,
    load_config,
    load_yaml,
)


def test_shipped_configs_load(tmp_path):
    for name in ("catch_ball", "demo_small", "tiny"):
        cfg = load_config(f"configs/{name}.yaml")
        assert isinstance(cfg, Config)
        # The resolved YAML reads back to an equal config.
        path = tmp_path / f"{name}.yaml"
        path.write_text(config_to_yaml(cfg))
        assert load_config(path) == cfg


def test_paper_setting():
    cfg = load_config("configs/catch_ball.yaml")
    assert cfg.demos.count == 311
    assert cfg.evolution.conditions == 300
    assert cfg.evolution.generations == 10
    assert cfg.basis.radius == pytest.approx(0.15)
    assert cfg.compiler.n_components == 4


def test_dotted_overrides_are_typed():
    cfg = config_from_dict({}, ["evolution.generations=20", "basis.radius=0.2", "dynamics=mjx"])
    assert cfg.evolution.generations == 20
    assert cfg.basis.radius == pytest.approx(0.2)
    assert cfg.dynamics == "mjx"


@pytest.mark.parametrize(
    ("data", "overrides", "message"),
    [
        (
            {"evolution": {"generatons": 3}},
            [],
            r"evolution.generatons: unknown key; did you mean 'generations'",
        ),
        ({}, ["evolution.generations=-3"], r"evolution.generations"),
        ({}, ["evolution.generations=ten"], r"evolution.generations: expected an integer"),
        ({}, ["dynamics=pinocchio"], r"dynamics: expected one of"),
        ({"basis": 3}, [], r"basis: expected a mapping"),
        ({}, ["basis.radius=-1"], r"basis.radius"),
        ({}, ["nope"], r"expected KEY=VALUE"),
        ({"demos": {"count": 0}}, [], r"demos.count"),
    ],
)
def test_mistakes_name_the_key(data, overrides, message):
    with pytest.raises(UserError, match=message):
        config_from_dict(data, overrides)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(UserError, match="config file not found"):
        load_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("evolution: [1, 2\n")
    with pytest.raises(UserError, match="not valid YAML"):
        load_config(bad)
    listy = tmp_path / "list.yaml"
    listy.write_text("- 1\n- 2\n")
    with pytest.raises(UserError, match="mapping"):
        load_config(listy)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", r"empty config file"),
        ("# only a comment\n", r"empty config file"),
        (
            "seed: 0\nevolution:\n  conditions: 6\n  generations: 2\n  conditions: 7\n",
            r"duplicate key 'evolution.conditions' at lines 3 and 5",
        ),
        ("seed: 0\nseed: 1\n", r"duplicate key 'seed' at lines 1 and 2"),
        ("demos: {count: 5, count: 6}\n", r"duplicate key 'demos.count' at line 1 twice"),
        ("evolution: {conditions: 6\n", r"not valid YAML \(.* at line 2\)"),
        ("demos:\n  count: 1e3\n", r"demos.count: expected an integer, got 1000.0 .*write 1000"),
        ("robot:\n  velocity_limits: {elbow: .nan}\n", r"robot.velocity_limits.elbow: expected a"),
        ("evolution:\n  duration: 1e9\n", r"evolution.duration: expected null or a number in"),
        ("demos:\n  region: {nope: 1}\n", r"demos.region.nope: unknown key \(known keys: "),
    ],
)
def test_file_mistakes_name_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match=message) as info:
        load_config(path)
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)


def test_yaml_merge_keys_are_not_duplicates(tmp_path):
    """A ``<<`` merge then an explicit key overrides the merged one (YAML's rule), no error."""
    path = tmp_path / "cfg.yaml"
    path.write_text("evolution: &e {conditions: 6}\ntrain:\n  <<: {plots: true}\n  plots: false\n")
    assert load_config(path).train.plots is False


def test_numbers_are_read_as_yaml_1_2():
    """``1e-3`` is a number (PyYAML's YAML 1.1 reads it as a string), ints stay ints."""
    assert load_yaml("a: 1e-3\nb: 2.5E+2\nc: 7\nd: e5\ne: .5e1\n") == {
        "a": 0.001, "b": 250.0, "c": 7, "d": "e5", "e": 5.0,
    }  # fmt: skip
    cfg = config_from_dict({}, ["evolution.ik_tolerance=2e-3"])
    assert cfg.evolution.ik_tolerance == pytest.approx(2e-3)


@pytest.mark.parametrize(
    ("overrides", "culprit"),
    [
        (["demos.count=abc"], "--set demos.count=abc: demos.count: expected an integer"),
        (["seed=1", "demos.count=0"], "--set demos.count=0: demos.count: expected an integer >= 1"),
        (["demos={count: 0}"], "--set demos={count: 0}: demos.count:"),
        (["compiler.n_components=2"], "--set compiler.n_components=2: compiler.max_free_per_j"),
        (["evolution.nope=1"], "--set evolution.nope=1: evolution.nope: unknown key (known"),
        (["demos.count=3", "demos.count=x"], "--set demos.count=x: demos.count:"),
    ],
)
def test_set_errors_name_the_set_argument(overrides, culprit):
    with pytest.raises(UserError) as info:
        load_config("configs/tiny.yaml", overrides)
    assert str(info.value).startswith(culprit), str(info.value)


def test_file_errors_fixed_by_set_are_accepted_and_others_name_the_file(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_text("evolution:\n  conditions: 0\n")
    assert load_config(path, ["evolution.conditions=5"]).evolution.conditions == 5
    with pytest.raises(UserError, match=rf"^{path}: evolution.conditions: expected"):
        load_config(path, ["evolution.generations=5"])
