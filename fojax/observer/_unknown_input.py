r"""The generalized functional observer with unknown-input estimation (thesis eq. 3.110)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_matrix
from ._base import AbstractFunctionalObserver, functional_gains, LinearObserverMatrices


class UnknownInputObserver(AbstractFunctionalObserver):
    r"""Generalized functional observer for $E\dot x = Ax + Bu + Dd$ (thesis eq. 3.110)

    $$\begin{aligned}
    \dot\zeta &= N\zeta + Jv + Fw + Hu + \Delta\hat d,\\
    \dot v &= S\zeta + Gv + Mw,\\
    \dot{\hat d} &= \Phi\zeta + \Lambda v - W w,\\
    \hat z &= P\zeta + Qw,
    \end{aligned}\qquad w = W_u u + W_y y = [-E^\perp B u;\; y],$$

    where $E^\perp$ annihilates $[E\;D]$. The state is $\xi = [\zeta; v; \hat d]$
    ($q_0 + q_1 + l$ entries); `output` returns $\hat z$ and
    `unknown_input_estimate` returns $\hat d$.

    With $\varepsilon = \zeta - TEx$ and $\tilde d = \hat d - d$, for a constant $d$
    and the design conditions a.–f. of Lemma 9 (see
    `fojax.design.design_unknown_input_observer`), $\sigma = [\varepsilon; v; \tilde d]$
    obeys $\dot\sigma = \mathbb A\sigma$ with

    $$\mathbb A = \begin{bmatrix} N & J & \Delta\\ S & G & 0\\ \Phi & \Lambda & 0\end{bmatrix},
      \qquad \hat z - z = P\varepsilon .$$

    **Deviations from the thesis** (documented in `fojax.design`): $W$ acts on the
    whole measured vector $w$ (the thesis writes $Wy$), and the $\hat d$ dynamics have
    an optional $\Lambda v$ term ($\Lambda = 0$ is the thesis's form).

    To simulate with a plant whose input is $[u; d]$ (the unknown input as an extra
    input channel of a `fojax.DescriptorSystem`), use `with_extra_inputs`.
    """

    N: Float[Array, "q0 q0"]
    J: Float[Array, "q0 q1"]
    F: Float[Array, "q0 nw"]
    H: Float[Array, "q0 m"]
    Delta: Float[Array, "q0 l"]
    S: Float[Array, "q1 q0"]
    G: Float[Array, "q1 q1"]
    M: Float[Array, "q1 nw"]
    Phi: Float[Array, "l q0"]
    Lambda: Float[Array, "l q1"]
    W: Float[Array, "l nw"]
    P: Float[Array, "q q0"]
    Q: Float[Array, "q nw"]
    Wu: Float[Array, "nw m"]
    Wy: Float[Array, "nw p"]

    def __init__(self, N, J, F, H, Delta, S, G, M, Phi, Lambda, W, P, Q, Wu, Wy):
        (self.N, self.J, self.F, self.H, self.S, self.G, self.M, self.P, self.Q,
         self.Wu, self.Wy) = functional_gains(N, J, F, H, S, G, M, P, Q, Wu, Wy)
        q0, q1, nw = self.N.shape[0], self.G.shape[0], self.Wu.shape[0]
        self.Delta = as_matrix("Delta", Delta, rows=q0)
        l = self.Delta.shape[1]
        self.Phi = as_matrix("Phi", Phi, rows=l, cols=q0)
        self.Lambda = as_matrix("Lambda", Lambda, rows=l, cols=q1)
        self.W = as_matrix("W", W, rows=l, cols=nw)

    # ------------------------------------------------------------------ sizes
    @property
    def num_unknown_inputs(self) -> int:
        return self.Delta.shape[-1]

    @property
    def state_size(self) -> int:
        return self.q0 + self.q1 + self.num_unknown_inputs

    @property
    def error_matrix(self) -> Float[Array, "s s"]:
        r"""$\mathbb A = [N\;J\;\Delta;\;S\;G\;0;\;\Phi\;\Lambda\;0]$."""
        l = self.num_unknown_inputs
        return jnp.block(
            [
                [self.N, self.J, self.Delta],
                [self.S, self.G, jnp.zeros((self.q1, l))],
                [self.Phi, self.Lambda, jnp.zeros((l, l))],
            ]
        )

    # --------------------------------------------------------------- dynamics
    def _split(self, xi):
        q0, q1 = self.q0, self.q1
        return xi[..., :q0], xi[..., q0 : q0 + q1], xi[..., q0 + q1 :]

    def vector_field(self, t, xi, u, y):
        zeta, v, dhat = self._split(xi)
        w = self.measured(u, y)
        dzeta = self.N @ zeta + self.J @ v + self.F @ w + self.H @ u + self.Delta @ dhat
        dv = self.S @ zeta + self.G @ v + self.M @ w
        ddhat = self.Phi @ zeta + self.Lambda @ v - self.W @ w
        return jnp.concatenate([dzeta, dv, ddhat])

    def output(self, t, xi, u, y):
        zeta = xi[: self.q0]
        return self.P @ zeta + self.Q @ self.measured(u, y)

    def unknown_input_estimate(self, xi) -> Float[Array, "*T l"]:
        r"""$\hat d$: the last ``l`` entries of the state (works on a trajectory ``(T, s)`` too)."""
        return self._split(xi)[2]

    def with_extra_inputs(self, extra: int) -> UnknownInputObserver:
        """The same observer for a plant input ``[u; d]`` with ``extra`` trailing channels
        (the unknown inputs) that the observer must *not* use: `H` and `Wu` get zero
        columns. For simulation against ``DescriptorSystem(E, A, [B D], C)``."""
        extra = int(extra)
        zq = jnp.zeros((self.q0, extra))
        zw = jnp.zeros((self.Wu.shape[0], extra))
        return UnknownInputObserver(
            self.N, self.J, self.F, jnp.concatenate([self.H, zq], axis=1), self.Delta,
            self.S, self.G, self.M, self.Phi, self.Lambda, self.W, self.P, self.Q,
            jnp.concatenate([self.Wu, zw], axis=1), self.Wy,
        )  # fmt: skip

    def linear_matrices(self) -> LinearObserverMatrices:
        l = self.num_unknown_inputs
        A = self.error_matrix
        Bw = jnp.concatenate([self.F, self.M, -self.W], axis=0)
        Bu = Bw @ self.Wu + jnp.concatenate(
            [self.H, jnp.zeros((self.q1 + l, self.H.shape[1]))], axis=0
        )
        By = Bw @ self.Wy
        Cm = jnp.concatenate([self.P, jnp.zeros((self.P.shape[0], self.q1 + l))], axis=1)
        return LinearObserverMatrices(A, Bu, By, Cm, self.Q @ self.Wu, self.Q @ self.Wy)
