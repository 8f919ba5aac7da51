"""Config loading: defaults, overrides, and one clear error per kind of mistake."""

import pytest

from evojax_motion.config import (
    Config,
    config_from_dict,
    config_to_yaml,
    load_config,
)
from evojax_motion.errors import UserError


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
