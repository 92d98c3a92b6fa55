r"""The exact step of a linear slow ODE on a uniform grid (the `fojax.Exact` stepper's step).

The slow ODE $\dot w = \mathcal A w + \mathcal B u$ of an index-1 loop (`joint_matrices`,
or `reduce_host` for a loop given by its matrices) is stepped over each grid interval
$[t_k, t_k + h]$ with

$$w_{k+1} = e^{\mathcal A h} w_k + \sum_{j=1}^{\nu} W_j\,u(t_k + c_j h),$$

where $c_j$ are the $\nu = 4$ Gauss–Legendre nodes of $[0, 1]$ and $W_j$ integrate, exactly,
the polynomial that interpolates $u$ at the nodes against the matrix exponential (Van
Loan's block exponential, `discretize`). Exact to round-off for inputs that are
polynomials of degree $< \nu$ on every interval (constants, and `Step`/`Ramp`/
`PiecewiseConstant` signals switching on the grid); local error $O(h^{2\nu+1})$ for smooth
inputs.

- `discretize`: traced (`fojax.simulation._expm.expm_small`), inside `fojax.simulate`'s
  compiled program;
- `discretize_host`: on the host (`scipy.linalg.expm`), for a loop discretised once and
  then stepped by a compiled scan of matrix products only (`simulate_lti`, the loops of
  `fojax.control`: nothing but the scan is compiled, whatever the loop's structure);
- `step_exact`: the time loop both use.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax import lax

from .._errors import InputError
from ._expm import expm_small
from ._reduction import reduce_host
from ._steppers import grid_deviation, UNIFORM_GRID_RTOL


#: Gauss–Legendre nodes per grid interval.
QUADRATURE_NODES = 4


def gauss_nodes(nu: int = QUADRATURE_NODES):
    """Nodes ``c`` on [0, 1], the inverse ``Vinv`` of ``V[j, i] = c_j^i / i!`` (the
    interpolant ``u(c_j) = Σ_i a_i c_j^i / i!`` has ``a = Vinv @ u_nodes``) and the Lagrange
    weights ``ell0``, ``ell1`` giving the interpolant's values at τ = 0 and 1."""
    x, _ = np.polynomial.legendre.leggauss(nu)
    c = 0.5 * (x + 1.0)
    fact = np.array([math.factorial(i) for i in range(nu)], dtype=float)
    V = c[:, None] ** np.arange(nu)[None, :] / fact[None, :]
    Vinv = np.linalg.inv(V)
    ell0 = Vinv[0]  # v(0) = a_0
    ell1 = (1.0 / fact) @ Vinv  # v(1) = Σ a_i / i!
    return c, Vinv, ell0, ell1


def _van_loan(A, B, h, nu, xp):
    """The Van Loan matrix of `discretize` in normalised time τ = s/h (entries O(1), so no
    cancellation between the monomial moments), in `xp` (NumPy or `jax.numpy`)."""
    N, m = B.shape
    blocks = [[h * A, h * B] + [xp.zeros((N, m), A.dtype)] * (nu - 1)]
    for i in range(nu):
        row = [xp.zeros((m, N), A.dtype)] + [xp.zeros((m, m), A.dtype)] * nu
        if i < nu - 1:
            row[i + 2] = xp.eye(m, dtype=A.dtype)
        blocks.append(row)
    return xp.block(blocks)


def discretize(Aj, Bj, h, nu: int = QUADRATURE_NODES):
    r"""``(Φ, W, c)``: ``Φ = expm(h A)``, the product-Gauss weights ``W_j`` (``(nu, N, m)``)
    and the nodes ``c``, traced.

    $\int_0^h e^{A(h-s)}B\,u(t_k+s)\,\mathrm ds \approx \sum_j W_j\,u(t_k + c_j h)$,
    exact for polynomial ``u`` of degree ``< nu``; from one exponential of the Van Loan
    matrix $\begin{bmatrix} hA & hB & & \\ & 0 & I & \\ & & \ddots & I\\ &&&0\end{bmatrix}$.
    """
    N, m = Bj.shape
    c, Vinv, _, _ = gauss_nodes(nu)
    if m == 0:
        return expm_small(h * Aj), jnp.zeros((nu, N, 0), dtype=Aj.dtype), c
    F = expm_small(_van_loan(Aj, Bj, h, nu, jnp))
    G = jnp.stack([F[:N, N + i * m : N + (i + 1) * m] for i in range(nu)])  # (nu, N, m)
    W = jnp.einsum("ij,ink->jnk", jnp.asarray(Vinv, dtype=Aj.dtype), G)
    return F[:N, :N], W, c


