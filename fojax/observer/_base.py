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

from .._dtype import as_matrix
from .._errors import ShapeError


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


class AbstractFunctionalObserver(AbstractObserver):
    r"""Abstract base of the functional observers of the thesis (generalized, unknown-input,
    Takagi–Sugeno): a state $[\zeta; v; \dots]$ with $\zeta$ of size ``q0`` (`N`) and $v$ of size
    ``q1`` (`G`), the measured vector $w = W_u u + W_y y$ and the estimate $\hat z = P\zeta + Qw$.
    The matrices may carry a leading rule axis (Takagi–Sugeno); the sizes are read from the
    trailing axes."""

    N: eqx.AbstractVar[Array]
    G: eqx.AbstractVar[Array]
    P: eqx.AbstractVar[Array]
    Wu: eqx.AbstractVar[Array]
    Wy: eqx.AbstractVar[Array]

    @property
    def q0(self) -> int:
        return self.N.shape[-1]

    @property
    def q1(self) -> int:
        return self.G.shape[-1]

    @property
    def state_size(self) -> int:
        return self.q0 + self.q1

    @property
    def output_size(self) -> int:
        return self.P.shape[-2]

    def measured(self, u, y):
        """The measured vector $w = W_u u + W_y y$ the observer is driven by."""
        return self.Wu @ u + self.Wy @ y


def functional_gains(N, J, F, H, S, G, M, P, Q, Wu, Wy, matrix=None) -> tuple[Array, ...]:
    r"""`(N, J, F, H, S, G, M, P, Q, Wu, Wy)` as float64 arrays whose trailing axes fit one
    another: `N` ``(q0, q0)``, `J` ``(q0, q1)``, `F` ``(q0, nw)``, `H` ``(q0, m)``, `S`
    ``(q1, q0)``, `G` ``(q1, q1)``, `M` ``(q1, nw)``, `P` ``(q, q0)``, `Q` ``(q, nw)``, `Wu`
    ``(nw, m)`` and `Wy` ``(nw, p)`` (a `ShapeError` naming the first matrix that does not fit).

    `matrix(name, x, rows, cols)` reads one gain (``None``: `as_matrix`, a single 2-d matrix; the
    Takagi–Sugeno observer passes one that stacks a leading rule axis)."""
    if matrix is None:
        def matrix(name, x, rows, cols):
            return as_matrix(name, x, rows=rows, cols=cols)

    N = matrix("N", N, None, None)
    q0 = N.shape[-2]
    if N.shape[-1] != q0:
        raise ShapeError("N", tuple(N.shape[:-2]) + (q0, q0), tuple(N.shape))
    Wy = as_matrix("Wy", Wy)
    Wu = as_matrix("Wu", Wu, rows=Wy.shape[0])
    nw, m = Wu.shape
    G = matrix("G", G, None, None)
    q1 = G.shape[-2]
    J = matrix("J", J, q0, q1)
    F = matrix("F", F, q0, nw)
    H = matrix("H", H, q0, m)
    S = matrix("S", S, q1, q0)
    G = matrix("G", G, q1, q1)
    M = matrix("M", M, q1, nw)
    P = matrix("P", P, None, q0)
    Q = matrix("Q", Q, P.shape[-2], nw)
    return N, J, F, H, S, G, M, P, Q, Wu, Wy


def fold_feedthrough(observer: AbstractObserver, D) -> AbstractObserver:
    r"""The observer for a plant with feedthrough $y = Cx + Du$.

    An observer designed for $y = Cx$ must be driven by $y - Du$. For the functional
    observers the measured vector is $w = W_u u + W_y y$, so substituting $y - Du$ gives

    $$w = (W_u - W_y D)\,u + W_y\,y,$$

    i.e. the same observer with $W_u \leftarrow W_u - W_y D$ (equivalently, in the
    thesis's form, $H \leftarrow H - F W_y D$ and the estimate's $Q W_u \leftarrow
    Q(W_u - W_y D)$). The error dynamics are unchanged; simulation and export need no
    special case. A finite-time observer folds both of its observers.

    **Arguments:**

    - `observer`: a functional observer (generalized, unknown-input, Takagi–Sugeno) or a
      `fojax.FiniteTimeObserver`.
    - `D`: the plant's ``(p, m)`` feedthrough.

    **Returns:** the observer that takes the measured ``y = Cx + Du``.
    """
    D = jnp.asarray(D, dtype=float)
    if isinstance(observer, AbstractFunctionalObserver):
        return eqx.tree_at(lambda o: o.Wu, observer, observer.Wu - observer.Wy @ D)
    if hasattr(observer, "obs1") and hasattr(observer, "obs2"):
        return eqx.tree_at(lambda o: (o.obs1, o.obs2), observer,
                           (fold_feedthrough(observer.obs1, D), fold_feedthrough(observer.obs2, D)))
    raise TypeError(f"fold_feedthrough: no rule for {type(observer).__name__}")
