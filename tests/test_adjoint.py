"""The adjoint (custom VJP) of the exact kernel's time loop (`fojax.studies._adjoint`, a private
piece tested itself): the split loop, and the loss loop in passes of S grid steps.

**Split loop** (`split_recurrence_reduce`). Oracles: (1) a plain `jax.lax.scan` of the same recurrence written here, differentiated
by `jax.grad` (what `study_loss` used before the custom VJP); (2) a NumPy loop for the
forward values; (3) central finite differences; (4) `study_loss` on a study with jumps (a
step input between grid points) with the kernel's former time loop, through `jax.grad`.
Every check runs on the split loop (`split_recurrence_reduce`: plant constant, adjoint at
the observers' size; the joint `linear_recurrence_reduce` was removed as unused) on a block
lower-triangular Φ: (1) as the matching blocks of `jax.grad` of the joint scan.

**Passes** (`pass_recurrence_reduce`). Oracles: (1) `jax.grad` of a plain `jax.lax.scan` of the same recurrence, step by step,
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
# private: the adjoint passes of the exact kernel are tested themselves
from fojax.studies import _adjoint, _exact
from fojax.studies._adjoint import split_recurrence_reduce
from tests.helpers import small_step_input_study


class _Metrics(eqx.Module):
    """`run_study`'s accumulators (the ones `study_loss` differentiates)."""

    settle_tol: jax.Array
    kinds: tuple = eqx.field(static=True, default=_exact.METRIC_NAMES)  # every metric accumulated
    computed = _exact.StudyProblem.computed
    init = _exact.StudyProblem.init
    update = _exact.StudyProblem.update


N, B, T, K, J = 4, 3, 12, 2, 2
PROB = _Metrics(jnp.asarray(0.3))


@pytest.fixture(scope="module")
def data():
    k = jax.random.split(jax.random.PRNGKey(3), 5)
    Phi = 0.9 * jnp.eye(N)[:, :, None] + 0.1 * jax.random.normal(k[0], (N, N, B))
    w0 = jax.random.normal(k[1], (N, B))
    G = jax.random.normal(k[2], (K, N, B))
    jv = jax.random.normal(k[3], (J, N, B))
    kon = jnp.array([[3, 11, -1], [7, 5, 1]])  # (J, B): jumps at steps 1 .. n = 11, -1 none
    ts = jnp.linspace(0.0, 1.1, T)
    return (Phi, w0, G, jv, ts), kon


def plain(diff, kon):
    """The recurrence as a plain scan (the oracle)."""
    Phi, w0, G, jv, ts = diff
    acc = PROB.init(jnp.einsum("kib,ib->kb", G, w0))

    def step(c, k):
        w, acc = c
        w = jnp.einsum("ijb,jb->ib", Phi, w) + jnp.einsum("jb,jib->ib", (kon == k).astype(w.dtype), jv)
        return (w, PROB.update(acc, jnp.einsum("kib,ib->kb", G, w), k, ts)), None

    (w, acc), _ = jax.lax.scan(step, (w0, acc), jnp.arange(1, T))
    return acc, w


#: plant part p = w[:M] (constant), observers ξ = w[M:]: Φ block lower triangular
M = 2


def split_data(data):
    """The split loop's arguments from the joint ``data``: ``(d0, plant, ts, kon)`` with
    ``d0 = (Φ_ξξ, Φ_ξp, G_ξ, G_p, ξ_0, jv_ξ)`` (differentiated) and Φ's upper right block zero."""
    (Phi, w0, G, jv, ts), kon = data
    Phi = Phi.at[:M, M:].set(0.0)
    d0 = (Phi[M:, M:], Phi[M:, :M], G[:, M:], G[:, :M], w0[M:], jv[:, M:])
    return d0, (Phi[:M, :M], w0[:M], jv[:, :M]), ts, kon


def split_scalar(d, plant, ts, kon, segment):
    """A scalar of every accumulator and of ξ_n, through `split_recurrence_reduce`."""
    (s1, s2, s3, peak, _), p_end, xi_end = split_recurrence_reduce(d + (ts,), plant, PROB, kon, segment)
    return jnp.sum(s1) + 0.7 * jnp.sum(s2) - 0.3 * jnp.sum(s3) + 0.2 * jnp.sum(peak) + jnp.sum(jnp.sin(xi_end))


