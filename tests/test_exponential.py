"""`fojax.simulation.simulate_batch_exponential`: batched ETDRK4 for time-varying linear loops.

The test loop is the thesis §4.1.3 plant under state feedback with a *time-varying*
uncertainty δ(t) = a sin(ωt + φ) on entries (1,3), (2,2) of A, a sinusoidal input u(t),
a constant fault that also enters the algebraic equation (so the algebraic state has a
feedthrough from the fault), and an LTI observer driven by y. The independent reference
eliminates x4 by hand from the algebraic row and integrates the 5-state ODE with SciPy's
DOP853 (rtol 1e-12, atol 1e-14); the metrics are the trapezoid rule on the grid.
"""

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from closed_loop_413 import (  # the §4.1.3 loop shared with test_batch_simulation.py
    ACL,
    AO,
    B0,
    BY,
    C0,
    DA,
    E,
    LTIObserver,
    ME,
    METRICS_NP,
    MX,
    X0,
)

import fojax
from fojax.plant import FaultyPlant
from fojax.simulation import simulate_batch_exponential, simulate_lti_batch

# private: the exponential kernel's set-up and TRACE_COUNTS
from fojax.simulation._exponential_setup import _ModelSetup, prepare, TRACE_COUNTS


# bit-for-bit equality of different programs (device counts): compiled as users get it
pytestmark = pytest.mark.production_codegen


FA = np.array([[0.3], [0.0], [-0.2], [0.5]])  # row 4: the fault enters the algebraic equation
TS = np.linspace(0.0, 2.0, 51)  # grid 0.04 s
B = 5
METRICS = {k: (kind, jnp.asarray(C)) for k, (kind, C) in METRICS_NP.items()}


def _observer(p):
    return LTIObserver(jnp.asarray(AO), jnp.asarray(BY), p["xi0"])


def model(p):
    nominal = fojax.DescriptorSystem(
        jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0)
    )
    delta = fojax.Sine(p["a"], p["omega"], p["phase"])
    plant = FaultyPlant(
        fojax.UncertainDescriptorSystem(nominal, dA=jnp.asarray(DA), delta=delta),
        Fa=jnp.asarray(FA),
        fault=fojax.Constant(p["fault"]),
    )
    u = fojax.Sine(p["u_amp"], p["u_omega"], 0.0, p["u_off"])
    return plant, (_observer(p),), u


def sample_params(seed, b=B):
    rng = np.random.default_rng(seed)
    params = dict(
        a=rng.uniform(0.0, 0.3, b),
        omega=rng.uniform(0.5, 5.0, b),
        phase=rng.uniform(0.0, 2 * np.pi, b),
        fault=rng.uniform(-1.0, 1.0, (b, 1)),
        u_amp=rng.uniform(-1.0, 1.0, (b, 2)),
        u_omega=rng.uniform(1.0, 3.0, (b, 2)),
        u_off=rng.uniform(-0.5, 0.5, (b, 2)),
        xi0=rng.normal(size=(b, 2)),
    )
    x0 = X0 * (1 + 0.1 * rng.normal(size=(b, 4)))
    return params, x0


def trapz(f, h):
    return h * (np.sum(f, axis=0) - 0.5 * (f[0] + f[-1]))


def scipy_reference(p, x0, ts=TS):
    """One sample by hand: x4 from the algebraic row, the 5-state ODE [x1..x3; xi], DOP853."""
    d, a = [0, 1, 2], 3

    def matrices(t):
        A = ACL + p["a"] * np.sin(p["omega"] * t + p["phase"]) * DA
        u = p["u_off"] + p["u_amp"] * np.sin(p["u_omega"] * t)
        return A, B0 @ u + FA @ p["fault"]

    def state(t, xd):
        A, c = matrices(t)
        return np.concatenate([xd, [-(A[a, d] @ xd + c[a]) / A[a, a]]])

    def rhs(t, w):
        A, c = matrices(t)
        x = state(t, w[:3])
        return np.concatenate([A[d] @ x + c[d], AO @ w[3:] + BY @ (C0 @ x)])

    sol = scipy.integrate.solve_ivp(
        rhs,
        (ts[0], ts[-1]),
        np.concatenate([x0[:3], p["xi0"]]),
        method="DOP853",
        rtol=1e-12,
        atol=1e-14,
        t_eval=ts,
    )
    assert sol.success
    traj = np.array([np.concatenate([state(t, w[:3]), w[3:]]) for t, w in zip(ts, sol.y.T)])
    h = ts[1] - ts[0]
    ox, oe = traj @ MX.T, traj @ ME.T
    return dict(
        iae_x=trapz(np.abs(ox), h),
        ise_e=trapz(oe**2, h),
        l1=trapz(np.abs(ox).sum(axis=1), h),
        l2=trapz((traj**2).sum(axis=1), h),
    )


