r"""The Takagi–Sugeno generalized functional observer (thesis eq. 3.152)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_float_array, as_matrix
from .._errors import ShapeError
from ..plant import AbstractMembership
from ._base import AbstractFunctionalObserver, functional_gains
from ._generalized import GeneralizedFunctionalObserver


_KINDS = ("generalized", "PI", "proportional")


def _stack(name, x, k, rows, cols):
    x = as_float_array(name, x)
    if x.ndim == 2:
        x = jnp.broadcast_to(x, (k,) + x.shape)
    if x.ndim != 3 or x.shape[0] != k:
        raise ShapeError(name, (k, rows, cols), tuple(x.shape), f"Stack one {name}_i per rule ({k} rules).")
    if (rows is not None and x.shape[1] != rows) or (cols is not None and x.shape[2] != cols):
        raise ShapeError(name, (k, rows, cols), tuple(x.shape))
    return x


class TakagiSugenoObserver(AbstractFunctionalObserver):
    r"""Rule-weighted generalized functional observer (thesis eq. 3.152)

    $$\begin{aligned}
    \dot\zeta &= \sum_{i=1}^k w_i(y, u)\,\big(N_i\zeta + J_i v + F_i w + H_i u\big),\\
    \dot v &= \sum_{i=1}^k w_i(y, u)\,\big(S_i\zeta + G_i v + M_i w\big),\\
    \hat z &= \sum_{i=1}^k w_i(y, u)\,\big(P_i\zeta + Q_i w\big),
    \end{aligned}\qquad w = W_u u + W_y y,$$

    with the *same* weights $w_i(y, u)$ as the plant (`membership`, evaluated on the
    measured output, so the observer can compute them) and one common $T$: the error
    $\varepsilon = \zeta - TEx$ obeys
    $\dot{[\varepsilon; v]} = \sum_i w_i\,\mathbb A_i\,[\varepsilon; v]$,
    $\mathbb A_i = [N_i\;J_i;\;S_i\;G_i]$, and $\hat z - z = \sum_i w_i P_i\varepsilon$
    whenever conditions a.–d. of Lemma 11 hold for every rule. For the thesis's
    design $w = y$ ($W_u = 0$, $W_y = I$; ``psi="output"`` in `fojax.design`).

    The proportional observer of §3.3.4 (eq. 3.185) is the case $q_1 = 0$.

    **Attributes:** `N, J, F, H, S, G, M, P, Q` stacked along a leading rule axis of
    size ``k``; `Wu` ``(nw, m)``, `Wy` ``(nw, p)``; `T` ``(q0, n)`` (the common
    transformation, for error analysis: $\varepsilon = \zeta - TEx$); `membership`;
    `kind` (static).

    The observer is time-varying (weights depend on $y$): `linear_matrices` is
    ``None``, and `rule(i)` returns the frozen rule-$i$ `GeneralizedFunctionalObserver`.
    """

    N: Float[Array, "k q0 q0"]
    J: Float[Array, "k q0 q1"]
    F: Float[Array, "k q0 nw"]
    H: Float[Array, "k q0 m"]
    S: Float[Array, "k q1 q0"]
    G: Float[Array, "k q1 q1"]
    M: Float[Array, "k q1 nw"]
    P: Float[Array, "k q q0"]
    Q: Float[Array, "k q nw"]
    Wu: Float[Array, "nw m"]
    Wy: Float[Array, "nw p"]
    T: Float[Array, "q0 n"]
    membership: AbstractMembership
    kind: str = eqx.field(static=True)

    def __init__(self, N, J, F, H, S, G, M, P, Q, Wu, Wy, T, membership, kind: str = "generalized"):
        if not isinstance(membership, AbstractMembership):
            raise TypeError(
                f"membership must be a fojax.plant.AbstractMembership (the plant's), got {type(membership).__name__}."
            )
        k = membership.num_rules
        (self.N, self.J, self.F, self.H, self.S, self.G, self.M, self.P, self.Q,
         self.Wu, self.Wy) = functional_gains(
            N, J, F, H, S, G, M, P, Q, Wu, Wy,
            lambda name, x, rows, cols: _stack(name, x, k, rows, cols))
        self.T = as_matrix("T", T, rows=self.N.shape[1])
        self.membership = membership
        if kind not in _KINDS:
            raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
        self.kind = kind

    # ------------------------------------------------------------------ sizes
    @property
    def num_rules(self) -> int:
        return self.N.shape[0]

    @property
    def error_matrices(self) -> Float[Array, "k s s"]:
        r"""$\mathbb A_i = [N_i\;J_i;\;S_i\;G_i]$ for every rule."""
        top = jnp.concatenate([self.N, self.J], axis=-1)
        bot = jnp.concatenate([self.S, self.G], axis=-1)
        return jnp.concatenate([top, bot], axis=-2)

    def rule(self, i: int) -> GeneralizedFunctionalObserver:
        """The rule-``i`` observer with frozen weights (``w_i = 1``)."""
        return GeneralizedFunctionalObserver(
            self.N[i], self.J[i], self.F[i], self.H[i], self.S[i], self.G[i], self.M[i],
            self.P[i], self.Q[i], self.Wu, self.Wy, kind=self.kind,
        )  # fmt: skip

    # --------------------------------------------------------------- dynamics
    def weights(self, u, y) -> Float[Array, " k"]:
        """Rule weights ``w(y, u)`` (the plant's membership functions)."""
        return self.membership(y, u)

    def vector_field(self, t, xi, u, y):
        zeta, v = xi[: self.q0], xi[self.q0 :]
        w = self.measured(u, y)
        h = self.weights(u, y)
        dzeta = (
            jnp.einsum("k,kij,j->i", h, self.N, zeta)
            + jnp.einsum("k,kij,j->i", h, self.J, v)
            + jnp.einsum("k,kij,j->i", h, self.F, w)
            + jnp.einsum("k,kij,j->i", h, self.H, u)
        )
        dv = (
            jnp.einsum("k,kij,j->i", h, self.S, zeta)
            + jnp.einsum("k,kij,j->i", h, self.G, v)
            + jnp.einsum("k,kij,j->i", h, self.M, w)
        )
        return jnp.concatenate([dzeta, dv])

    def output(self, t, xi, u, y):
        zeta = xi[: self.q0]
        w = self.measured(u, y)
        h = self.weights(u, y)
        return jnp.einsum("k,kij,j->i", h, self.P, zeta) + jnp.einsum("k,kij,j->i", h, self.Q, w)
