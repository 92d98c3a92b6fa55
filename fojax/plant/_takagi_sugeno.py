r"""Takagi–Sugeno descriptor models with measured premise variables."""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_float_array, as_matrix
from .._errors import ShapeError
from ._base import AbstractPlant
from ._descriptor import DescriptorSystem


class AbstractMembership(eqx.Module):
    """Rule weights ``w(y, u)``: non-negative, summing to one, differentiable.

    Premise variables are functions of the *measured* output and the input, so the
    observer can evaluate the same weights as the plant (standard assumption).
    """

    @property
    @abc.abstractmethod
    def num_rules(self) -> int: ...

    @abc.abstractmethod
    def __call__(self, y, u) -> Float[Array, " k"]: ...


class SincPremise(eqx.Module):
    r"""Premise $\rho = \sin(y_i)/y_i$ (with $\rho(0) = 1$), smooth and differentiable."""

    index: int = eqx.field(static=True)

    def __call__(self, y, u):
        s = y[self.index]
        # jnp.sinc(x) = sin(pi x)/(pi x): smooth at 0 with correct derivatives.
        return jnp.sinc(s / jnp.pi)


class OutputPremise(eqx.Module):
    """Premise ``rho = y[index]``."""

    index: int = eqx.field(static=True)

    def __call__(self, y, u):
        return y[self.index]


class SectorMembership(AbstractMembership):
    r"""Two-rule sector membership (thesis eqs. 2.10–2.11 / 3.190–3.191).

    $$w_1 = \frac{\bar\rho - \rho}{\bar\rho - \underline\rho}, \qquad w_2 = 1 - w_1,$$

    with $\rho$ given by `premise(y, u)`; $\rho$ is clipped to
    $[\underline\rho, \bar\rho]$ so that the weights stay a convex combination.
    Rule 1 is the model at $\rho = \underline\rho$, rule 2 at $\rho = \bar\rho$.
    """

    premise: eqx.Module
    lower: Float[Array, ""]
    upper: Float[Array, ""]

    def __init__(self, premise, lower, upper):
        self.premise = premise
        self.lower = as_float_array("lower", lower)
        self.upper = as_float_array("upper", upper)

    @property
    def num_rules(self):
        return 2

    def __call__(self, y, u):
        rho = jnp.clip(self.premise(y, u), self.lower, self.upper)
        w1 = (self.upper - rho) / (self.upper - self.lower)
        return jnp.stack([w1, 1.0 - w1])


class TakagiSugenoSystem(AbstractPlant):
    r"""Takagi–Sugeno descriptor model (thesis eq. 3.150)

    $$E\dot x = \sum_{i=1}^k w_i(y, u)\,(A_i x + B_i u), \qquad y = Cx,$$

    with common $E$ and $C$ and rule matrices stacked along a leading axis.

    **Arguments:**

    - `E`: ``(n, n)``; `A`: ``(k, n, n)``; `B`: ``(k, n, m)``; `C`: ``(p, n)``.
    - `membership`: an `AbstractMembership` with ``k`` rules.
    """

    E: Float[Array, "n n"]
    A: Float[Array, "k n n"]
    B: Float[Array, "k n m"]
    C: Float[Array, "p n"]
    membership: AbstractMembership

    linear_in_state: ClassVar[bool] = False

    def __init__(self, E, A, B, C, membership):
        E = as_matrix("E", E)
        n = E.shape[0]
        if E.shape != (n, n):
            raise ShapeError("E", (n, n), tuple(E.shape))
        A = as_float_array("A", A)
        if A.ndim != 3 or A.shape[1:] != (n, n):
            raise ShapeError("A", ("k", n, n), tuple(A.shape), "Stack the rule matrices A_i.")
        k = A.shape[0]
        B = as_float_array("B", B)
        if B.ndim == 2:
            B = jnp.broadcast_to(B, (k,) + B.shape)
        if B.ndim != 3 or B.shape[0] != k or B.shape[1] != n:
            raise ShapeError("B", (k, n, "m"), tuple(B.shape), "Give one B_i per rule or a common B.")
        C = as_matrix("C", C, cols=n)
        if membership.num_rules != k:
            raise ShapeError("membership", f"{k} rules", f"{membership.num_rules} rules")
        self.E, self.A, self.B, self.C, self.membership = E, A, B, C, membership

    @property
    def num_rules(self) -> int:
        return self.A.shape[0]

    @property
    def m(self):
        return self.B.shape[-1]

    @property
    def p(self):
        return self.C.shape[-2]

    def weights(self, x, u):
        return self.membership(self.C @ x, u)

    def rhs(self, t, x, u):
        w = self.weights(x, u)
        return jnp.einsum("k,kij,j->i", w, self.A, x) + jnp.einsum("k,kij,j->i", w, self.B, u)

    def output(self, t, x, u):
        return self.C @ x

    def rule(self, i: int) -> DescriptorSystem:
        """The ``i``-th local linear model as a `DescriptorSystem`."""
        return DescriptorSystem(self.E, self.A[i], self.B[i], self.C)
