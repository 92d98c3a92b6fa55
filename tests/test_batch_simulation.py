"""`fojax.simulation.simulate_lti_batch`: exact batched LTI stepping with in-scan metrics.

Checked against (1) `jax.vmap(fojax.simulate)` trajectories integrated on the host and
(2) an independent SciPy recurrence (index partition of the diagonal E by hand,
`scipy.linalg.expm`, trapezoid rule), on the thesis §4.1.3 closed loop with a parameter
perturbation and an LTI observer driven by y.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from closed_loop_413 import (  # the §4.1.3 loop shared with test_exponential.py
    ACL,
    AO,
    B0,
    BY,
    C0,
    DA,
    E,
    LTIObserver,
    ME,
    METRICS_NP as METRICS,
    MX,
    X0,
)
from helpers import count_equations

import fojax
from fojax.simulation import simulate_lti_batch

# private: TRACE_COUNTS, the no-retrace check, and the kernel's parts
from fojax.simulation._batch import TRACE_COUNTS


# bit-for-bit equality of different programs (chunks, blocks and device counts): compiled as users get it
pytestmark = pytest.mark.production_codegen


TS = np.linspace(0.0, 4.0, 401)
B = 7


def model(p):
    plant = fojax.DescriptorSystem(
        jnp.asarray(E),
        jnp.asarray(ACL) + p["delta"] * jnp.asarray(DA),
        jnp.asarray(B0),
        jnp.asarray(C0),
    )
    return plant, (LTIObserver(jnp.asarray(AO), jnp.asarray(BY), p["xi0"]),)


def sample_params(seed, b=B):
    rng = np.random.default_rng(seed)
    params = {"delta": rng.uniform(-0.3, 0.3, b), "xi0": rng.normal(size=(b, 2))}
    x0 = X0 * (1 + 0.1 * rng.normal(size=(b, 4)))
    return params, x0


def trapz(f, h):
    return h * (np.sum(f, axis=0) - 0.5 * (f[0] + f[-1]))


def host_metrics(traj, h):
    """``(T, 6)`` joint trajectory -> the METRICS dict for one sample."""
    ox, oe = traj @ MX.T, traj @ ME.T
    return {
        "iae_x": trapz(np.abs(ox), h),
        "ise_e": trapz(oe**2, h),
        "l1": trapz(np.sum(np.abs(ox), axis=1), h),
        "l2": trapz(np.sum(traj**2, axis=1), h),
    }


def scipy_reference(delta, xi0, x0, e=1.0):
    """Hand index partition (x4 algebraic), joint ODE, scipy expm recurrence.

    `e`: the plant with E = diag(e, 1, 1, 0), i.e. the first row of A + δΔA divided by e."""
    A = ACL + delta * DA
    A[0] /= e
    d, a = [0, 1, 2], [3]
    K = -np.linalg.solve(A[np.ix_(a, a)], A[np.ix_(a, d)])  # x4 = K xd
    As = A[np.ix_(d, d)] + A[np.ix_(d, a)] @ K
    Tx = np.zeros((4, 3))
    Tx[d, :] = np.eye(3)
    Tx[a, :] = K
    Aj = np.block([[As, np.zeros((3, 2))], [BY @ C0 @ Tx, AO]])
    h = TS[1] - TS[0]
    Phi = scipy.linalg.expm(h * Aj)
    w = np.concatenate([x0[:3], xi0])
    ws = [w]
    for _ in range(len(TS) - 1):
        w = Phi @ w
        ws.append(w)
    ws = np.array(ws)
    traj = np.hstack([ws[:, :3] @ Tx.T, ws[:, 3:]])
    return host_metrics(traj, h)


def rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.abs(b)))


@pytest.fixture(scope="module")
def batch_result():
    params, x0 = sample_params(0)
    before = TRACE_COUNTS["simulate_lti_batch"]
    out = simulate_lti_batch(model, params, x0, TS, metrics=METRICS, chunk_size=B)
    return (
        params,
        x0,
        {k: np.asarray(v) for k, v in out.items()},
        TRACE_COUNTS["simulate_lti_batch"] - before,
    )


def test_shapes(batch_result):
    _, _, out, _ = batch_result
    assert out["iae_x"].shape == (B, 4)
    assert out["ise_e"].shape == (B, 2)
    assert out["l1"].shape == (B,)
    assert out["l2"].shape == (B,)


def test_matches_independent_scipy_recurrence(batch_result):
    params, x0, out, _ = batch_result
    for k in range(3):
        ref = scipy_reference(params["delta"][k], params["xi0"][k], x0[k])
        for name in METRICS:
            assert rel(out[name][k], ref[name]) <= 1e-10, name


def test_matches_vmapped_simulate(batch_result):
    params, x0, out, _ = batch_result
    ks = slice(0, 3)

    def one(p, x):
        plant, obs = model(p)
        sol = fojax.simulate(plant, x, jnp.asarray(TS), observers=obs, observer_x0=(p["xi0"],))
        return jnp.concatenate([sol.xs, sol.observer_states[0]], axis=1)

    trajs = np.asarray(
        jax.vmap(one)(jax.tree.map(lambda a: jnp.asarray(a[ks]), params), jnp.asarray(x0[ks]))
    )
    h = TS[1] - TS[0]
    for k in range(3):
        ref = host_metrics(trajs[k], h)
        for name in METRICS:
            assert rel(out[name][k], ref[name]) <= 1e-10, name


def test_second_call_with_new_numbers_does_not_retrace(batch_result):
    _, _, _, traces = batch_result
    assert traces == 1
    params, x0 = sample_params(1)
    before = TRACE_COUNTS["simulate_lti_batch"]
    simulate_lti_batch(model, params, x0, TS + 1.0, metrics=METRICS, chunk_size=B)
    assert TRACE_COUNTS["simulate_lti_batch"] == before


def test_chunked_equals_unchunked_exactly(batch_result):
    params, x0, out, _ = batch_result
    before = TRACE_COUNTS["simulate_lti_batch"]
    chunked = simulate_lti_batch(
        model, params, x0, TS, metrics=METRICS, chunk_size=3
    )  # 3 + 3 + 1 (padded)
    assert TRACE_COUNTS["simulate_lti_batch"] == before + 1  # one kernel for all chunks
    blocked = simulate_lti_batch(model, params, x0, TS, metrics=METRICS, chunk_size=B, block=2)
    for name in METRICS:
        np.testing.assert_array_equal(np.asarray(chunked[name]), out[name])
        np.testing.assert_array_equal(np.asarray(blocked[name]), out[name])


def test_traceable_inside_jit(batch_result):
    params, x0, out, _ = batch_result

    @jax.jit
    def study(p, x):
        return simulate_lti_batch(model, p, x, jnp.asarray(TS), metrics=METRICS, chunk_size=3)

    res = study(jax.tree.map(jnp.asarray, params), jnp.asarray(x0))
    for name in METRICS:
        np.testing.assert_allclose(np.asarray(res[name]), out[name], rtol=1e-13)


def test_vmapped_simulate_traceable_inside_jit(batch_result):
    # `simulate`'s method resolution inspects a concrete ts with NumPy (no float() of a tracer).
    params, x0, _, _ = batch_result
    ts = jnp.asarray(TS)  # a concrete jax.Array closed over by the jitted function

    @jax.jit
    def first_states(p, x):
        def one(pk, xk):
            plant, obs = model(pk)
            return fojax.simulate(plant, xk, ts).xs[-1]

        return jax.vmap(one)(p, x)

    p2 = jax.tree.map(lambda a: jnp.asarray(a[:2]), params)
    got = first_states(p2, jnp.asarray(x0[:2]))
    plant, _ = model(jax.tree.map(lambda a: a[0], p2))
    ref = fojax.simulate(plant, jnp.asarray(x0[0]), jnp.asarray(TS)).xs[-1]
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(ref), rtol=1e-12, atol=1e-14)


def test_refuses_bad_inputs(batch_result):
    params, x0, _, _ = batch_result
    with pytest.raises(fojax.errors.InputError, match="uniform"):
        simulate_lti_batch(model, params, x0, TS**2, metrics=METRICS)
    with pytest.raises(fojax.errors.InputError, match="kind in"):
        simulate_lti_batch(model, params, x0, TS, metrics={"a": ("peak", MX)})
    with pytest.raises(fojax.errors.ShapeError, match="metrics"):
        simulate_lti_batch(model, params, x0, TS, metrics={"a": ("iae", MX[:, :4])})

    def nonlinear(p):
        f = lambda x, u, th: jnp.asarray(ACL) @ x  # noqa: E731
        return fojax.NonlinearDescriptorSystem(jnp.asarray(E), f, lambda x, th: x[:3], {}, m=2, p=3)

    with pytest.raises(fojax.errors.InputError, match="linear time-invariant"):
        simulate_lti_batch(nonlinear, params, x0, TS, metrics={"a": ("iae", np.eye(4))})


def test_output_coordinates_path_matches_scipy(batch_result):
    # Few metric rows (K = 6 <= N = 5 + ... here: |x| (4 rows, rank 3 since x4 is algebraic) and
    # y - xi (2 rows)): the kernel steps in output coordinates; check against SciPy.
    params, x0, out, _ = batch_result
    few = {"iae_x": ("iae", MX), "ise_e": ("ise", ME)}
    # private: tested itself
    from fojax.simulation._batch import _output_basis

    # the path is really taken: rows 0, 1, 2 of |x| and both error rows are independent
    A = ACL + params["delta"][0] * DA
    Tx = np.vstack([np.eye(3), -A[3:, :3] / A[3, 3]])  # x = Tx x_d (hand index partition)
    out_map = scipy.linalg.block_diag(Tx, np.eye(2))  # (6, 5): joint state from [x_d; xi]
    ind, Nc = _output_basis(np.vstack([MX, ME]) @ out_map)
    assert len(ind) == 5 and Nc.shape == (0, 5)  # 5 independent outputs span the 5 states
    got = simulate_lti_batch(model, params, x0, TS, metrics=few, chunk_size=B)
    for k in range(B):
        ref = scipy_reference(params["delta"][k], params["xi0"][k], x0[k])
        np.testing.assert_allclose(np.asarray(got["iae_x"][k]), ref["iae_x"], rtol=1e-10)
        np.testing.assert_allclose(np.asarray(got["ise_e"][k]), ref["ise_e"], rtol=1e-10)


def test_independent_of_device_count_and_block(batch_result):
    # conftest forces 4 host devices: the default spreads blocks over all of them
    params, x0, out, _ = batch_result
    assert jax.device_count() >= 2
    one = simulate_lti_batch(model, params, x0, TS, metrics=METRICS, chunk_size=B, devices=jax.devices()[:1])
    two = simulate_lti_batch(model, params, x0, TS, metrics=METRICS, chunk_size=5, block=1,
                             devices=jax.devices()[:2])
    for name in METRICS:
        np.testing.assert_array_equal(np.asarray(one[name]), out[name])
        np.testing.assert_array_equal(np.asarray(two[name]), out[name])


def model_scaled_E(p):
    # E_k = diag(e_k, 1, 1, 0): every sample has its own E (no shared SVD split)
    plant = fojax.DescriptorSystem(
        jnp.diag(jnp.stack([p["e"], 1.0, 1.0, p["e4"]])),
        jnp.asarray(ACL) + p["delta"] * jnp.asarray(DA),
        jnp.asarray(B0),
        jnp.asarray(C0),
    )
    return plant, (LTIObserver(jnp.asarray(AO), jnp.asarray(BY), p["xi0"]),)


def test_per_sample_E_matches_scipy_and_rank_change_gives_nan(batch_result):
    # E_k = diag(e_k, 1, 1, 0): dividing the first equation by e_k gives the plant with E
    # and A's first row scaled by 1/e_k, which the independent SciPy reference uses.
    params, x0, _, _ = batch_result
    rng = np.random.default_rng(5)
    e = rng.uniform(0.5, 2.0, B)
    e4 = np.zeros(B)
    e4[-1] = 1.0  # the last sample has rank E = 4, not 3: its metrics must be NaN
    p = dict(params, e=e, e4=e4)
    got = simulate_lti_batch(model_scaled_E, p, x0, TS, metrics=METRICS, chunk_size=B)
    for k in range(B - 1):
        ref = scipy_reference(params["delta"][k], params["xi0"][k], x0[k], e[k])
        for name in METRICS:
            np.testing.assert_allclose(np.asarray(got[name][k]), ref[name], rtol=1e-10)
    for name in METRICS:
        assert np.all(np.isnan(np.asarray(got[name][B - 1])))


def test_forward_kernel_graph_does_not_grow_with_n():
    # Issue 16 item 2: the forward time loop (`_multistep_block`: m steps per pass as batched
    # matrix products) has a graph of the same size for every N (the former batch-last matvec
    # was unrolled over N columns, so compile time grew with n: 12 / 24 / 52 s at n = 16 / 32 / 64)
    # private: the kernel is tested itself
    from fojax.simulation._batch import _block_kernel
    from fojax.simulation._lti_batch import _ModelProblem

    def count(n, keep):
        def plant(A):
            return fojax.DescriptorSystem(jnp.eye(n), A, jnp.zeros((n, 1)), jnp.eye(n)[:1])

        problem = _ModelProblem(plant, jnp.eye(n), None, None, (("iae_l1", n),), keep)
        p = (jnp.zeros((3, n, n)), jnp.zeros((3, n)))
        return count_equations(lambda p: _block_kernel(problem, p, 0.01, jnp.linspace(0.0, 1.0, 11), None), p)

    assert count(16, False) == count(40, False)
    assert count(16, 3) == count(40, 3)
