"""The plant protocol shared by every model.

A plant is an ``equinox.Module`` describing

$$E\\dot x(t) = f(t, x(t), u(t)), \\qquad y(t) = g(t, x(t), u(t))$$

with a constant (possibly singular) matrix ``E``. Linear, Takagi–Sugeno, uncertain
and nonlinear models all implement `rhs` and `output`; the simulator reduces any of
them to an ODE in the slow coordinates plus an algebraic solve.
"""

from __future__ import annotations

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

    # m and p are abstract properties, not eqx.AbstractVar: a subclass may define them as
    # properties or as (static) fields, and an AbstractVar would turn them into dataclass
    # fields of a subclass that defines them as properties.
    @property
    @abc.abstractmethod
    def m(self) -> int:
        """Number of inputs."""

    @property
    @abc.abstractmethod
    def p(self) -> int:
        """Number of measured outputs."""

    @abc.abstractmethod
    def rhs(self, t, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " n"]:
        """Right-hand side ``f(t, x, u)`` of ``E ẋ = f``."""

    @abc.abstractmethod
    def output(self, t, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " p"]:
        """Measured output ``y = g(t, x, u)``."""

    #: True when ``f`` is affine in ``x`` for every ``t`` (the algebraic part is then
    #: solved by one linear solve instead of a Newton iteration).
    linear_in_state: eqx.AbstractClassVar[bool]
