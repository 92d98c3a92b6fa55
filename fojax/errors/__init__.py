"""The typed errors fojax raises on purpose, all subclasses of `FojaxError`.
Bad input is an `InputError` (a `ValueError`); a failed design or solver a `RuntimeError`."""

from .._errors import (
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
