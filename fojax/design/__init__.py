"""Design layer: parameterization (pure JAX), LMI regions, LMI design (cvxpy, host), verification,
and `AbstractDesign`, the base of every design result (verify, summary, save/load).

`SOLVERS` names the LMI solvers a design accepts (``solver=``), `DEFAULT_SOLVER` the default.
"""

from ._base import AbstractDesign as AbstractDesign
from ._conditions import (
    check_detectability as check_detectability,
    check_functional_observability as check_functional_observability,
    check_structure as check_structure,
    default_R as default_R,
    fixed_modes as fixed_modes,
)
from ._fault import (
    design_fault_estimator as design_fault_estimator,
    FaultEstimatorDesign as FaultEstimatorDesign,
)
from ._finite_time import (
    design_finite_time_observer as design_finite_time_observer,
    FiniteTimeObserverDesign as FiniteTimeObserverDesign,
    reconstruction_matrices as reconstruction_matrices,
)
from ._functional import (
    design_functional_observer as design_functional_observer,
    FunctionalObserverDesign as FunctionalObserverDesign,
)
from ._gain_parameterization import (
    contraction as contraction,
    disk_gain as disk_gain,
    lemma10_gain as lemma10_gain,
)
from ._hinf import (
    check_channels as check_channels,
    error_norms as error_norms,
    error_system as error_system,
    H2Certificate as H2Certificate,
    hinf_uncertainty_channel as hinf_uncertainty_channel,
    HinfCertificate as HinfCertificate,
)
from ._lmi import DEFAULT_SOLVER as DEFAULT_SOLVER, SOLVERS as SOLVERS
from ._parameterization import (
    design_residuals as design_residuals,
    error_dynamics as error_dynamics,
    FunctionalObserverStructure as FunctionalObserverStructure,
    observer_matrices as observer_matrices,
    observer_structure as observer_structure,
    ObserverMatrices as ObserverMatrices,
    pieces as pieces,
    project_parameters as project_parameters,
    zero_params as zero_params,
)
from ._regions import (
    AbstractRegion as AbstractRegion,
    as_region as as_region,
    DiscreteDisk as DiscreteDisk,
    Disk as Disk,
    HalfPlane as HalfPlane,
    Intersection as Intersection,
    region_from_dict as region_from_dict,
    Sector as Sector,
)
from ._stein import (
    host_stein_certificate as host_stein_certificate,
    stein_certificate as stein_certificate,
)
from ._takagi_sugeno import (
    check_impulse_observability as check_impulse_observability,
    design_ts_observer as design_ts_observer,
    TakagiSugenoObserverDesign as TakagiSugenoObserverDesign,
)
from ._tunable import (
    AbstractParameterization as AbstractParameterization,
    certify as certify,
    live_parameters as live_parameters,
    LiveParameters as LiveParameters,
    unflatten as unflatten,
)
from ._tunable_finals import (
    CommonCertificate as CommonCertificate,
    FixedCertificateDisk as FixedCertificateDisk,
    SteinDisk as SteinDisk,
)
from ._unknown_input import (
    check_unknown_input_modes as check_unknown_input_modes,
    design_unknown_input_observer as design_unknown_input_observer,
)
from ._unknown_input_matrices import (
    unknown_input_error_dynamics as unknown_input_error_dynamics,
    unknown_input_observer_matrices as unknown_input_observer_matrices,
    unknown_input_residuals as unknown_input_residuals,
    UnknownInputObserverDesign as UnknownInputObserverDesign,
    UnknownInputObserverMatrices as UnknownInputObserverMatrices,
)
from ._verify import VerificationReport as VerificationReport, verify as verify
