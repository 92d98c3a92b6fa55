"""`fojax.discretize`: zero-order hold of descriptor systems and of designed observers.

Oracles: ``scipy.signal.cont2discrete`` (ZOH of state-space systems, including the
slow subsystem of a descriptor system reduced by hand), ``scipy.linalg.expm``, and the
continuous eigenvalues from ``scipy.linalg.eig`` / ``numpy.linalg.eigvals`` mapped by
``exp(λ h)`` (eigenvalue sets matched one to one, never sorted).
"""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.signal as ss
from helpers import assert_eigenvalues_match

import fojax


H = 0.05
# A continuous model used by no other test: three differential rows, one algebraic row (index 1).
Ec = np.diag([1.0, 1.0, 1.0, 0.0])
Ac = np.array([[-1.0, 0.4, 0.0, 0.0], [0.1, -2.0, 0.5, 0.0], [0.0, 0.3, -0.5, 1.0], [0.5, 0.0, 1.0, 2.0]])
Bc = np.array([[1.0, 0.0], [0.0, 0.0], [0.5, 1.0], [1.0, -1.0]])
Cc = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
Lc = np.array([[0.0, 1.0, 1.0, 0.0]])


def reduced():
    """The slow subsystem by hand: x4 = -(A[3, :3] x1 + B[3] u) / A[3, 3]."""
    k = Ac[:3, 3:] / Ac[3, 3]
    As = Ac[:3, :3] - k @ Ac[3:, :3]
    Bs = Bc[:3] - k @ Bc[3:]
    return As, Bs


def oracle_samples(x1_0, us):
    As, Bs = reduced()
    Phi, Gam, *_ = ss.cont2discrete((As, Bs, np.eye(3), np.zeros((3, 2))), H, method="zoh")
    xs, x1 = [], np.asarray(x1_0, float)
    for u in us:
        x4 = -(Ac[3, :3] @ x1 + Bc[3] @ u) / Ac[3, 3]
        xs.append(np.r_[x1, x4])
        x1 = Phi @ x1 + Gam @ u
    return np.array(xs)