def test_forward_matches_numpy_loop(data):
    d0, plant, ts, kon = split_data(data)
    (s1, s2, s3, peak, last), p_end, xi_end = split_recurrence_reduce(d0 + (ts,), plant, PROB, kon, segment=5)
    Poo, Pop, Go, Gp, xi0, jvo = (np.asarray(x) for x in d0)
    Ppp, p0, jvp = (np.asarray(x) for x in plant)
    Phi = np.concatenate([np.concatenate([Ppp, np.zeros((M, N - M, B))], axis=1),
                          np.concatenate([Pop, Poo], axis=1)], axis=0)
    G, w0, jv = np.concatenate([Gp, Go], axis=1), np.concatenate([p0, xi0]), np.concatenate([jvp, jvo], axis=1)
    ts, kon = np.asarray(ts), np.asarray(kon)
    w = np.concatenate([np.asarray(p_end), np.asarray(xi_end)])
    for b in range(B):
        w_ = w0[:, b].copy()
        os_ = [G[:, :, b] @ w_]
        for k in range(1, T):
            w_ = Phi[:, :, b] @ w_ + sum(jv[j, :, b] for j in range(J) if kon[j, b] == k)
            os_.append(G[:, :, b] @ w_)
        o = np.abs(np.array(os_))
        np.testing.assert_allclose(w[:, b], w_, rtol=1e-12)
        np.testing.assert_allclose(s1[:, b], o[1:].sum(0), rtol=1e-12)
        np.testing.assert_allclose(s2[:, b], (o[1:] ** 2).sum(0), rtol=1e-12)
        np.testing.assert_allclose(s3[:, b], ((ts[1:] - ts[0])[:, None] * o[1:]).sum(0), rtol=1e-12)
        np.testing.assert_allclose(peak[:, b], o.max(0), rtol=1e-12)
        above = np.nonzero(o > 0.3)
        lastk = [max([k for k, i in zip(*above) if i == r], default=-1) for r in range(K)]
        np.testing.assert_array_equal(last[:, b], lastk)


def test_grad_matches_central_differences(data):
    d0, plant, ts, kon = split_data(data)
    f = jax.jit(lambda d: split_scalar(d, plant, ts, kon, 4))
    g = jax.grad(f)(d0)
    keys = jax.random.split(jax.random.PRNGKey(11), len(d0))
    eps = 1e-6
    for i in range(len(d0)):  # Φ_ξξ, Φ_ξp, G_ξ, G_p, ξ_0, jv_ξ along a random direction
        v = jax.random.normal(keys[i], d0[i].shape)
        up = tuple(x + eps * v if k == i else x for k, x in enumerate(d0))
        dn = tuple(x - eps * v if k == i else x for k, x in enumerate(d0))
        fd = (f(up) - f(dn)) / (2 * eps)
        an = jnp.sum(g[i] * v)
        assert abs(float(an - fd)) <= 1e-6 * max(1.0, abs(float(fd))), (i, float(an), float(fd))


def test_vmap_of_grad_equals_per_element_grad(data):
    d0, plant, ts, kon = split_data(data)
    scale = jnp.array([0.5, 1.0, 1.3])

    def loss(c):
        return split_scalar((c * d0[0],) + d0[1:], plant, ts, kon, 5)

    gv = jax.jit(jax.vmap(jax.grad(loss)))(scale)
    g1 = jax.jit(jax.grad(loss))
    for c, gc in zip(scale, gv):
        np.testing.assert_allclose(gc, g1(c), rtol=1e-12)