def max_rel(out, ref):
    return max(
        float(np.max(np.abs(np.asarray(out[k]) - np.asarray(ref[k])) / np.abs(np.asarray(ref[k]))))
        for k in ref
    )


def run(params, x0, **kw):
    return simulate_batch_exponential(
        model, jax.tree.map(jnp.asarray, params), jnp.asarray(x0), jnp.asarray(TS), metrics=METRICS, **kw
    )


@pytest.fixture(scope="module")
def batch():
    return sample_params(3)


@pytest.fixture(scope="module")
def reference(batch):
    params, x0 = batch
    refs = [scipy_reference({k: v[i] for k, v in params.items()}, x0[i]) for i in range(B)]
    return {k: np.stack([r[k] for r in refs]) for k in METRICS}


@pytest.fixture(scope="module")
def by_substeps(batch):
    params, x0 = batch
    return {s: run(params, x0, substeps=s) for s in (2, 4, 8)}


def test_agrees_with_scipy_reference(by_substeps, reference):
    out = by_substeps[8]  # h = 0.005
    assert out["iae_x"].shape == (B, 4) and out["ise_e"].shape == (B, 2)
    assert out["l1"].shape == (B,) and out["l2"].shape == (B,)
    assert max_rel(out, reference) < 1e-8


def test_time_variation_and_faults_matter(batch, reference, by_substeps):
    # Sanity of the comparison: with δ(t) ≡ 0 and no fault the metrics differ by far more
    # than the tolerance above, so agreement is not an accident of a weak perturbation.
    params, x0 = batch
    p0 = dict(params, a=np.zeros(B), fault=np.zeros((B, 1)))
    out0 = run(p0, x0, substeps=2)
    assert max_rel(out0, reference) > 1e-2