def test_state_space_matches_cont2discrete():
    rng = np.random.default_rng(3)
    A, B, C = rng.normal(size=(3, 3)), rng.normal(size=(3, 2)), rng.normal(size=(1, 3))
    d = fojax.discretize(fojax.DescriptorSystem.from_state_space(A, B, C), 0.2)
    Ad, Bd, Cd, _, _ = ss.cont2discrete((A, B, C, np.zeros((1, 2))), 0.2, method="zoh")
    assert d.dt == 0.2
    np.testing.assert_allclose(d.E, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(d.A, Ad, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(d.B, Bd, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(d.C, Cd)


@pytest.mark.parametrize("transform", [False, True])
def test_descriptor_zoh_is_exact_at_the_samples(transform):
    rng = np.random.default_rng(11)
    P, Q = (np.eye(4), np.eye(4)) if not transform else (rng.normal(size=(4, 4)), rng.normal(size=(4, 4)))
    sys_c = fojax.DescriptorSystem(P @ Ec @ Q, P @ Ac @ Q, P @ Bc, Cc @ Q)
    d = fojax.discretize(sys_c, H)
    assert d.dt == H
    us = np.stack([np.sin(0.7 * np.arange(40)), np.cos(0.3 * np.arange(40))], axis=1)
    xs = oracle_samples([1.0, -0.5, 0.3], us) @ np.linalg.inv(Q).T  # x' = Q^{-1} x
    Ed, Ad, Bd = (np.asarray(M) for M in (d.E, d.A, d.B))
    res = [Ed @ xs[k + 1] - Ad @ xs[k] - Bd @ us[k] for k in range(len(us) - 1)]
    assert np.max(np.abs(res)) < 1e-10 * np.max(np.abs(xs))
    # the discrete model is regular and causal, and its poles are exp(λ h)
    lam = np.linalg.eigvals(reduced()[0])
    assert fojax.analysis.is_causal(d)
    assert_eigenvalues_match(fojax.analysis.finite_poles(d), np.exp(lam * H), rtol=1e-8)
    # and simulate steps the samples the oracle gives
    sig = fojax.PiecewiseConstant(H * np.arange(1, 40), us)
    sol = fojax.simulate(d, xs[0], H * jnp.arange(40), sig)
    np.testing.assert_allclose(sol.xs, xs, rtol=1e-9, atol=1e-10 * np.max(np.abs(xs)))


def _design():
    return fojax.design_functional_observer(fojax.DescriptorSystem(Ec, Ac, Bc, Cc), Lc, kind="generalized")


def test_observer_zoh_eigenvalues_are_exp_lambda_h():
    des = _design()
    obs_d = fojax.discretize(des, H)
    assert obs_d.dt == H and des.observer.dt is None
    Aa = np.asarray(des.observer.error_matrix)
    lam = np.linalg.eigvals(Aa)
    assert_eigenvalues_match(np.linalg.eigvals(np.asarray(obs_d.error_matrix)), np.exp(lam * H), rtol=1e-8)
    np.testing.assert_allclose(obs_d.N, sla.expm(Aa * H), rtol=1e-12, atol=1e-14)
    # its realisation is the ZOH (u and y held) of the continuous realisation
    c, dm = des.observer.linear_matrices(), obs_d.linear_matrices()
    Bcat = np.hstack([np.asarray(c.Bu), np.asarray(c.By)])
    Dcat = np.hstack([np.asarray(c.Du), np.asarray(c.Dy)])
    Ad, Bd, Cd, Dd, _ = ss.cont2discrete((np.asarray(c.A), Bcat, np.asarray(c.C), Dcat), H, method="zoh")
    scale = np.max(np.abs(Bd))
    np.testing.assert_allclose(dm.A, Ad, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.hstack([dm.Bu, dm.By]), Bd, rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(dm.C, Cd)
    np.testing.assert_allclose(np.hstack([dm.Du, dm.Dy]), Dd)
    # the observer itself is accepted as well as the design
    np.testing.assert_allclose(fojax.discretize(des.observer, H).N, obs_d.N)


def test_design_on_the_discretized_model_converges():
    d = fojax.discretize(fojax.DescriptorSystem(Ec, Ac, Bc, Cc), H)
    des = fojax.design_functional_observer(d, Lc, kind="proportional", method="riccati",
                                           region=fojax.design.DiscreteDisk(0.5, 0.4))
    assert des.dt == H and des.report.passed
    ts = H * jnp.arange(200)
    x0 = oracle_samples([1.0, -0.5, 0.3], np.zeros((1, 2)))[0]
    sol = fojax.simulate(d, x0, ts, jnp.array([0.3, -0.1]), observers=des.observer)
    err = np.asarray(sol.estimates[0])[:, 0] - np.asarray(sol.xs) @ Lc[0]
    assert abs(err[0]) > 0.1 and np.max(np.abs(err[-5:])) < 1e-8


def test_errors():
    impulsive = fojax.DescriptorSystem(np.array([[0.0, 1.0], [0.0, 0.0]]), np.eye(2))
    with pytest.raises(fojax.errors.ImpulsiveSystemError, match="impulsive"):
        fojax.discretize(impulsive, 0.1)
    with pytest.raises(fojax.errors.IrregularSystemError):
        fojax.discretize(fojax.DescriptorSystem(np.zeros((2, 2)), np.array([[1.0, 0.0], [0.0, 0.0]])), 0.1)
    sys_c = fojax.DescriptorSystem(Ec, Ac, Bc, Cc)
    for bad in (0.0, -1.0, None):
        with pytest.raises(fojax.errors.InputError, match="dt"):
            fojax.discretize(sys_c, bad)
    with pytest.raises(fojax.errors.InputError, match="method"):
        fojax.discretize(sys_c, 0.1, method="tustin")
    with pytest.raises(fojax.errors.InputError, match="already discrete-time"):
        fojax.discretize(fojax.discretize(sys_c, 0.1), 0.1)
    with pytest.raises(fojax.errors.InputError, match="expected a fojax.DescriptorSystem"):
        fojax.discretize("plant", 0.1)
