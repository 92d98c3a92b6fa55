"""Monte Carlo studies: uncertainty and fault families, the batched study runner, metrics."""

from ._families import (
    constant_delta as constant_delta,
    constant_faults as constant_faults,
    Family as Family,
    fault_scenarios as fault_scenarios,
    initial_conditions as initial_conditions,
    output_noise as output_noise,
    parameter_uncertainty as parameter_uncertainty,
    piecewise_constant_delta as piecewise_constant_delta,
    sinusoidal_delta as sinusoidal_delta,
)
from ._runner import (
    error_metrics as error_metrics,
    run_study as run_study,
    SimConfig as SimConfig,
    Study as Study,
    study_loss as study_loss,
    StudyResult as StudyResult,
)
from ._wrappers import (
    FaultProfile as FaultProfile,
    FaultyPlant as FaultyPlant,
    NoisyPlant as NoisyPlant,
)
