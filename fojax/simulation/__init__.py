"""Simulation: `simulate`, the stepper objects (`Auto`, `Exact`, `Exponential`, `Diffrax`), what
to save (`Trajectory`, `Metrics`, `Bands`), index-1 reduction and consistent initial conditions."""

from ._discrete import Discrete as Discrete
from ._reduction import (
    consistent_initial_condition as consistent_initial_condition,
    Index1Reduction as Index1Reduction,
    reduce_index1 as reduce_index1,
)
from ._save import Bands as Bands, Metrics as Metrics, Trajectory as Trajectory
from ._simulate import simulate as simulate
from ._solution import Solution as Solution
from ._steppers import (
    AbstractStepper as AbstractStepper,
    Auto as Auto,
    Diffrax as Diffrax,
    Exact as Exact,
    Exponential as Exponential,
    resolve_stepper as resolve_stepper,
)
