r"""Finite-time functional observer (thesis §3.1.2–3.1.3), with an exact reconstruction.

Two generalized observers $i = 1, 2$ with a **common** $T$ (same $R$ and $Z$) and error
matrices $\mathbb A_1, \mathbb A_2$ with separated spectra run in parallel. With
$\xi_i = [\zeta_i; v_i]$, $m(t) = TEx(t)$ and $\vartheta_i = \xi_i - [m; 0]$,
$\vartheta_i(t) = e^{\mathbb A_i h}\vartheta_i(t-h)$ gives, for any input,

$$\underbrace{\xi_i(t) - e^{\mathbb A_i h}\xi_i(t-h)}_{D_i(t)}
  = \Pi_0 m(t) - e^{\mathbb A_i h}\Pi_0\, m(t-h),\qquad \Pi_0 = [I_{q_0}; 0].$$

Stacking $i = 1, 2$: $\mathbb M [m(t); m(t-h)] = [D_1; D_2]$ with
$\mathbb M = \begin{bmatrix}\Pi_0 & -e^{\mathbb A_1h}\Pi_0\\ \Pi_0 & -e^{\mathbb A_2h}\Pi_0\end{bmatrix}$,
which has full column rank when Lemma 6's separation holds (then
$[I\;e^{\mathbb A_1h}; I\;e^{\mathbb A_2h}]$ is nonsingular). Hence

$$z(t) = P\,[I\;0]\,\mathbb M^+ [D_1(t); D_2(t)] + Q\,w(t)\qquad (t \ge h)$$

exactly (for the nominal model), because $z = P\,TEx + Qw$ by condition d.

**Deviation from the thesis.** Formula (3.107) reconstructs $z$ from the two
*outputs* $\hat z_i$ through $\bar P^+$; it is exact only when $\bar P = [P\;0]$ has full
column rank, which fails whenever $q_1 > 0$ (and whenever $P$ is not injective).
fojax uses the observers' full internal states instead (above).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._base import AbstractObserver, LinearObserverMatrices
from ._generalized import GeneralizedFunctionalObserver


class FiniteTimeObserver(AbstractObserver):
    r"""Two generalized observers and a delay ``h`` (see module docstring).

    The internal state is $[\xi_1; \xi_2]$. `output` returns the *asymptotic* estimate
    of observer 1 (what is available without history); `reconstruct` returns the
    exact finite-time estimate from the current and the delayed state, and
    `finite_time_estimates` applies it along a simulated trajectory.

    **Attributes:** `obs1`, `obs2` (the two `GeneralizedFunctionalObserver`\ s),
    `h` (delay), `Gamma_now`, `Gamma_delay` (``q0 × 2(q0+q1)``: $\hat m(t) =
    \Gamma_{now}[\xi_1;\xi_2](t) - \Gamma_{delay}[\xi_1;\xi_2](t-h)$).
    """

    obs1: GeneralizedFunctionalObserver
    obs2: GeneralizedFunctionalObserver
    h: Float[Array, ""]
    Gamma_now: Float[Array, "q0 s"]
    Gamma_delay: Float[Array, "q0 s"]

    @property
    def state_size(self) -> int:
        return self.obs1.state_size + self.obs2.state_size

    @property
    def output_size(self) -> int:
        return self.obs1.output_size

    def _split(self, xi):
        s1 = self.obs1.state_size
        return xi[..., :s1], xi[..., s1:]

    def vector_field(self, t, xi, u, y):
        x1, x2 = self._split(xi)
        return jnp.concatenate(
            [self.obs1.vector_field(t, x1, u, y), self.obs2.vector_field(t, x2, u, y)]
        )

    def output(self, t, xi, u, y):
        x1, _ = self._split(xi)
        return self.obs1.output(t, x1, u, y)

    def reconstruct(self, xi_now, xi_delayed, u, y):
        """Exact estimate of ``z(t)`` from ``ξ(t)``, ``ξ(t - h)`` and ``u(t), y(t)``."""
        m = self.Gamma_now @ xi_now - self.Gamma_delay @ xi_delayed
        return self.obs1.P @ m + self.obs1.Q @ self.obs1.measured(u, y)

    def finite_time_estimates(self, ts, xis, us, ys):
        """Apply `reconstruct` along a trajectory on a uniform grid.

        `ts` must be uniform with ``h`` a multiple of the step (checked); for
        ``t < h`` the asymptotic estimate of observer 1 is returned.
        Returns ``(T, q)``.
        """
        import numpy as np

        ts_np = np.asarray(ts)
        dt = float(ts_np[1] - ts_np[0])
        if not np.allclose(np.diff(ts_np), dt, rtol=1e-9, atol=1e-12):
            raise ValueError("finite_time_estimates needs a uniform time grid")
        k = int(round(float(self.h) / dt))
        if abs(k * dt - float(self.h)) > 1e-9 * max(1.0, float(self.h)):
            raise ValueError(
                f"the delay h = {float(self.h)} must be a multiple of the grid step {dt}; "
                "choose ts with a step that divides h."
            )
        o = self.obs1
        q0 = o.q0
        asym = (
            jnp.einsum("ij,tj->ti", o.P, xis[:k, :q0])
            + jnp.einsum("ij,tj->ti", o.Q @ o.Wu, us[:k])
            + jnp.einsum("ij,tj->ti", o.Q @ o.Wy, ys[:k])
        )
        exact = (
            jnp.einsum("ij,tj->ti", self.obs1.P @ self.Gamma_now, xis[k:])
            - jnp.einsum("ij,tj->ti", self.obs1.P @ self.Gamma_delay, xis[: len(ts_np) - k])
            + jnp.einsum("ij,tj->ti", self.obs1.Q @ self.obs1.Wu, us[k:])
            + jnp.einsum("ij,tj->ti", self.obs1.Q @ self.obs1.Wy, ys[k:])
        )
        return jnp.concatenate([asym, exact], axis=0)

    def linear_matrices(self) -> LinearObserverMatrices:
        m1, m2 = self.obs1.linear_matrices(), self.obs2.linear_matrices()
        s1, s2 = self.obs1.state_size, self.obs2.state_size
        A = jnp.block([[m1.A, jnp.zeros((s1, s2))], [jnp.zeros((s2, s1)), m2.A]])
        C = jnp.concatenate([m1.C, jnp.zeros((m1.C.shape[0], s2))], axis=1)
        return LinearObserverMatrices(
            A,
            jnp.concatenate([m1.Bu, m2.Bu]),
            jnp.concatenate([m1.By, m2.By]),
            C,
            m1.Du,
            m1.Dy,
        )
