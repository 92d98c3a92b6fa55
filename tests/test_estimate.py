"""fojax.estimate: a designed observer run on recorded (u, y) samples.

Oracles: the record is simulated by SciPy (`scipy.signal.lsim`, linear interpolation of
u); the estimate is compared with python-control's own simulation of the exported
observer (`control.forced_response`, which also interpolates linearly between samples),
with the functional L x of SciPy's states, with a zero-order-hold recursion written out
from `scipy.linalg.expm`, and gradients with central finite differences.
"""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.signal as sig

import fojax
from fojax.interop import from_control, to_control


def _record(seed=1, T=801, horizon=8.0, uniform=True):
    """A python-control plant with D, its observer design and a SciPy-simulated log."""
    rng = np.random.default_rng(seed)
    n, m, p = 4, 2, 2
    A = rng.standard_normal((n, n)) - 2.5 * np.eye(n)
    B, C, D = rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng.standard_normal((p, m))
    L = rng.standard_normal((1, n))
    P = control.ss(A, B, C, D)
    design = fojax.design_functional_observer(from_control(P), L, region=fojax.Disk(-3.0, 1.5))
    ts = np.linspace(0.0, horizon, T)
    u = np.stack([np.sin(1.3 * ts), np.cos(0.7 * ts) + 0.2 * ts], axis=1)
    _, y, x = sig.lsim((A, B, C, D), u, ts, X0=rng.standard_normal(n))
    if not uniform:  # a random subset of the samples (first and last kept)
        keep = np.sort(np.concatenate([[0, T - 1], rng.choice(np.arange(1, T - 1), T // 3, replace=False)]))
        ts, u, y, x = ts[keep], u[keep], y[keep], x[keep]
    return design, ts, u, y, x @ L.T


@pytest.mark.parametrize("uniform", [True, False])
def test_estimate_agrees_with_python_control_and_converges(uniform):
    design, ts, u, y, z = _record(uniform=uniform)
    zh = np.asarray(fojax.estimate(design, ts, u, y))
    # python-control needs a uniform grid: the same piecewise-linear signals on the uniform
    # grid that contains every sample time, read at the sample times
    grid = np.linspace(0.0, ts[-1], 801)
    at = np.searchsorted(grid, ts - 1e-12)
    v = np.stack([np.interp(grid, ts, col) for col in np.hstack([u, y]).T])
    ref = np.reshape(control.forced_response(to_control(design), T=grid, U=v).outputs, (1, -1)).T[at]
    rel = np.abs(zh - ref).max() / np.abs(ref).max()
    assert rel < 1e-4, rel
    # the estimate converges to L x of the SciPy simulation (error poles in Disk(-3, 1.5))
    tail = ts > ts[-1] - 1.0
    assert np.abs(zh[tail] - z[tail]).max() < 1e-3 * np.abs(z).max()
    # a jitted call gives the same numbers
    zj = jax.jit(fojax.estimate)(design.observer, jnp.asarray(ts), jnp.asarray(u), jnp.asarray(y))
    np.testing.assert_allclose(zj, zh, rtol=1e-12, atol=1e-12)


def test_zero_order_hold_matches_the_expm_recursion():
    """interpolation="zoh": ξ_{k+1} = e^{A h} ξ_k + ∫ e^{As} ds B v_k, from scipy.linalg.expm."""
    design, ts, u, y, _ = _record(T=201, horizon=4.0)
    lm = design.observer.linear_matrices()
    A, Bo = np.asarray(lm.A), np.hstack([lm.Bu, lm.By])
    Co, Do = np.asarray(lm.C), np.hstack([lm.Du, lm.Dy])
    h = ts[1] - ts[0]
    s, k = A.shape[0], Bo.shape[1]
    F = scipy.linalg.expm(np.block([[A, Bo], [np.zeros((k, s + k))]]) * h)
    Phi, G = F[:s, :s], F[:s, s:]
    v = np.hstack([u, y])
    xi = np.zeros(s)
    want = []
    for j in range(len(ts)):
        want.append(Co @ xi + Do @ v[j])
        xi = Phi @ xi + G @ v[j]
    got = fojax.estimate(design, ts, u, y, interpolation="zoh")
    np.testing.assert_allclose(got, np.array(want), rtol=1e-10, atol=1e-12)


def test_vmap_over_records_and_grad_against_finite_differences():
    design, ts, u, y, _ = _record(T=101, horizon=2.0)
    obs = design.observer
    rng = np.random.default_rng(0)
    U = jnp.asarray(u[None] + 0.1 * rng.standard_normal((3,) + u.shape))
    Y = jnp.asarray(y[None] + 0.1 * rng.standard_normal((3,) + y.shape))
    batched = jax.vmap(fojax.estimate, in_axes=(None, None, 0, 0))(obs, jnp.asarray(ts), U, Y)
    for i in range(3):
        np.testing.assert_allclose(batched[i], fojax.estimate(obs, ts, U[i], Y[i]), rtol=1e-12, atol=1e-12)

    def loss(uu, yy):
        return jnp.sum(fojax.estimate(obs, jnp.asarray(ts), uu, yy) ** 2)

    gu, gy = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.asarray(u), jnp.asarray(y))
    eps = 1e-6
    for arr, g, which in ((u, gu, 0), (y, gy, 1)):
        for idx in ((5, 0), (50, 1), (100, 0)):
            d = np.zeros_like(arr)
            d[idx] = eps
            args_p = [jnp.asarray(u), jnp.asarray(y)]
            args_m = [jnp.asarray(u), jnp.asarray(y)]
            args_p[which] = jnp.asarray(arr + d)
            args_m[which] = jnp.asarray(arr - d)
            fd = (loss(*args_p) - loss(*args_m)) / (2 * eps)
            np.testing.assert_allclose(g[idx], fd, rtol=1e-6, atol=1e-8)
    # vmap of grad equals the per-record grads
    gb = jax.vmap(jax.grad(loss), in_axes=(0, 0))(U, Y)
    np.testing.assert_allclose(gb[1], jax.grad(loss)(U[1], Y[1]), rtol=1e-10, atol=1e-12)


def test_new_data_does_not_recompile():
    design, ts, u, y, _ = _record(T=51, horizon=1.0)
    f = jax.jit(fojax.estimate)
    f(design.observer, ts, u, y)
    n0 = f._cache_size()
    f(design.observer, ts + 1.0, 2 * u, y - 1.0)
    assert f._cache_size() == n0


def test_errors_are_typed_and_clear():
    design, ts, u, y, _ = _record(T=21, horizon=1.0)
    with pytest.raises(fojax.errors.ShapeError, match=r"y has shape \(20, 2\), expected \(21, 2\)"):
        fojax.estimate(design, ts, u, y[:-1])
    with pytest.raises(fojax.errors.ShapeError, match=r"u has shape \(21, 3\), expected \(21, 2\)"):
        fojax.estimate(design, ts, np.hstack([u, u[:, :1]]), y)
    bad = y.copy()
    bad[7, 1] = np.nan
    with pytest.raises(fojax.errors.NonFiniteError, match=r"y contains 1 non-finite.*first at index \(7, 1\)"):
        fojax.estimate(design, ts, u, bad)
    t2 = ts.copy()
    t2[5] = t2[4]
    with pytest.raises(fojax.errors.InputError, match=r"strictly increasing; ts\[5\]"):
        fojax.estimate(design, t2, u, y)
    with pytest.raises(fojax.errors.InputError, match="interpolation"):
        fojax.estimate(design, ts, u, y, interpolation="cubic")
    with pytest.raises(fojax.errors.InputError, match="at least two samples"):
        fojax.estimate(design, ts[:1], u[:1], y[:1])
    with pytest.raises(fojax.errors.InputError, match="observer or a design"):
        fojax.estimate("observer", ts, u, y)
    # traced data: the same checks inside XLA
    with pytest.raises(Exception, match="strictly increasing"):
        jax.jit(fojax.estimate)(design.observer, t2, u, y)
    with pytest.raises(Exception, match="NaN or infinite"):
        jax.jit(fojax.estimate)(design.observer, ts, u, bad)


def test_discrete_time_observer_runs_its_recursion():
    """A discretized observer (fojax.discretize, ZOH) on samples dt apart: the estimate is
    its own recursion, written out in NumPy; samples at another spacing are refused."""
    design, ts, u, y, _ = _record(T=101, horizon=2.0)
    h = float(ts[1] - ts[0])
    obs = fojax.discretize(design.observer, h)
    lm = obs.linear_matrices()
    A, Bo = np.asarray(lm.A), np.hstack([lm.Bu, lm.By])
    Co, Do = np.asarray(lm.C), np.hstack([lm.Du, lm.Dy])
    v = np.hstack([u, y])
    xi, want = np.zeros(A.shape[0]), []
    for k in range(len(ts)):
        want.append(Co @ xi + Do @ v[k])
        xi = A @ xi + Bo @ v[k]
    np.testing.assert_allclose(fojax.estimate(obs, ts, u, y), np.array(want), rtol=1e-10, atol=1e-12)
    # the same as the continuous observer with a zero-order hold on the same grid
    np.testing.assert_allclose(fojax.estimate(obs, ts, u, y),
                               fojax.estimate(design, ts, u, y, interpolation="zoh"), rtol=1e-9, atol=1e-10)
    with pytest.raises(fojax.errors.InputError, match="dt apart"):
        fojax.estimate(obs, ts[::2], u[::2], y[::2])
