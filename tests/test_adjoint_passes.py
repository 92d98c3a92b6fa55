"""The exact kernel's loss loop in passes of S grid steps (`fojax.studies._adjoint.pass_recurrence_reduce`).

Oracles: (1) `jax.grad` of a plain `jax.lax.scan` of the same recurrence, step by step,
written here (values and gradients to 1e-12 relative); (2) `study_loss` with the loop step
by step (`split_recurrence_reduce`, the implementation before the passes: `pass_length`
patched to 1) on a study without jumps, loss and gradient to 1e-12 relative; (3) `run_study`'s
forward engine for the loss's value; (4) central finite differences of the ISE loss.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax import studies as S

# private: the adjoint passes of the exact kernel are tested themselves
from fojax.studies import _adjoint, _exact
from tests.helpers import small_step_input_study


M, Q, K, B = 3, 4, 2, 3  # plant states, observer states, outputs, samples


class _Loss(eqx.Module):
    """The additive reduction of `study_loss` (`LossProblem`): ISE, smooth."""

    additive = True

    def init(self, o0):
        return jnp.zeros_like(o0)

    def update(self, acc, o, k, ts):
        return acc + o * o


@pytest.fixture(scope="module")
def data():
    k = jax.random.split(jax.random.PRNGKey(7), 7)
    Ppp = 0.9 * jnp.eye(M)[:, :, None] + 0.05 * jax.random.normal(k[0], (M, M, B))
    Poo = 0.8 * jnp.eye(Q)[:, :, None] + 0.05 * jax.random.normal(k[1], (Q, Q, B))
    Pop = 0.1 * jax.random.normal(k[2], (Q, M, B))
    Go = jax.random.normal(k[3], (K, Q, B))
    Gp = jax.random.normal(k[4], (K, M, B))
    xi0 = jax.random.normal(k[5], (Q, B))
    p0 = jax.random.normal(k[6], (M, B))
    return (Poo, Pop, Go, Gp, xi0), (Ppp, p0)


def _scalar(acc, p_end, xi_end):
    return jnp.sum(acc * jnp.arange(1.0, K + 1)[:, None]) + jnp.sum(jnp.sin(xi_end)) + jnp.sum(p_end)


def _plain(d, plant, T):
    """Oracle (1): the loop step by step as a plain scan."""
    Poo, Pop, Go, Gp, xi0 = d
    Ppp, p0 = plant

    def step(c, _):
        p, xi, acc = c
        pn = jnp.einsum("ijb,jb->ib", Ppp, p)
        xn = jnp.einsum("ijb,jb->ib", Poo, xi) + jnp.einsum("ijb,jb->ib", Pop, p)
        o = jnp.einsum("kib,ib->kb", Go, xn) + jnp.einsum("kib,ib->kb", Gp, pn)
        return (pn, xn, acc + o * o), None

    (p, xi, acc), _ = jax.lax.scan(step, (p0, xi0, jnp.zeros((K, B))), None, length=T - 1)
    return _scalar(acc, p, xi)


def test_pass_length():
    assert [_adjoint.pass_length(n) for n in (1000, 999, 20, 8, 4, 3, 2)] == [8, 1, 4, 4, 2, 1, 1]


@pytest.mark.parametrize("T, segment", [(33, None), (33, 2)])
def test_passes_equal_plain_scan_and_its_gradient(data, T, segment):
    d, plant = data
    ts = jnp.linspace(0.0, 1.0, T)
    S_ = _adjoint.pass_length(T - 1)
    assert S_ == 8  # 4 passes: one segment of 3 (None), or 2 + a last one of 1

    def f(d):
        acc, p_end, xi_end = _adjoint.pass_recurrence_reduce(d + (None, ts), plant + (None,), _Loss(), S_, segment)
        return _scalar(acc, p_end, xi_end)

    want_v, want_g = jax.value_and_grad(lambda d: _plain(d, plant, T))(d)
    v, g = jax.jit(jax.value_and_grad(f))(d)
    assert np.isclose(float(v), float(want_v), rtol=1e-12)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(want_g)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12 * float(jnp.max(jnp.abs(b))))


def test_passes_refuse_jumps_and_non_dividing_grids(data):
    d, plant = data
    with pytest.raises(fojax.errors.InputError, match="steps per pass"):
        _adjoint.pass_recurrence_reduce(d + (None, jnp.linspace(0.0, 1.0, 12)), plant + (None,), _Loss(), 4)


@pytest.fixture(scope="module")
def study():
    # the short §3.3.7 study of the study-loss tests without its step input: no jumps, so
    # study_loss takes the passes (20 steps: S = 4)
    st, d = small_step_input_study(11, 3, 2)
    st = S.Study(st.plant, st.x0, st.ts, st.L, None, uncertainty=st.uncertainty, scenarios=st.scenarios)
    return st, d.observer


def _vg(study, observer, loss):
    dyn, st = eqx.partition(observer, eqx.is_inexact_array)
    f = eqx.filter_jit(eqx.filter_value_and_grad(lambda p: S.study_loss(study, eqx.combine(p, st), loss=loss)))
    return f, dyn


def test_study_loss_in_passes_equals_step_by_step_run_study_and_central_differences(study, monkeypatch):
    # the ISE loss (smooth: a sharp finite-difference oracle); the IAE loss runs the same
    # code with another integrand (and is what benchmarks/tuning_step.py compares)
    st, observer = study
    calls = []
    real = _exact.pass_recurrence_reduce
    monkeypatch.setattr(_exact, "pass_recurrence_reduce", lambda *a, **k: calls.append(a[3]) or real(*a, **k))
    f, dyn = _vg(st, observer, "ise")
    v, g = f(dyn)
    assert calls == [4]  # the loss took the passes, 4 steps each
    res = S.run_study(st, (observer,), stepper=fojax.Exact(), quantiles=(), quiet=True, devices=jax.devices()[:1])
    assert np.isclose(float(v), float(np.mean(np.asarray(res.metrics["ise"])[0])), rtol=1e-12)
    monkeypatch.setattr(_exact, "pass_length", lambda n: 1)  # step by step: the loop before the passes
    f1, _ = _vg(st, observer, "ise")
    v1, g1 = f1(dyn)
    assert np.isclose(float(v), float(v1), rtol=1e-12)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g1)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(b))))
    monkeypatch.undo()
    # central differences along a random direction, on the passes
    st_obs = eqx.partition(observer, eqx.is_inexact_array)[1]
    loss_fn = eqx.filter_jit(lambda p: S.study_loss(st, eqx.combine(p, st_obs), loss="ise"))
    leaves = jax.tree.leaves(dyn)
    keys = jax.random.split(jax.random.PRNGKey(3), len(leaves))
    u = jax.tree.unflatten(jax.tree.structure(dyn), [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])
    an = float(sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(u))))
    eps = 1e-5
    fd = (float(loss_fn(jax.tree.map(lambda a, b: a + eps * b, dyn, u)))
          - float(loss_fn(jax.tree.map(lambda a, b: a - eps * b, dyn, u)))) / (2 * eps)
    assert abs(an - fd) <= 1e-6 * abs(fd)
