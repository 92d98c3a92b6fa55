"""Observer modules: the thesis's matrices under the thesis's names."""

from ._base import (
    AbstractObserver as AbstractObserver,
    LinearObserverMatrices as LinearObserverMatrices,
)
from ._finite_time import FiniteTimeObserver as FiniteTimeObserver
from ._generalized import GeneralizedFunctionalObserver as GeneralizedFunctionalObserver
