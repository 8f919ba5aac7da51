"""Run configuration: frozen, validated dataclasses loaded from YAML (`config`), and the settings
of each stage of the pipeline beside it.

`config.Config` gathers one section per stage; `config.load_config` reads a YAML file with
``--set KEY=VALUE`` overrides and validates every key and value, naming the key of any mistake.
"""

from evojax_motion.settings.config import (
    Config,
    RobotConfig,
    config_from_dict,
    config_to_dict,
    config_to_yaml,
    load_config,
    load_yaml,
)

__all__ = [
    "Config",
    "RobotConfig",
    "config_from_dict",
    "config_to_dict",
    "config_to_yaml",
    "load_config",
    "load_yaml",
]
