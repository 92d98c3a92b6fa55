r"""Nonlinear descriptor models ``E ẋ = f(x, u, θ)``, ``y = g(x, θ)``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
from jaxtyping import Array, Float, PyTree

from .._dtype import as_matrix
from .._errors import ShapeError
from ._base import AbstractPlant


class NonlinearDescriptorSystem(AbstractPlant):
    r"""A nonlinear descriptor model

    $$E\dot x = f(x, u, \theta), \qquad y = g(x, \theta),$$

    with constant $E$ and parameters $\theta$ (a pytree of arrays: the leaves that
    `jax.grad` and `jax.vmap` act on, e.g. uncertain physical parameters).

    **Arguments:**

    - `E`: ``(n, n)`` constant matrix.
    - `f`: callable ``f(x, u, theta) -> (n,)``; may also take a time argument if
      `time_varying=True`: ``f(t, x, u, theta)``.
    - `g`: callable ``g(x, theta) -> (p,)``.
    - `theta`: pytree of parameters.
    - `m`, `p`: input and output sizes (static).

    Pass the *same* function objects between calls (not fresh lambdas) so that
    compiled simulations are reused instead of retraced.
    """

    E: Float[Array, "n n"]
    theta: PyTree
    f: Callable = eqx.field(static=True)
    g: Callable = eqx.field(static=True)
    n_inputs: int = eqx.field(static=True)
    n_outputs: int = eqx.field(static=True)
    time_varying: bool = eqx.field(static=True)

    linear_in_state: ClassVar[bool] = False

    def __init__(
        self,
        E,
        f: Callable,
        g: Callable,
        theta: Any,
        *,
        m: int,
        p: int,
        time_varying: bool = False,
    ):
        E = as_matrix("E", E)
        n = E.shape[0]
        if E.shape != (n, n):
            raise ShapeError("E", (n, n), tuple(E.shape))
        self.E, self.f, self.g, self.theta = E, f, g, theta
        self.n_inputs, self.n_outputs, self.time_varying = int(m), int(p), bool(time_varying)

    @property
    def m(self):
        return self.n_inputs

    @property
    def p(self):
        return self.n_outputs

    def rhs(self, t, x, u):
        if self.time_varying:
            return self.f(t, x, u, self.theta)
        return self.f(x, u, self.theta)

    def output(self, t, x, u):
        return self.g(x, self.theta)
