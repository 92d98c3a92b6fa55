"""fojax: functional observers for descriptor systems, in JAX.

Layers (data flows one way): ``plant`` (models) → ``analysis`` (structure) →
``design`` (LMIs, verified) → ``observer`` (modules) → ``simulation`` →
``studies`` (Monte Carlo) → ``tuning`` (optax) → ``results`` (files, plots, CLI).
``models`` holds the thesis's examples.
"""

import importlib.metadata

from . import plant as plant
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


__version__ = importlib.metadata.version("fojax")