def test_study_loss_with_jumps_equals_former_reverse_mode(monkeypatch):
    # a step input between grid points (a jump of the exosystem state): study_loss's
    # gradient with the adjoint equals jax.grad through the kernel's own scan
    study, d = small_step_input_study(2, 2, 2)
    dyn, st = eqx.partition(d.observer, eqx.is_inexact_array)

    def vg(loss):
        return jax.jit(jax.value_and_grad(lambda p: S.study_loss(study, eqx.combine(p, st), loss=loss)))(dyn)

    v1, g1 = vg("iae")
    orig = _exact._block_kernel
    monkeypatch.setattr(_exact, "_block_kernel", lambda *a, time_loop=None, **k: orig(*a, **k))
    v0, g0 = vg("iae")
    assert np.isclose(float(v1), float(v0), rtol=1e-13)
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g0)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(b))))


@pytest.mark.parametrize("segment", [None, 1, 4, 5, 11, 20])
def test_split_loop_equals_joint_scan_and_its_gradient_blocks(data, segment):
    # the split loop's value and its gradient w.r.t. Φ_ξξ, Φ_ξp, G, ξ_0 and the observer
    # part of the jumps equal the joint scan's and the matching blocks of jax.grad of the
    # joint scan; every segment layout (a tail of 3 steps at 4, 1 at 5, none at 11, one
    # segment at 20, one step per segment at 1)
    d0, plant, ts, kon = split_data(data)
    (Phi, w0, G, jv, _), _ = data
    Phi = Phi.at[:M, M:].set(0.0)

    def scalar1(acc, xi_end):
        s1, s2, s3, peak, _ = acc
        return jnp.sum(s1) + 0.7 * jnp.sum(s2) - 0.3 * jnp.sum(s3) + 0.2 * jnp.sum(peak) + jnp.sum(jnp.sin(xi_end))

    def split(d):
        acc, p_end, xi_end = split_recurrence_reduce(d + (ts,), plant, PROB, kon, segment)
        return scalar1(acc, xi_end), p_end

    def joint(Phi_, w0_, G_, jv_):
        acc, w = plain((Phi_, w0_, G_, jv_, ts), kon)
        return scalar1(acc, w[M:]), w[:M]

    (v, p_end), g = jax.jit(jax.value_and_grad(split, has_aux=True))(d0)
    (v0, p0_end), (gP, gw, gG, gj) = jax.value_and_grad(joint, argnums=(0, 1, 2, 3), has_aux=True)(Phi, w0, G, jv)
    np.testing.assert_allclose(v, v0, rtol=1e-13)
    np.testing.assert_allclose(p_end, p0_end, rtol=1e-13)
    want = (gP[M:, M:], gP[M:, :M], gG[:, M:], gG[:, :M], gw[M:], gj[:, M:])
    for a, b in zip(g, want):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12 * float(jnp.max(jnp.abs(b))))


class _Sums(eqx.Module):
    """IAE, ISE and ITAE sums: ``update`` adds a function of ``(o, k, ts)``; with `additive`
    the adjoint takes the outputs' cotangents of a whole segment at once."""

    additive: bool = eqx.field(static=True)

    def init(self, o0):
        return (jnp.zeros_like(o0),) * 3

    def update(self, acc, o, k, ts):
        a = jnp.abs(o)
        return acc[0] + a, acc[1] + o * o, acc[2] + (ts[k] - ts[0]) * a


