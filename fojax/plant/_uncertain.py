r"""Descriptor systems with structured (affine) parametric uncertainty."""

from __future__ import annotations

from operator import attrgetter
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_float_array
from .._errors import ShapeError
from ._base import AbstractPlant
from ._descriptor import DescriptorSystem
from ._signals import AbstractSignal, Constant


class UncertainDescriptorSystem(AbstractPlant):
    r"""Affine uncertainty around a nominal descriptor system:

    $$E\dot x = \Big(A + \sum_j \delta_j(t) A_j\Big)x + \Big(B + \sum_j \delta_j(t) B_j\Big)u,
      \qquad y = \Big(C + \sum_j \delta_j(t) C_j\Big)x.$$

    **Arguments:**

    - `nominal`: the nominal `DescriptorSystem`.
    - `dA`: ``(k, n, n)`` uncertainty directions for ``A`` (``None``: zeros).
    - `dB`: ``(k, n, m)``; `dC`: ``(k, p, n)`` (``None``: zeros).
    - `delta`: the uncertainty profile, an `AbstractSignal` of size ``k`` (constant
      per sample: `fojax.Constant`; time-varying: `Sine`, `PiecewiseConstant`, ...),
      or a ``(k,)`` array for a constant ``δ``.

    With ``δ`` constant the system is time-invariant (`nominal_at` returns the
    corresponding `DescriptorSystem`, which the exact LTI stepper uses).
    """

    nominal: DescriptorSystem
    dA: Float[Array, "k n n"]
    dB: Float[Array, "k n m"]
    dC: Float[Array, "k p n"]
    delta: AbstractSignal

    linear_in_state: ClassVar[bool] = True

    def __init__(self, nominal: DescriptorSystem, dA=None, dB=None, dC=None, delta=None):
        n, m, p = nominal.n, nominal.m, nominal.p
        k = None
        for name, d in (("dA", dA), ("dB", dB), ("dC", dC)):
            if d is not None:
                k = jnp.shape(d)[0] if jnp.ndim(d) == 3 else 1
                break
        if k is None:
            raise ShapeError("dA/dB/dC", "at least one uncertainty direction", "none")

        def prep(name, d, shape):
            if d is None:
                return jnp.zeros((k,) + shape)
            d = as_float_array(name, d)
            if d.ndim == 2:
                d = d[None]
            if d.shape != (k,) + shape:
                raise ShapeError(name, (k,) + shape, tuple(d.shape))
            return d

        self.nominal = nominal
        self.dA = prep("dA", dA, (n, n))
        self.dB = prep("dB", dB, (n, m))
        self.dC = prep("dC", dC, (p, n))
        if delta is None:
            delta = jnp.zeros((k,))
        if not isinstance(delta, AbstractSignal):
            delta = Constant(delta)
        if delta.size != k:
            raise ShapeError("delta", f"a signal of size {k}", f"size {delta.size}")
        self.delta = delta

    # the nominal system's matrix E and sizes
    E = property(attrgetter("nominal.E"))
    m = property(attrgetter("nominal.m"))
    p = property(attrgetter("nominal.p"))

    def matrices(self, t):
        d = self.delta(t)
        A = self.nominal.A + jnp.einsum("k,kij->ij", d, self.dA)
        B = self.nominal.B + jnp.einsum("k,kij->ij", d, self.dB)
        C = self.nominal.C + jnp.einsum("k,kij->ij", d, self.dC)
        return A, B, C

    def rhs(self, t, x, u):
        A, B, _ = self.matrices(t)
        return A @ x + B @ u

    def output(self, t, x, u):
        _, _, C = self.matrices(t)
        return C @ x + self.nominal.D @ u

    def nominal_at(self, t=0.0) -> DescriptorSystem:
        """The frozen-time `DescriptorSystem` at time ``t`` (exact when ``δ`` is constant)."""
        A, B, C = self.matrices(t)
        return DescriptorSystem(self.nominal.E, A, B, C, self.nominal.D)
