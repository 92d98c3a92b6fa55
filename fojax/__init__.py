"""fojax: functional observers for descriptor systems, in JAX.

Layers (data flows one way): ``plant`` (models) → ``analysis`` (structure) →
``design`` (LMIs, verified) → ``observer`` (modules) → ``simulation`` →
``studies`` (Monte Carlo) → ``tuning`` (optax) → ``results`` (files, plots, CLI).
``models`` holds the thesis's examples.
"""

import importlib.metadata

from . import models as models, plant as plant, simulation as simulation
from ._errors import (
    ConfigError as ConfigError,
    DesignVerificationError as DesignVerificationError,
    DetectabilityError as DetectabilityError,
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
    RankConditionError as RankConditionError,
    RegionError as RegionError,
    ShapeError as ShapeError,
)
from .analysis import (
    admissibility_certificate as admissibility_certificate,
    AdmissibilityCertificate as AdmissibilityCertificate,
    AXIS_TOL as AXIS_TOL,
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
    nilpotency_index as nilpotency_index,
    regular_at as regular_at,
    regularity_margin_at as regularity_margin_at,
    slow_matrix_index1 as slow_matrix_index1,
    stability_margin_index1 as stability_margin_index1,
    structure_report as structure_report,
    StructureReport as StructureReport,
    weierstrass_form as weierstrass_form,
    WeierstrassForm as WeierstrassForm,
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
from .simulation import (
    consistent_initial_condition as consistent_initial_condition,
    Index1Reduction as Index1Reduction,
    reduce_index1 as reduce_index1,
    simulate as simulate,
    Solution as Solution,
)


__version__ = importlib.metadata.version("fojax")