def test_fourth_order_convergence(by_substeps, reference):
    errs = [max_rel(by_substeps[s], reference) for s in (2, 4, 8)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[-1] > 1e-12  # still far above the reference's own error
    assert np.all((orders >= 3.5) & (orders <= 4.5)), (errs, orders)


def test_startup_schedule(batch, by_substeps, reference):
    params, x0 = batch
    # a start-up covering the whole horizon is exactly uniform stepping with its substeps
    whole = run(params, x0, substeps=1, startup=(len(TS) - 1, 4))
    for k in METRICS:
        np.testing.assert_allclose(whole[k], by_substeps[4][k], rtol=1e-14)
    # The error of the coarse schedule is made in the initial layer, where the perturbation
    # excites the fast pole (-39.8): 8 steps per interval over the first 0.12 s make 2 steps
    # per interval ~100x more accurate, and more accurate than 4 everywhere with fewer steps.
    coarse = max_rel(by_substeps[2], reference)
    graded = max_rel(run(params, x0, substeps=2, startup=(3, 8)), reference)
    assert graded < coarse / 20
    assert graded < max_rel(by_substeps[4], reference)  # 118 steps vs 200


def test_no_retrace_for_new_numbers(batch, by_substeps):
    params, x0 = sample_params(11)
    before = dict(TRACE_COUNTS)
    out = run(params, x0, substeps=4)
    assert dict(TRACE_COUNTS) == before
    assert not np.allclose(np.asarray(out["l1"]), np.asarray(by_substeps[4]["l1"]))


def test_plan_exploits_the_structure(batch):
    # δ(t) touches two entries of A: one shared state term reading only 2 of the 5 kept
    # components. The input and the fault only force; the fault also moves the algebraic x4,
    # which the observer measures (y3 = x4), so the forcing writes every row (plant and
    # observer) and x4 has a feedthrough term from the fault.
    params, x0 = batch
    p = jax.tree.map(jnp.asarray, params)
    first = jax.tree.map(lambda a: a[0], p)
    Cs = jnp.concatenate([C for _, C in METRICS.values()], axis=0)
    x0 = jnp.asarray(x0)
    _, plan, _, _, _ = prepare(_ModelSetup(model, Cs), (p, x0), (first, x0[0]), 4096)
    assert len(plan.keep) == 5  # 3 slow plant coordinates + 2 observer states
    assert plan.terms == ((1, "shared"),)  # the δ direction; Ā_k = A0 (common nominal)
    assert len(plan.cols) == 2 and plan.rows == tuple(range(5))
    assert plan.fterms == (0, 2)  # input u (term 0) and the fault (signal index 1 -> term 2)
    assert plan.gterms == ((0, "shared"),) and plan.hterms == (2,)


def test_chunks_blocks_and_padding_do_not_change_results(batch, by_substeps):
    params, x0 = batch
    out = run(params, x0, substeps=4, chunk_size=2, block=1)  # 3 chunks, the last padded
    for k in METRICS:
        np.testing.assert_allclose(out[k], by_substeps[4][k], rtol=1e-13)


def test_device_count_does_not_change_results(batch, by_substeps):
    # conftest forces 4 host devices; the fixture ran on all of them (blocks round-robin)
    params, x0 = batch
    assert jax.device_count() >= 2
    one = run(params, x0, substeps=4, devices=jax.devices()[:1])
    two = run(params, x0, substeps=4, block=1, devices=jax.devices()[:2])
    for k in METRICS:
        np.testing.assert_array_equal(np.asarray(one[k]), np.asarray(by_substeps[4][k]))
        np.testing.assert_allclose(np.asarray(two[k]), np.asarray(by_substeps[4][k]), rtol=1e-13)


def test_traceable_inside_jit(batch, by_substeps):
    params, x0 = batch
    f = jax.jit(lambda p, x: run(p, x, substeps=4))
    out = f(jax.tree.map(jnp.asarray, params), jnp.asarray(x0))
    # the traced path applies every term per sample (no plan): same numbers to round-off
    for k in METRICS:
        np.testing.assert_allclose(out[k], by_substeps[4][k], rtol=1e-12)


# ------------------------------------------------------------------- LTI: exact stepping


def model_lti(p):
    plant = fojax.DescriptorSystem(
        jnp.asarray(E), jnp.asarray(ACL) + p["delta"] * jnp.asarray(DA), jnp.asarray(B0), jnp.asarray(C0)
    )
    return plant, (_observer(p),)


def test_reproduces_simulate_lti_batch(batch):
    _, x0 = batch
    rng = np.random.default_rng(5)
    xi0 = jnp.asarray(rng.normal(size=(B, 2)))
    x0 = jnp.asarray(x0)
    ts = jnp.asarray(TS)
    # (a) every sample has the reference's matrices: g = 0, the method is exact stepping
    same = {"delta": jnp.full((B,), 0.17), "xi0": xi0}
    ref = simulate_lti_batch(model_lti, same, x0, ts, metrics=METRICS)
    out = simulate_batch_exponential(model_lti, same, x0, ts, metrics=METRICS)
    assert max_rel(out, ref) < 1e-12
    # (b) per-sample constant δ_k around the reference δ = 0: g = δ_k ΔA w, ETDRK4 with h = 2 ms
    varied = {"delta": jnp.asarray(rng.uniform(-0.3, 0.3, B)), "xi0": xi0}
    ref = simulate_lti_batch(model_lti, varied, x0, ts, metrics=METRICS)
    zero = {"delta": jnp.asarray(0.0), "xi0": jnp.zeros(2)}
    out = simulate_batch_exponential(model_lti, varied, x0, ts, metrics=METRICS, reference=zero, substeps=20)
    assert max_rel(out, ref) < 1e-10


def model_autonomous(p):
    return fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) + 0.0 * p)


def test_autonomous_common_loop_is_exact_stepping(batch):
    # No signals, no input, the same matrices for every sample: g vanishes identically, the
    # plan has nothing to apply (the kernel only multiplies by e^{hA0}) — exact stepping.
    _, x0 = batch
    metrics = {"x": ("iae", jnp.eye(4)), "l2": ("ise_l2", jnp.eye(4))}
    p = jnp.zeros(B)
    ref = simulate_lti_batch(model_autonomous, p, jnp.asarray(x0), jnp.asarray(TS), metrics=metrics)
    out = simulate_batch_exponential(model_autonomous, p, jnp.asarray(x0), jnp.asarray(TS), metrics=metrics)
    assert max_rel(out, ref) < 1e-12


def test_observer_shapes_are_checked():
    with pytest.raises(fojax.errors.ShapeError, match=r"observers\[0\].linear_matrices\(\).Bu has shape \(2, 2\), expected \(2, 0\)"):
        simulate_batch_exponential(
            lambda q: (fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) * q, C=jnp.asarray(C0)), (_observer({"xi0": jnp.zeros(2)}),)),
            jnp.ones(2),
            jnp.ones((2, 4)),
            jnp.asarray(TS),
            metrics=METRICS,
        )


# ------------------------------------------------------------------- errors


class ClockPlant(fojax.plant.AbstractPlant):
    """Linear in x but with an explicit time dependence (not through a signal)."""

    E: jax.Array
    A: jax.Array
    linear_in_state: ClassVar[bool] = True

    @property
    def m(self):
        return 0

    @property
    def p(self):
        return 2

    def rhs(self, t, x, u):
        return (self.A + jnp.sin(3.0 * t) * jnp.eye(2)) @ x

    def output(self, t, x, u):
        return x


