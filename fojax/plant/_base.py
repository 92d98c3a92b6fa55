"""The plant protocol shared by every model.

A plant is an ``equinox.Module`` describing

$$E\\dot x(t) = f(t, x(t), u(t)), \\qquad y(t) = g(t, x(t), u(t))$$

with a constant (possibly singular) matrix ``E``. Linear, Takagi–Sugeno, uncertain
and nonlinear models all implement `rhs` and `output`; the simulator reduces any of
them to an ODE in the slow coordinates plus an algebraic solve.
"""

import abc

import equinox as eqx
from jaxtyping import Array, Float


class AbstractPlant(eqx.Module):
    """Abstract base of every plant model (see module docstring)."""

    E: eqx.AbstractVar[Float[Array, "n n"]]

    @property
    def n(self) -> int:
        """Number of (descriptor) states."""
        return self.E.shape[0]

    #: Number of inputs and of measured outputs: a field (static, with or without a default)
    #: or a property of each plant. (No ``from __future__ import annotations`` in this module:
    #: equinox recognises an ``AbstractVar`` only from an evaluated annotation; as a string it
    #: would become a dataclass field of every subclass.)
    m: eqx.AbstractVar[int]
    p: eqx.AbstractVar[int]

    @abc.abstractmethod
    def rhs(self, t, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " n"]:
        """Right-hand side ``f(t, x, u)`` of ``E ẋ = f``."""

    @abc.abstractmethod
    def output(self, t, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " p"]:
        """Measured output ``y = g(t, x, u)``."""

    #: True when ``f`` is affine in ``x`` for every ``t`` (the algebraic part is then
    #: solved by one linear solve instead of a Newton iteration).
    linear_in_state: eqx.AbstractClassVar[bool]
