"""Gradient tuning of observer gains over Monte Carlo studies (optax), certified at every iterate:
`tune`, its coordinates and initial parameters, and the H2/H∞ robustness terms."""

from ._optimizer import shared_optimizer as shared_optimizer
from ._robustness import (
    AbstractRobustnessTerm as AbstractRobustnessTerm,
    H2Term as H2Term,
    HinfTerm as HinfTerm,
)
from ._tune import (
    Coordinates as Coordinates,
    initial_parameters as initial_parameters,
    make_parameterization as make_parameterization,
    observer_from_parameters as observer_from_parameters,
    tune as tune,
    TuneResult as TuneResult,
)