def discretize_host(As, Bs, dt: float, nu: int = QUADRATURE_NODES):
    r"""``(Φ, W)`` of `discretize`, on the host (NumPy arrays, `scipy.linalg.expm`)."""
    As, Bs = np.asarray(As, float), np.asarray(Bs, float)
    N, m = Bs.shape
    _, Vinv, _, _ = gauss_nodes(nu)
    if m == 0:
        return scipy.linalg.expm(dt * As), np.zeros((nu, N, 0))
    F = scipy.linalg.expm(_van_loan(As, Bs, dt, nu, np))
    G = np.stack([F[:N, N + i * m : N + (i + 1) * m] for i in range(nu)])
    W = np.einsum("ij,ink->jnk", Vinv, G)
    return F[:N, :N], W


def step_exact(Phi, W, c, w0, ts, h, u):
    r"""``(T, N)``: $w_0$ and $w_{k+1} = \Phi w_k + \sum_j W_j u(t_k + c_j h)$ on the grid
    ``ts`` (a `jax.lax.scan`)."""
    if W.shape[-1] > 0:
        nodes = ts[:-1, None] + jnp.asarray(c)[None, :] * h
        Un = jax.vmap(jax.vmap(u))(nodes)  # (T-1, nu, m)
        forcing = jnp.einsum("jnk,tjk->tn", W, Un)
    else:
        forcing = jnp.zeros((ts.shape[0] - 1, Phi.shape[0]), dtype=Phi.dtype)

    def step(w, f):
        w = Phi @ w + f
        return w, w

    _, ws = lax.scan(step, w0, forcing)
    return jnp.concatenate([w0[None], ws], axis=0)


def grid_step(ts) -> float:
    """The step of a concrete uniform grid (`fojax.errors.InputError` otherwise)."""
    if isinstance(ts, jax.core.Tracer):
        raise InputError("the exact stepper needs concrete output times ts (not traced).")
    t = np.asarray(ts, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise InputError(f"ts must be a 1-d array with at least 2 times, got shape {t.shape}.")
    dev, dt = grid_deviation(t)  # the one uniform-grid test (inf when dt <= 0)
    if not dev <= UNIFORM_GRID_RTOL:
        raise InputError(
            "the exact stepper needs a uniform, increasing grid ts (use jnp.linspace); "
            f"max |t_k − (t_0 + kΔt)|/Δt = {dev:.2e}."
        )
    return float(dt)


class LTIStepper(eqx.Module):
    """A loop discretised on the host (leaves: arrays; a new loop of the same size reuses the
    compiled scan)."""

    Phi: jax.Array
    W: jax.Array
    c: jax.Array
    Tx: jax.Array
    Tu: jax.Array
    V1: jax.Array

    @classmethod
    def build(cls, system, dt: float) -> LTIStepper:
        As, Bs, Tx, Tu, V1 = reduce_host(system.E, system.A, system.B)
        Phi, W = discretize_host(As, Bs, dt)
        c, *_ = gauss_nodes()
        return cls(*(jnp.asarray(a) for a in (Phi, W, c, Tx, Tu, V1)))

    def __call__(self, x0, ts, u):
        return _lti_scan(self, jnp.asarray(x0, dtype=jnp.float64), jnp.asarray(ts), u)


@eqx.filter_jit
def _lti_scan(st: LTIStepper, x0, ts, u):
    zs = step_exact(st.Phi, st.W, st.c, st.V1.T @ x0, ts, ts[1] - ts[0], u)
    us = jax.vmap(u)(ts)
    return zs @ st.Tx.T + us @ st.Tu.T, us


def simulate_lti(system, x0, ts, u):
    r"""Exact stepping of an index-1 `DescriptorSystem` on a uniform grid, discretised on the
    host (`discretize_host`; only the time loop is compiled).

    **Arguments:** `system`, `x0` ``(n,)`` (its slow part $V_1^\top x_0$ is kept; the
    algebraic part is recomputed — the same projection as `fojax.simulate`), `ts`
    (uniform, concrete), `u` (a `fojax.plant.AbstractSignal` of size ``system.m``).

    **Returns:** ``(xs, us)`` on the grid. Works under `jax.vmap` over `x0` and `u`.
    """
    st = LTIStepper.build(system, grid_step(ts))
    return st(x0, ts, u)
