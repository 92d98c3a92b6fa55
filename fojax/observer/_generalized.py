r"""The generalized functional observer (thesis eq. 3.5) and its special cases."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..plant._descriptor import check_dt
from ._base import AbstractFunctionalObserver, functional_gains, LinearObserverMatrices


class GeneralizedFunctionalObserver(AbstractFunctionalObserver):
    r"""Generalized functional observer (thesis eq. 3.5)

    $$\begin{aligned}
    \dot\zeta &= N\zeta + Jv + F w + Hu,\\
    \dot v &= S\zeta + Gv + M w,\\
    \hat z &= P\zeta + Q w,
    \end{aligned}\qquad w = W_u u + W_y y,$$

    where for a descriptor plant $w = [-E^\perp B u;\; y]$ ($W_u = [-E^\perp B; 0]$,
    $W_y = [0; I]$) and for an output-injection design $w = y$.
    The state is $\xi = [\zeta; v]$ with $\zeta \in \mathbb R^{q_0}$, $v \in \mathbb R^{q_1}$.

    Special cases (Remark 2): the **proportional** observer has $q_1 = 0$
    ($J = S = M = G = 0$); the **proportional-integral** observer has $S = 0$.
    `kind` (static) records which one a design produced.

    The estimation error obeys $\hat z - z = P\varepsilon$ with
    $\dot{[\varepsilon; v]} = \mathbb A [\varepsilon; v]$, $\mathbb A = [N\;J;\;S\;G]$,
    whenever the design conditions a.–d. hold (see `fojax.design`).

    **Discrete time** (`dt` $= h$ set, static): the same matrices define the recursion
    $\zeta[k+1] = N\zeta[k] + Jv[k] + Fw[k] + Hu[k]$, $v[k+1] = S\zeta[k] + Gv[k] + Mw[k]$,
    $\hat z[k] = P\zeta[k] + Qw[k]$ on the grid $t_k = t_0 + kh$ (`vector_field` then
    returns the next state $\xi[k+1]$), with the error $[\varepsilon; v][k+1] =
    \mathbb A[\varepsilon; v][k]$. Designed by `fojax.design_functional_observer` on a
    discrete-time plant, or obtained from a continuous observer by `fojax.discretize`.
    """

    N: Float[Array, "q0 q0"]
    J: Float[Array, "q0 q1"]
    F: Float[Array, "q0 nw"]
    H: Float[Array, "q0 m"]
    S: Float[Array, "q1 q0"]
    G: Float[Array, "q1 q1"]
    M: Float[Array, "q1 nw"]
    P: Float[Array, "q q0"]
    Q: Float[Array, "q nw"]
    Wu: Float[Array, "nw m"]
    Wy: Float[Array, "nw p"]
    kind: str = eqx.field(static=True)
    dt: float | None = eqx.field(static=True)

    def __init__(self, N, J, F, H, S, G, M, P, Q, Wu, Wy, kind: str = "generalized", *, dt=None):
        (self.N, self.J, self.F, self.H, self.S, self.G, self.M, self.P, self.Q,
         self.Wu, self.Wy) = functional_gains(N, J, F, H, S, G, M, P, Q, Wu, Wy)
        if kind not in ("generalized", "PI", "proportional"):
            raise ValueError(f"kind must be 'generalized', 'PI' or 'proportional', got {kind!r}")
        self.kind = kind
        self.dt = check_dt(dt)

    @property
    def error_matrix(self) -> Float[Array, "s s"]:
        r"""$\mathbb A = [N\;J;\;S\;G]$."""
        return jnp.block([[self.N, self.J], [self.S, self.G]])

    # --------------------------------------------------------------- dynamics
    def vector_field(self, t, xi, u, y):
        zeta, v = xi[: self.q0], xi[self.q0 :]
        w = self.measured(u, y)
        dzeta = self.N @ zeta + self.J @ v + self.F @ w + self.H @ u
        dv = self.S @ zeta + self.G @ v + self.M @ w
        return jnp.concatenate([dzeta, dv])

    def output(self, t, xi, u, y):
        zeta = xi[: self.q0]
        return self.P @ zeta + self.Q @ self.measured(u, y)

    def linear_matrices(self) -> LinearObserverMatrices:
        A = self.error_matrix
        Bw = jnp.concatenate([self.F, self.M], axis=0)
        Bu = Bw @ self.Wu + jnp.concatenate([self.H, jnp.zeros((self.q1, self.H.shape[1]))], axis=0)
        By = Bw @ self.Wy
        Cm = jnp.concatenate([self.P, jnp.zeros((self.P.shape[0], self.q1))], axis=1)
        return LinearObserverMatrices(A, Bu, By, Cm, self.Q @ self.Wu, self.Q @ self.Wy)
