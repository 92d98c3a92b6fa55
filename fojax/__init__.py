"""fojax: functional observers for descriptor systems, in JAX.

Layers (data flows one way): ``plant`` (models) → ``analysis`` (structure) →
``design`` (LMIs, verified) → ``observer`` (modules) → ``simulation`` →
``studies`` (Monte Carlo) → ``tuning`` (optax) → ``results`` (files, plots, CLI).
``models`` holds the thesis's examples.
"""

from .cli import _startup as _startup  # first: the `fojax` program ends on Ctrl-C while importing


# isort: split
import importlib.metadata as _metadata

from . import (
    analysis as analysis,
    config as config,
    control as control,
    design as design,
    interop as interop,
    models as models,
    observer as observer,
    plant as plant,
    results as results,
    simulation as simulation,
    studies as studies,
    tuning as tuning,
)
from ._errors import (
    AlgebraicLoopError as AlgebraicLoopError,
    ConfigError as ConfigError,
    DataRangeError as DataRangeError,
    DesignVerificationError as DesignVerificationError,
    DetectabilityError as DetectabilityError,
    DistributedError as DistributedError,
    ExistenceConditionError as ExistenceConditionError,
    Float64RequiredError as Float64RequiredError,
    FojaxError as FojaxError,
    FunctionalObservabilityError as FunctionalObservabilityError,
    ImpulseObservabilityError as ImpulseObservabilityError,
    ImpulsiveSystemError as ImpulsiveSystemError,
    InconsistentInitialConditionError as InconsistentInitialConditionError,
    InputError as InputError,
    IrregularSystemError as IrregularSystemError,
    LMIInfeasibleError as LMIInfeasibleError,
    NonFiniteError as NonFiniteError,
    NumericallyUndecidableError as NumericallyUndecidableError,
    RankConditionError as RankConditionError,
    RegionError as RegionError,
    ShapeError as ShapeError,
    SolverStoppedShortError as SolverStoppedShortError,
    StabilizabilityError as StabilizabilityError,
    UnsafePathError as UnsafePathError,
)
from .analysis import (
    admissibility_certificate as admissibility_certificate,
    AdmissibilityCertificate as AdmissibilityCertificate,
    AXIS_TOL as AXIS_TOL,
    balance_system as balance_system,
    Balancing as Balancing,
    e_perp as e_perp,
    finite_poles as finite_poles,
    functional_observability_gap as functional_observability_gap,
    impulse_free_margin as impulse_free_margin,
    is_admissible as is_admissible,
    is_c_controllable as is_c_controllable,
    is_c_observable as is_c_observable,
    is_detectable as is_detectable,
    is_functionally_observable as is_functionally_observable,
    is_i_controllable as is_i_controllable,
    is_i_observable as is_i_observable,
    is_impulse_controllable as is_impulse_controllable,
    is_impulse_free as is_impulse_free,
    is_impulse_observable as is_impulse_observable,
    is_r_controllable as is_r_controllable,
    is_r_observable as is_r_observable,
    is_regular as is_regular,
    is_s_controllable as is_s_controllable,
    is_s_observable as is_s_observable,
    is_stabilizable as is_stabilizable,
    is_stable as is_stable,
    kronecker_structure as kronecker_structure,
    KroneckerStructure as KroneckerStructure,
    mode_counts as mode_counts,
    ModeCounts as ModeCounts,
    nilpotency_index as nilpotency_index,
    Properness as Properness,
    properness as properness,
    regular_at as regular_at,
    regularity_margin_at as regularity_margin_at,
    Scaling as Scaling,
    slow_matrix_index1 as slow_matrix_index1,
    stability_margin_index1 as stability_margin_index1,
    structure_report as structure_report,
    StructureReport as StructureReport,
    system_zeros as system_zeros,
    SystemZeros as SystemZeros,
    weierstrass_form as weierstrass_form,
    WeierstrassForm as WeierstrassForm,
)
from .config import load_config as load_config
from .control import (
    closed_loop as closed_loop,
    design_actuator_ftc as design_actuator_ftc,
    design_sensor_ftc as design_sensor_ftc,
    design_simultaneous_ftc as design_simultaneous_ftc,
    design_state_feedback as design_state_feedback,
    finite_time_loop as finite_time_loop,
)
from .design import (
    AbstractDesign as AbstractDesign,
    AbstractRegion as AbstractRegion,
    design_fault_estimator as design_fault_estimator,
    design_finite_time_observer as design_finite_time_observer,
    design_functional_observer as design_functional_observer,
    design_ts_observer as design_ts_observer,
    design_unknown_input_observer as design_unknown_input_observer,
    Disk as Disk,
    FiniteTimeObserverDesign as FiniteTimeObserverDesign,
    FunctionalObserverDesign as FunctionalObserverDesign,
    HalfPlane as HalfPlane,
    Intersection as Intersection,
    observer_matrices as observer_matrices,
    observer_structure as observer_structure,
    Sector as Sector,
    VerificationReport as VerificationReport,
)
from .interop import discretize as discretize, estimate as estimate
from .observer import (
    AbstractObserver as AbstractObserver,
    FiniteTimeObserver as FiniteTimeObserver,
    GeneralizedFunctionalObserver as GeneralizedFunctionalObserver,
    TakagiSugenoObserver as TakagiSugenoObserver,
    UnknownInputObserver as UnknownInputObserver,
)
from .plant import (
    AbstractMembership as AbstractMembership,
    AbstractPlant as AbstractPlant,
    AbstractSignal as AbstractSignal,
    augment_faults as augment_faults,
    Constant as Constant,
    DescriptorSystem as DescriptorSystem,
    intermittent as intermittent,
    NonlinearDescriptorSystem as NonlinearDescriptorSystem,
    OutputPremise as OutputPremise,
    PiecewiseConstant as PiecewiseConstant,
    Ramp as Ramp,
    SectorMembership as SectorMembership,
    SincPremise as SincPremise,
    Sine as Sine,
    Stack as Stack,
    Step as Step,
    SumSignal as SumSignal,
    TakagiSugenoSystem as TakagiSugenoSystem,
    UncertainDescriptorSystem as UncertainDescriptorSystem,
    Zero as Zero,
)
from .results import load_design as load_design, save_design as save_design
from .simulation import (
    AbstractStepper as AbstractStepper,
    Auto as Auto,
    Bands as Bands,
    consistent_initial_condition as consistent_initial_condition,
    Diffrax as Diffrax,
    Exact as Exact,
    Exponential as Exponential,
    Index1Reduction as Index1Reduction,
    Metrics as Metrics,
    reduce_index1 as reduce_index1,
    simulate as simulate,
    simulate_batch_exponential as simulate_batch_exponential,
    Solution as Solution,
    Trajectory as Trajectory,
)
from .studies import run_study as run_study, Study as Study, StudyResult as StudyResult
from .tuning import tune as tune


__version__ = _metadata.version("fojax")
