r"""Exact stepping of linear index-1 descriptor loops on a uniform grid (host discretization).

An index-1 loop $\mathcal E\dot X = \mathcal AX + \mathcal Bv$ is reduced on the host to
its slow ODE (SVD of $\mathcal E$, $X = V[z_1; z_2]$):

$$\dot z_1 = A_sz_1 + B_sv,\qquad X = T_xz_1 + T_uv,$$

and stepped over each grid interval $[t_k, t_k + \Delta t]$ with

$$z_1(t_{k+1}) = e^{A_s\Delta t}z_1(t_k) + \sum_{j=1}^{4} W_j\,v(t_k + c_j\Delta t),$$

where $c_j$ are the Gauss–Legendre nodes of $[0, 1]$ and $W_j$ integrate, exactly, the
cubic that interpolates $v$ at the nodes against the matrix exponential (Van Loan's
block exponential; one `scipy.linalg.expm` per discretization, on the host). The
result is exact to round-off for inputs that are cubic polynomials on every grid
interval — constants, and `Step`/`Ramp`/`PiecewiseConstant` faults with their
switching times on the grid — and has local error $O(\Delta t^9)$ for smooth inputs.

Why not `fojax.simulate`? It does the same for plain loops (and `FaultTolerantControl`
can use it, ``backend="fojax"``; the tests check that both agree), but its compiled
program includes the matrix exponential, which takes seconds to compile for every new
loop structure; here the exponentials are computed once on the host and only a
`lax.scan` of matrix products is compiled. The delay loop of the finite-time
observer (`fojax.control.finite_time_loop`) needs the same discretization with a
history buffer, which `fojax.simulate` does not provide.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax import lax

from .._errors import ImpulsiveSystemError, InputError
from ..simulation._steppers import grid_deviation, UNIFORM_GRID_RTOL


#: Gauss–Legendre nodes per grid interval.
NODES = 4


def reduce_host(E, A, B):
    r"""Host reduction of $(E, A, B)$ to ``(As, Bs, Tx, Tu, V1)`` (module docstring).

    Raises `fojax.ImpulsiveSystemError` when $\tilde A_{22}$ is singular (index > 1).
    """
    from ..analysis._split import index1_split

    E, A, B = (np.asarray(x, dtype=float) for x in (E, A, B))
    n = E.shape[0]
    sp = index1_split(E, A, fname="reduce_host")  # fojax.analysis's rank and verdict
    r, s = sp.rank, sp.s
    U1, U2, V1, V2 = sp.U1, sp.U2, sp.V1, sp.V2
    A11, A12, A21, A22 = sp.blocks(A)
    B1, B2 = U1.T @ B, U2.T @ B
    if n - r:
        if not sp.impulse_free:
            raise ImpulsiveSystemError(
                "the loop is not impulse-free: U2ᵀ A V2 (the algebraic block) is singular, so the "
                "algebraic variables are not determined (index > 1). Check the design "
                "(fojax.analysis.is_impulse_free)."
            )
        K = -np.linalg.solve(A22, A21)
        Ku = -np.linalg.solve(A22, B2)
    else:
        K, Ku = np.zeros((0, r)), np.zeros((0, B.shape[1]))
    sig = s[:r, None]
    As = (A11 + A12 @ K) / sig
    Bs = (B1 + A12 @ Ku) / sig
    return As, Bs, V1 + V2 @ K, V2 @ Ku, V1


def gauss_nodes(nu: int = NODES):
    """Nodes ``c`` on [0, 1], the inverse ``Vinv`` of ``V[j, i] = c_j^i / i!`` and the
    Lagrange weights ``ell0``, ``ell1`` giving the interpolant's values at τ = 0 and 1."""
    x, _ = np.polynomial.legendre.leggauss(nu)
    c = 0.5 * (x + 1.0)
    fact = np.array([math.factorial(i) for i in range(nu)], dtype=float)
    V = c[:, None] ** np.arange(nu)[None, :] / fact[None, :]
    Vinv = np.linalg.inv(V)
    ell0 = Vinv[0]  # v(0) = a_0
    ell1 = (1.0 / fact) @ Vinv  # v(1) = Σ a_i / i!
    return c, Vinv, ell0, ell1


def discretize_host(As, Bs, dt: float, nu: int = NODES):
    r"""``Φ = e^{A_s Δt}`` and ``W`` (``(nu, N, m)``) on the host (module docstring)."""
    As, Bs = np.asarray(As, float), np.asarray(Bs, float)
    N, m = Bs.shape
    c, Vinv, _, _ = gauss_nodes(nu)
    if m == 0:
        return scipy.linalg.expm(dt * As), np.zeros((nu, N, 0))
    size = N + nu * m
    M = np.zeros((size, size))
    M[:N, :N] = dt * As
    M[:N, N : N + m] = dt * Bs
    for i in range(nu - 1):
        a, b = N + i * m, N + (i + 1) * m
        M[a : a + m, b : b + m] = np.eye(m)
    F = scipy.linalg.expm(M)
    G = np.stack([F[:N, N + i * m : N + (i + 1) * m] for i in range(nu)])
    W = np.einsum("ij,ink->jnk", Vinv, G)
    return F[:N, :N], W


def grid_step(ts) -> float:
    """The step of a uniform grid (checked on the host when `ts` is concrete)."""
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
    """Discretized index-1 loop (leaves: arrays; a new loop of the same size reuses the
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
    dt = ts[1] - ts[0]
    nodes = ts[:-1, None] + st.c[None, :] * dt
    Un = jax.vmap(jax.vmap(u))(nodes)  # (T-1, nu, m)
    forcing = jnp.einsum("jnk,tjk->tn", st.W, Un)
    z0 = st.V1.T @ x0

    def step(z, f):
        z = st.Phi @ z + f
        return z, z

    _, zs = lax.scan(step, z0, forcing)
    zs = jnp.concatenate([z0[None], zs], axis=0)
    us = jax.vmap(u)(ts)
    xs = zs @ st.Tx.T + us @ st.Tu.T
    return xs, us


def simulate_lti(system, x0, ts, u):
    r"""Exact stepping of an index-1 `DescriptorSystem` on a uniform grid.

    **Arguments:** `system`, `x0` ``(n,)`` (its slow part $V_1^\top x_0$ is kept; the
    algebraic part is recomputed — the same projection as `fojax.simulate`), `ts`
    (uniform, concrete), `u` (a `fojax.AbstractSignal` of size ``system.m``).

    **Returns:** ``(xs, us)`` on the grid. Works under `jax.vmap` over `x0` and `u`.
    """
    st = LTIStepper.build(system, grid_step(ts))
    return st(x0, ts, u)
