"""TOML model and study files, read into plants, observer specifications and studies
(format: `fojax.config.load_config` and ``docs/config.md``)."""

from ._load import (
    example_names as example_names,
    example_path as example_path,
    load_config as load_config,
)
from ._parse import parse_config as parse_config
from ._spec import (
    Config as Config,
    ObserverSpec as ObserverSpec,
    StudySpec as StudySpec,
    TuningSpec as TuningSpec,
)
