"""Monte Carlo studies: uncertainty and fault families, the batched study runner, metrics,
and the helpers of a study spread over several processes.

Also the multi-process helpers of a computation spread over the devices of several
processes (`fojax.tuning.tune` and ``fojax study --distributed`` use them):
`spans_processes`, `writes_files` (only process 0 writes), `replicate`,
`check_same_on_every_process`, `broadcast_bytes` (process 0's bytes on every process) and
`distributed_errors` (a lost peer becomes `fojax.errors.DistributedError`).
"""

from ._exact import exact_refusal as exact_refusal
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
from ._loss import resolve_engine as resolve_engine, study_loss as study_loss
from ._runner import (
    error_metrics as error_metrics,
    run_study as run_study,
    SimConfig as SimConfig,
    Study as Study,
    StudyResult as StudyResult,
)
from ._sharding import (
    broadcast_bytes as broadcast_bytes,
    check_same_on_every_process as check_same_on_every_process,
    distributed_errors as distributed_errors,
    replicate as replicate,
    spans_processes as spans_processes,
    writes_files as writes_files,
)