E2 = jnp.diag(jnp.array([1.0, 0.0]))
A2 = jnp.array([[-1.0, 0.5], [1.0, 1.0]])
X2 = jnp.ones((2, 2))
M2 = {"x": ("iae_l1", jnp.eye(2))}
TS2 = jnp.linspace(0.0, 1.0, 11)


def model_clock(p):
    return ClockPlant(E2, A2 * p)


def model_alg_delta(p):
    # δ(t) in the algebraic row: the reduced field is not affine in δ
    nominal = fojax.DescriptorSystem(E2, A2)
    dA = jnp.array([[0.0, 0.0], [0.0, 1.0]])
    return fojax.UncertainDescriptorSystem(nominal, dA=dA, delta=fojax.Sine(0.5, p, 0.0))


@pytest.mark.parametrize(
    "fn, match",
    [(model_clock, r"misses the vector field at t = "), (model_alg_delta, r"random signal values")],
)
def test_non_affine_plants_are_refused(fn, match):
    with pytest.raises(fojax.errors.InputError, match=r"affine in the state and in the values of its signals") as e:
        simulate_batch_exponential(fn, jnp.array([1.0, 2.0]), X2, TS2, metrics=M2)
    assert e.match(match)


def test_input_errors(batch):
    params, x0 = batch
    p = jax.tree.map(jnp.asarray, params)
    x0 = jnp.asarray(x0)
    bad_ts = jnp.asarray(np.r_[0.0, 0.1, 0.25, 0.3])
    with pytest.raises(fojax.errors.InputError, match=r"uniform increasing grid.*jnp.linspace"):
        simulate_batch_exponential(model, p, x0, bad_ts, metrics=METRICS)
    with pytest.raises(fojax.errors.ShapeError, match=r"x0 has shape \(5, 3\), expected \(B, 4\)"):
        simulate_batch_exponential(model, p, x0[:, :3], jnp.asarray(TS), metrics=METRICS)
    with pytest.raises(fojax.errors.ShapeError, match=r"leading batch axis 4"):
        simulate_batch_exponential(model, p, x0[:4], jnp.asarray(TS), metrics=METRICS)
    with pytest.raises(fojax.errors.InputError, match=r"substeps must be a positive integer.*got 0"):
        simulate_batch_exponential(model, p, x0, jnp.asarray(TS), metrics=METRICS, substeps=0)
    with pytest.raises(fojax.errors.InputError, match=r"startup must be a pair \(n_intervals, substeps\)"):
        simulate_batch_exponential(model, p, x0, jnp.asarray(TS), metrics=METRICS, startup=5)
    with pytest.raises(fojax.errors.InputError, match=r"startup\[0\] must be a non-negative integer.*got -1"):
        simulate_batch_exponential(model, p, x0, jnp.asarray(TS), metrics=METRICS, startup=(-1, 2))
    with pytest.raises(fojax.errors.InputError, match=r"reference must be the params of one sample"):
        simulate_batch_exponential(model, p, x0, jnp.asarray(TS), metrics=METRICS, reference=p)
    with pytest.raises(fojax.errors.ShapeError, match=r"metrics\['x'\] C has shape \(4, 5\)"):
        simulate_batch_exponential(model, p, x0, jnp.asarray(TS), metrics={"x": ("iae", jnp.ones((4, 5)))})
    with pytest.raises(fojax.errors.InputError, match=r"must return a fojax.plant.AbstractPlant"):
        simulate_batch_exponential(lambda q: q, p, x0, jnp.asarray(TS), metrics=METRICS)


def test_nonlinear_plants_and_observers_are_refused():
    f = lambda x, u, th: -x + th * x**2  # noqa: E731
    nl = lambda th: fojax.NonlinearDescriptorSystem(E2, f, lambda x, th: x, th, m=0, p=2)  # noqa: E731
    with pytest.raises(fojax.errors.InputError, match=r"linear in the state.*NonlinearDescriptorSystem"):
        simulate_batch_exponential(nl, jnp.array([1.0, 2.0]), X2, TS2, metrics=M2)

    class TVObserver(LTIObserver):
        def linear_matrices(self):
            return None

    def with_tv_observer(p):
        obs = TVObserver(jnp.asarray(AO), jnp.asarray(BY[:, :2]), jnp.zeros(2))
        return fojax.DescriptorSystem(E2, A2 * p), (obs,)

    with pytest.raises(fojax.errors.InputError, match=r"needs LTI observers.*TVObserver"):
        simulate_batch_exponential(with_tv_observer, jnp.array([1.0, 2.0]), X2, TS2, metrics=M2)
