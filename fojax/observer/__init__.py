"""Observer modules (generalized functional, unknown-input, finite-time, Takagi–Sugeno): equinox
modules holding the thesis's matrices under the thesis's names."""

from ._base import (
    AbstractFunctionalObserver as AbstractFunctionalObserver,
    AbstractObserver as AbstractObserver,
    LinearObserverMatrices as LinearObserverMatrices,
)
from ._finite_time import FiniteTimeObserver as FiniteTimeObserver
from ._generalized import GeneralizedFunctionalObserver as GeneralizedFunctionalObserver
from ._takagi_sugeno import TakagiSugenoObserver as TakagiSugenoObserver
from ._unknown_input import UnknownInputObserver as UnknownInputObserver
