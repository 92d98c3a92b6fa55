"""Plants: descriptor, uncertain, Takagi–Sugeno and nonlinear systems, their faults and noise,
and the input signals that drive them."""

from ._base import AbstractPlant as AbstractPlant
from ._descriptor import (
    augment_faults as augment_faults,
    check_functional as check_functional,
    DescriptorSystem as DescriptorSystem,
)
from ._faults import (
    FaultProfile as FaultProfile,
    FaultyPlant as FaultyPlant,
    NoisyPlant as NoisyPlant,
)
from ._nonlinear import NonlinearDescriptorSystem as NonlinearDescriptorSystem
from ._signals import (
    AbstractSignal as AbstractSignal,
    as_signal as as_signal,
    Constant as Constant,
    intermittent as intermittent,
    PiecewiseConstant as PiecewiseConstant,
    Ramp as Ramp,
    Sine as Sine,
    Stack as Stack,
    Step as Step,
    SumSignal as SumSignal,
    Zero as Zero,
)
from ._takagi_sugeno import (
    AbstractMembership as AbstractMembership,
    OutputPremise as OutputPremise,
    SectorMembership as SectorMembership,
    SincPremise as SincPremise,
    TakagiSugenoSystem as TakagiSugenoSystem,
)
from ._uncertain import UncertainDescriptorSystem as UncertainDescriptorSystem
