"""Parts of the exponential kernel (`fojax.simulation._exponential`) with their own derivation.

Oracles: (1) the φ-functions in closed form on a diagonalizable matrix,
$\\varphi_j(hA) = V\\,\\mathrm{diag}(\\varphi_j(h\\lambda))\\,V^{-1}$ with
$\\varphi_1(z) = (e^z-1)/z$, $\\varphi_2(z) = (e^z-1-z)/z^2$, $\\varphi_3(z) = (e^z-1-z-z^2/2)/z^3$,
for both the host path (SciPy's expm of the augmented matrix) and the traced path (the
scaled Taylor series); (2) the custom tangent rule of `_matvec_batch` against NumPy's
``einsum`` (value), the JVP and VJP that JAX derives for the plain ``einsum`` form, and a
central finite difference, under `jax.jit` and `jax.vmap`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# private: the kernel's parts are tested themselves
from fojax.simulation._exponential import _matvec_batch, phi_functions


def _closed_form(A, h):
    lam, V = np.linalg.eig(A)
    z = h * lam
    e = np.exp(z)
    phis = [e, (e - 1) / z, (e - 1 - z) / z**2, (e - 1 - z - z**2 / 2) / z**3]
    return np.stack([np.real(V @ np.diag(p) @ np.linalg.inv(V)) for p in phis])


@pytest.mark.parametrize("h", [0.01, 0.3])
def test_phi_functions_host_and_traced_match_the_closed_form(h):
    rng = np.random.default_rng(4)
    A = rng.standard_normal((6, 6)) - 3.0 * np.eye(6)
    host = phi_functions(jnp.asarray(A), jnp.asarray(h))
    traced = jax.jit(phi_functions)(jnp.asarray(A), jnp.asarray(h))
    for k, scale in enumerate((h, 0.5 * h)):
        ref = _closed_form(A, scale)
        for got in (host[k], traced[k]):
            # the closed form divides by z^3 (|z| >= ~0.01): its own round-off ~1e-10 at h = 0.01
            np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))
        np.testing.assert_allclose(np.asarray(host[k]), np.asarray(traced[k]), rtol=0, atol=1e-14)


def test_matvec_batch_value_jvp_vjp():
    rng = np.random.default_rng(5)
    M, v = jnp.asarray(rng.standard_normal((4, 5, 3))), jnp.asarray(rng.standard_normal((5, 3)))
    dM, dv = jnp.asarray(rng.standard_normal(M.shape)), jnp.asarray(rng.standard_normal(v.shape))
    plain = lambda M, v: jnp.einsum("ijb,jb->ib", M, v)  # noqa: E731
    np.testing.assert_allclose(np.asarray(jax.jit(_matvec_batch)(M, v)), np.einsum("ijb,jb->ib", M, v), rtol=0, atol=1e-13)
    _, t = jax.jit(lambda M, v, dM, dv: jax.jvp(_matvec_batch, (M, v), (dM, dv)))(M, v, dM, dv)
    _, t_ref = jax.jvp(plain, (M, v), (dM, dv))
    np.testing.assert_allclose(np.asarray(t), np.asarray(t_ref), rtol=1e-13, atol=1e-14)
    eps = 1e-6  # central difference of the value along (dM, dv): the map is bilinear
    fd = (_matvec_batch(M + eps * dM, v + eps * dv) - _matvec_batch(M - eps * dM, v - eps * dv)) / (2 * eps)
    np.testing.assert_allclose(np.asarray(t), np.asarray(fd), rtol=1e-8, atol=1e-9)
    ct = jnp.asarray(rng.standard_normal((4, 3)))
    g = jax.jit(jax.grad(lambda M, v: jnp.sum(ct * _matvec_batch(M, v)), argnums=(0, 1)))(M, v)
    g_ref = jax.grad(lambda M, v: jnp.sum(ct * plain(M, v)), argnums=(0, 1))(M, v)
    for a, b in zip(g, g_ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-14)
    # only one argument differentiated (a symbolic-zero tangent), and under vmap
    gv = jax.vmap(jax.grad(lambda v, M: jnp.sum(_matvec_batch(M, v))), in_axes=(None, 0))(v, jnp.stack([M, 2 * M]))
    np.testing.assert_allclose(np.asarray(gv[1]), 2 * np.asarray(gv[0]), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(gv[0]), np.asarray(M).sum(axis=0), rtol=1e-13)
