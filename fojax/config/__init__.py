"""TOML model and study files (format: `fojax.config.load_config` and ``docs/config.md``)."""

from ._load import (
    Config as Config,
    example_names as example_names,
    example_path as example_path,
    load_config as load_config,
    ObserverSpec as ObserverSpec,
    parse_config as parse_config,
    StudySpec as StudySpec,
    TuningSpec as TuningSpec,
)
