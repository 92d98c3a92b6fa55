"""`study_loss` on exact loops without jumps: the observers' part of a step computed once per
call (`fojax.studies._exact.coupling_factors`), per sample only what the observers do not
reach (`_coupled_block`, `fojax.studies._adjoint.shared_recurrence_reduce`).

Oracles: (1) SciPy: `scipy.linalg.expm` of each sample's joint loop matrix ``h 𝒜`` (the
joint of plant, exosystem and the real observer, `StudyProblem.joint`) and a NumPy
recurrence on the grid with the trapezoid rule: the loss (IAE and ISE) to ≤ 1e-10
relative, and the coupling block ``X`` and ``e^{hN}`` against the blocks of that
exponential; (2) central finite differences of the ISE loss (its gradient under `jax.grad`); (3)
new numbers (observer, δ and fault samples) reuse the compiled loss and gradient. The
joint path (one differentiable exponential of the whole loop per sample, still used for
loops with jumps) is covered by ``test_study_loss_blocks.py``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk
from fojax.studies import _exact


def _study(seed, n_delta=3, n_faults=2):
    """The short §3.3.7 study of ``tests/helpers.small_step_input_study`` with a sine input
    (an exosystem with rotation, no jump on the grid) instead of a step."""
    ex = fojax.models.example_3_3_7()
    dA = np.zeros((1, 9, 9))
    dA[0, :6, :6] = ex.dA
    plant = fojax.UncertainDescriptorSystem(ex.augmented, dA=dA, delta=fojax.Constant(jnp.zeros(1)))
    x0 = jnp.zeros(9).at[:6].set(0.5)
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    u = fojax.Sine(jnp.array([0.4, -0.3]), jnp.array([3.0, 5.0]), phase=0.2, offset=0.1)
    return S.Study(plant, x0, jnp.linspace(0.0, 1.0, 21), ex.L_aug, u,
                   uncertainty=(S.constant_delta(k1, n_delta, 1, bounds=(-0.3, 0.3)),),
                   scenarios=(S.constant_faults(k2, n_faults, x0, 3),))


@pytest.fixture(scope="module")
def case():
    ex = fojax.models.example_3_3_7()
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    study = _study(3)
    dyn, st = eqx.partition(d.observer, eqx.is_inexact_array)
    return study, d.observer, dyn, st


def _peer_losses(study, observer):
    """SciPy/NumPy: per sample the joint matrix, its exponential, the outputs on the grid and
    their trapezoid IAE / ISE, averaged over signals and samples."""
    E0 = _exact._unwrap(study.sample(0, 0)[0])[0].E
    pr = _exact.StudyProblem(study, (observer,), _exact.svd_split(E0), E0, jnp.asarray(0.05), None)
    ts = np.asarray(study.ts)
    h = (ts[-1] - ts[0]) / (len(ts) - 1)
    iae, ise = [], []
    for k in range(study.num_samples):
        Aj, w0, G, ok, jumps = pr.joint((jnp.asarray(k // study.num_scenarios), jnp.asarray(k % study.num_scenarios)))
        assert jumps is None and bool(ok)
        Phi = scipy.linalg.expm(h * np.asarray(Aj))
        w, out = np.asarray(w0), []
        for _ in range(len(ts)):
            out.append(np.asarray(G) @ w)
            w = Phi @ w
        o = np.array(out)  # (T, K)
        trap = lambda f: h * (f.sum(axis=0) - 0.5 * f[0] - 0.5 * f[-1])  # noqa: E731
        iae.append(np.mean(trap(np.abs(o))))
        ise.append(np.mean(trap(o * o)))
    return float(np.mean(iae)), float(np.mean(ise))


def _loss(study, st, loss):
    return eqx.filter_jit(lambda p, s: S.study_loss(s, eqx.combine(p, st), loss=loss))


def test_coupling_blocks_equal_scipy_expm_of_the_joint(case):
    study, observer, _, _ = case
    E0 = _exact._unwrap(study.sample(0, 0)[0])[0].E
    pr = _exact.StudyProblem(study, (observer,), _exact.svd_split(E0), E0, jnp.asarray(0.05), None)
    h = 0.05
    Aj = np.asarray(pr.joint((jnp.asarray(1), jnp.asarray(1)))[0])
    n, q = 9, observer.state_size
    Phi = scipy.linalg.expm(h * Aj)
    Phi_oo, Psi, _, _, _ = eqx.filter_jit(_exact.coupling_factors)((observer,), h)
    np.testing.assert_allclose(Phi_oo, Phi[n : n + q, n : n + q], rtol=0, atol=1e-14)
    # X = Ψ [Y (hA_p)^i]_i with A_p, Y read from 𝒜 (observer rows = [By, Bu] Y)
    keep = np.r_[0:n, n + q : Aj.shape[0]]
    Ap = Aj[np.ix_(keep, keep)]
    lm = observer.linear_matrices()
    Bt = np.concatenate([lm.By, lm.Bu], axis=1)
    Y = np.linalg.lstsq(Bt, Aj[np.ix_(np.r_[n : n + q], keep)], rcond=None)[0]
    assert np.allclose(Bt @ Y, Aj[np.ix_(np.r_[n : n + q], keep)], atol=1e-12)
    M = np.concatenate([Y @ np.linalg.matrix_power(h * Ap, i) for i in range(_exact.COUPLING_TERMS)], axis=0)
    X = np.asarray(Psi) @ M
    want = Phi[np.ix_(np.r_[n : n + q], keep)]
    np.testing.assert_allclose(X, want, rtol=0, atol=1e-13 * np.max(np.abs(want)))


def test_loss_equals_scipy_peer_gradient_central_differences_no_retrace(case):
    study, observer, dyn, st = case
    peer_iae, peer_ise = _peer_losses(study, observer)
    v_iae = float(_loss(study, st, "iae")(dyn, study))
    assert abs(v_iae - peer_iae) <= 1e-10 * peer_iae, (v_iae, peer_iae)
    f = _loss(study, st, "ise")
    v_ise = float(f(dyn, study))
    assert abs(v_ise - peer_ise) <= 1e-10 * peer_ise, (v_ise, peer_ise)
    vg = eqx.filter_jit(eqx.filter_value_and_grad(lambda p, s: S.study_loss(s, eqx.combine(p, st), loss="ise")))
    v, g = vg(dyn, study)
    assert abs(float(v) - v_ise) <= 1e-13 * v_ise  # grad does not change the value
    leaves = jax.tree.leaves(dyn)
    keys = jax.random.split(jax.random.PRNGKey(7), len(leaves))
    d = jax.tree.unflatten(jax.tree.structure(dyn), [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])
    an = float(sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d))))
    eps = 1e-5
    fd = (float(f(jax.tree.map(lambda a, b: a + eps * b, dyn, d), study))
          - float(f(jax.tree.map(lambda a, b: a - eps * b, dyn, d), study))) / (2 * eps)
    assert abs(an - fd) <= 1e-6 * abs(fd), (an, fd)
    # new numbers (another observer, other δ and fault samples) reuse the compiled loss and gradient
    before = _exact.TRACE_COUNTS["study_loss_exact"]
    other = _study(11)
    f(jax.tree.map(lambda a, b: a + 1e-3 * b, dyn, d), other)
    vg(jax.tree.map(lambda a, b: a + 1e-3 * b, dyn, d), other)
    assert _exact.TRACE_COUNTS["study_loss_exact"] == before


def test_samples_beyond_the_series_range_are_flagged_not_wrong(case):
    # ‖h A_p‖₁ > COUPLING_MAX_NORM (a grid step of 1 s here): the sample is NaN, never a
    # truncated series
    study, observer, dyn, st = case
    coarse = eqx.tree_at(lambda s: s.ts, study, jnp.linspace(0.0, 20.0, 21))
    mets, ok = eqx.filter_jit(_exact.sample_metrics_traced)(coarse, (observer,), 0.05, metric="iae")
    assert not bool(jnp.any(ok)) and bool(jnp.all(jnp.isnan(mets)))


def test_badly_scaled_states_stay_in_the_series_range():
    # regression: the same plant with states scaled by (1e3, 1e-3, 1) has ‖h A_p‖₁ ≈ 1e5; the
    # series runs on the balanced A_p, so the loss is finite and equals the plain model's
    # (z = L x is the same signal): before the balancing every sample was flagged (NaN) and
    # test_tunable's whitened-twin tuning failed
    A = np.array([[-1.0, 0.0, 0.0], [1.0, -2.0, 0.0], [0.0, 1.0, -3.0]])
    B, C, L = np.array([[1.0], [0.0], [0.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    ts, u = jnp.linspace(0.0, 3.0, 31), fojax.Sine(jnp.array([1.0]), 1.0)
    vals = []
    for Dx in (np.ones(3), np.array([1e3, 1e-3, 1.0])):
        D = np.diag(Dx)
        sysm = fojax.DescriptorSystem(D, A @ D, B, C @ D)
        d = design_functional_observer(fojax.DescriptorSystem(np.eye(3), A, B, C), L, kind="generalized", q1=1,
                                       region=Disk(-2.0, 1.0), R=L)
        study = S.Study(sysm, jnp.asarray(np.array([1.0, -1.0, 0.5]) / Dx), ts, L @ D, u)
        vals.append(float(eqx.filter_jit(S.study_loss)(study, d.observer)))
    assert np.isfinite(vals[1]) and abs(vals[1] - vals[0]) <= 1e-9 * vals[0], vals