@pytest.mark.parametrize("segment", [None, 4])
def test_additive_adjoint_equals_generic_and_plain_scan(data, segment):
    # issue 13: the additive fast path (LossProblem: ō of a whole segment at once, the
    # scan carrying only λ) against the generic per-step VJP and jax.grad of a plain scan
    # of the same sums (oracle 1), with the grid ts differentiated too (its cotangent is
    # only formed when ts is perturbed) and without it
    d0, plant, ts, kon = split_data(data)

    def scalar(d, ts, additive):
        (s1, s2, s3), _, xi_end = split_recurrence_reduce(d + (ts,), plant, _Sums(additive), kon, segment)
        return jnp.sum(s1) + 0.7 * jnp.sum(s2) - 0.3 * jnp.sum(s3) + jnp.sum(jnp.sin(xi_end))

    def oracle(d, ts):
        Poo, Pop, Go, Gp, xi0, jvo = d
        Ppp, p0, jvp = plant

        def step(c, k):
            p, xi, acc = c
            hit = (kon == k).astype(p.dtype)
            pn = jnp.einsum("ijb,jb->ib", Ppp, p) + jnp.einsum("jb,jib->ib", hit, jvp)
            xn = jnp.einsum("ijb,jb->ib", Poo, xi) + jnp.einsum("ijb,jb->ib", Pop, p) + jnp.einsum("jb,jib->ib", hit, jvo)
            return (pn, xn, _Sums(False).update(acc, jnp.einsum("kib,ib->kb", Go, xn) + jnp.einsum("kib,ib->kb", Gp, pn),
                                                k, ts)), None

        (_, xi_end, (s1, s2, s3)), _ = jax.lax.scan(step, (p0, xi0, (jnp.zeros((K, B)),) * 3), jnp.arange(1, T))
        return jnp.sum(s1) + 0.7 * jnp.sum(s2) - 0.3 * jnp.sum(s3) + jnp.sum(jnp.sin(xi_end))

    want_v, want_g = jax.value_and_grad(oracle, argnums=(0, 1))(d0, ts)
    for additive in (True, False):
        v, g = jax.jit(jax.value_and_grad(lambda d, t, a=additive: scalar(d, t, a), argnums=(0, 1)))(d0, ts)
        assert np.isclose(float(v), float(want_v), rtol=1e-13)
        for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(want_g)):
            np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13 * max(1.0, float(jnp.max(jnp.abs(b)))))
        gd = jax.jit(jax.grad(lambda d, a=additive: scalar(d, ts, a)))(d0)  # ts not differentiated
        for a, b in zip(jax.tree.leaves(gd), jax.tree.leaves(want_g[0])):
            np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13 * max(1.0, float(jnp.max(jnp.abs(b)))))


# ==================================================================================================
# The exact kernel's loss loop in passes of S grid steps
# (`fojax.studies._adjoint.pass_recurrence_reduce`).
# ==================================================================================================


PASSES_M, Q, PASSES_K, PASSES_B = 3, 4, 2, 3  # plant states, observer states, outputs, samples


class _Loss(eqx.Module):
    """The additive reduction of `study_loss` (`LossProblem`): ISE, smooth."""

    additive = True

    def init(self, o0):
        return jnp.zeros_like(o0)

    def update(self, acc, o, k, ts):
        return acc + o * o


@pytest.fixture(scope="module")
def data_passes():
    k = jax.random.split(jax.random.PRNGKey(7), 7)
    Ppp = 0.9 * jnp.eye(PASSES_M)[:, :, None] + 0.05 * jax.random.normal(k[0], (PASSES_M, PASSES_M, PASSES_B))
    Poo = 0.8 * jnp.eye(Q)[:, :, None] + 0.05 * jax.random.normal(k[1], (Q, Q, PASSES_B))
    Pop = 0.1 * jax.random.normal(k[2], (Q, PASSES_M, PASSES_B))
    Go = jax.random.normal(k[3], (PASSES_K, Q, PASSES_B))
    Gp = jax.random.normal(k[4], (PASSES_K, PASSES_M, PASSES_B))
    xi0 = jax.random.normal(k[5], (Q, PASSES_B))
    p0 = jax.random.normal(k[6], (PASSES_M, PASSES_B))
    return (Poo, Pop, Go, Gp, xi0), (Ppp, p0)


def _scalar(acc, p_end, xi_end):
    return jnp.sum(acc * jnp.arange(1.0, PASSES_K + 1)[:, None]) + jnp.sum(jnp.sin(xi_end)) + jnp.sum(p_end)


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

    (p, xi, acc), _ = jax.lax.scan(step, (p0, xi0, jnp.zeros((PASSES_K, PASSES_B))), None, length=T - 1)
    return _scalar(acc, p, xi)


def test_pass_length():
    assert [_adjoint.pass_length(n) for n in (1000, 999, 20, 8, 4, 3, 2)] == [8, 1, 4, 4, 2, 1, 1]


@pytest.mark.parametrize("T, segment", [(33, None), (33, 2)])
def test_passes_equal_plain_scan_and_its_gradient(data_passes, T, segment):
    d, plant = data_passes
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


def test_passes_refuse_jumps_and_non_dividing_grids(data_passes):
    d, plant = data_passes
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
