"""The observer protocol.

An observer is an ``equinox.Module`` with an internal state ``ξ`` driven by the
plant's input ``u`` and measured output ``y``:

$$\\dot\\xi = \\phi(t, \\xi, u, y), \\qquad \\hat z = \\psi(t, \\xi, u, y).$$

Linear time-invariant observers also expose `linear_matrices`, so that plant and
observer can be assembled into one descriptor system and stepped exactly.
"""

from __future__ import annotations

import abc
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float


class LinearObserverMatrices(NamedTuple):
    r"""``ξ̇ = A ξ + Bu u + By y``, ``ẑ = C ξ + Du u + Dy y``."""

    A: Float[Array, "s s"]
    Bu: Float[Array, "s m"]
    By: Float[Array, "s p"]
    C: Float[Array, "q s"]
    Du: Float[Array, "q m"]
    Dy: Float[Array, "q p"]


class AbstractObserver(eqx.Module):
    """Abstract base of every observer (see module docstring)."""

    @property
    @abc.abstractmethod
    def state_size(self) -> int:
        """Size of the observer's internal state ``ξ``."""

    @property
    @abc.abstractmethod
    def output_size(self) -> int:
        """Size of the estimate ``ẑ``."""

    @abc.abstractmethod
    def vector_field(self, t, xi, u, y) -> Float[Array, " s"]:
        """``ξ̇``."""

    @abc.abstractmethod
    def output(self, t, xi, u, y) -> Float[Array, " q"]:
        """``ẑ``."""

    def initial_state(self) -> Float[Array, " s"]:
        return jnp.zeros((self.state_size,))

    def linear_matrices(self) -> LinearObserverMatrices | None:
        """The LTI realisation, or ``None`` for time-varying/nonlinear observers."""
        return None
