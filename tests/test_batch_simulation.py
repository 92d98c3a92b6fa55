"""`fojax.run_study` on the exact batch kernel: many LTI samples of one loop, metrics in the loop.

Checked against (1) `jax.vmap(fojax.simulate)` trajectories and (2) an independent SciPy
recurrence (index partition of the diagonal E by hand, `scipy.linalg.expm`, trapezoid rule),
on the thesis §4.1.3 closed loop with a per-sample parameter perturbation ``A_k = A + δ_k ΔA``,
per-sample initial states and an LTI observer driven by y. The metrics of the joint vector
``[x; ξ]`` are read from three studies of the same samples: the signal study ``z = x``
(IAE and ISE per state), the observer's error ``ξ − [x1; x2]`` and the observer state itself
(``L = 0``).
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
    X0,
)
from helpers import count_equations

import fojax

# private: TRACE_COUNTS (the no-retrace check), and the kernel's parts tested themselves
from fojax.simulation._batch import TRACE_COUNTS
from fojax.studies import Family


# bit-for-bit equality of different programs (chunks and device counts): compiled as users get it
pytestmark = pytest.mark.production_codegen


TS = np.linspace(0.0, 4.0, 401)
B = 7
XI0 = np.array([0.7, -1.2])
OBSERVER = LTIObserver(jnp.asarray(AO), jnp.asarray(BY), jnp.asarray(XI0))
#: the signals of the three studies: x itself, the observer error ξ − [x1; x2], ξ itself
SIGNALS = {"x": (np.eye(4), False), "e": (C0[:2], True), "xi": (np.zeros((2, 4)), True)}
SAVE = fojax.Metrics(kinds=("iae", "ise"), bands=None)


def sample_params(seed, b=B):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.3, 0.3, b), X0 * (1 + 0.1 * rng.normal(size=(b, 4)))


def study(delta, x0, L, ts=TS, E_k=None):
    """The samples ``A_k = A + δ_k ΔA`` (and optionally ``E_k``) from ``x0_k`` as one `Study`."""
    plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL), jnp.asarray(B0), jnp.asarray(C0))
    A = jnp.asarray(ACL)[None] + jnp.asarray(delta)[:, None, None] * jnp.asarray(DA)[None]
    fams = (Family(A, ("plant", "A")), Family(jnp.asarray(x0), ("x0",)))
    if E_k is not None:
        fams += (Family(jnp.asarray(E_k), ("plant", "E")),)
    return fojax.Study(plant, X0, ts, L, uncertainty=fams)


def run(delta, x0, ts=TS, names=tuple(SIGNALS), **kw):
    """``{name: (B, q) iae, (B, q) ise}`` of the three studies (or of `names`), and their results."""
    out, results = {}, {}
    for name in names:
        L, observed = SIGNALS[name]
        res = fojax.run_study(study(delta, x0, L, ts), OBSERVER if observed else None, save=SAVE, stepper=fojax.Exact(), quiet=True, **kw)
        results[name] = res
        out[name] = {k: res.metrics[k][0, :, 0] for k in ("iae", "ise")}
    return out, results


def trapz(f, h):
    return h * (np.sum(f, axis=0) - 0.5 * (f[0] + f[-1]))


def host_metrics(traj, h):
    """``(T, 6)`` joint trajectory ``[x; ξ]`` -> the metrics of the three studies."""
    x, xi = traj[:, :4], traj[:, 4:]
    e = xi - x @ C0[:2].T
    return {name: {"iae": trapz(np.abs(v), h), "ise": trapz(v**2, h)} for name, v in (("x", x), ("e", e), ("xi", xi))}


def scipy_reference(delta, x0, e=1.0):
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
    w = np.concatenate([x0[:3], XI0])
    ws = [w]
    for _ in range(len(TS) - 1):
        w = Phi @ w
        ws.append(w)
    ws = np.array(ws)
    traj = np.hstack([ws[:, :3] @ Tx.T, ws[:, 3:]])
    return host_metrics(traj, h)


def assert_close(got, ref, k, rtol=1e-10):
    for name in SIGNALS:
        for kind in ("iae", "ise"):
            np.testing.assert_allclose(got[name][kind][k], ref[name][kind], rtol=rtol, err_msg=f"{name} {kind}")


@pytest.fixture(scope="module")
def batch_result():
    delta, x0 = sample_params(0)
    before = TRACE_COUNTS["StudyProblem"]
    out, results = run(delta, x0, chunk_size=8)
    return delta, x0, out, results, TRACE_COUNTS["StudyProblem"] - before


def test_exact_engine_and_shapes(batch_result):
    _, _, out, results, _ = batch_result
    for name, res in results.items():
        assert res.attrs["engine"] == "exact-batch", name
        assert np.all(res.metrics["success"])
    assert out["x"]["iae"].shape == (B, 4) and out["e"]["ise"].shape == (B, 2) and out["xi"]["ise"].shape == (B, 2)


def test_matches_independent_scipy_recurrence(batch_result):
    delta, x0, out, _, _ = batch_result
    for k in range(B):
        assert_close(out, scipy_reference(delta[k], x0[k]), k)


def test_matches_vmapped_simulate(batch_result):
    delta, x0, out, _, _ = batch_result
    ks = slice(0, 3)

    def one(d, x):
        plant = fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) + d * jnp.asarray(DA), jnp.asarray(B0),
                                       jnp.asarray(C0))
        sol = fojax.simulate(plant, x, jnp.asarray(TS), observers=(OBSERVER,))
        return jnp.concatenate([sol.xs, sol.observer_states[0]], axis=1)

    trajs = np.asarray(jax.vmap(one)(jnp.asarray(delta[ks]), jnp.asarray(x0[ks])))
    h = TS[1] - TS[0]
    for k in range(3):
        assert_close(out, host_metrics(trajs[k], h), k)


def test_second_call_with_new_numbers_does_not_retrace(batch_result):
    _, _, _, _, traces = batch_result
    assert traces == 2  # one kernel per structure: z = x, and the observer's (e and ξ differ only in L's numbers)
    delta, x0 = sample_params(1)
    before = TRACE_COUNTS["StudyProblem"]
    run(delta, x0, TS + 1.0, chunk_size=8)
    assert TRACE_COUNTS["StudyProblem"] == before


def test_chunked_equals_unchunked_exactly(batch_result):
    delta, x0, out, _, _ = batch_result
    before = TRACE_COUNTS["StudyProblem"]
    chunked, results = run(delta, x0, chunk_size=4)  # 4 + 3 (padded)
    assert TRACE_COUNTS["StudyProblem"] == before + 2  # one kernel per structure for all chunks
    assert all(res.attrs["num_chunks"] == 2 for res in results.values())
    for name in SIGNALS:
        for kind in ("iae", "ise"):
            np.testing.assert_array_equal(chunked[name][kind], out[name][kind])


def test_vmapped_simulate_traceable_inside_jit(batch_result):
    # `simulate`'s method resolution inspects a concrete ts with NumPy (no float() of a tracer).
    delta, x0, _, _, _ = batch_result
    ts = jnp.asarray(TS)  # a concrete jax.Array closed over by the jitted function

    def plant_of(d):
        return fojax.DescriptorSystem(jnp.asarray(E), jnp.asarray(ACL) + d * jnp.asarray(DA), jnp.asarray(B0),
                                      jnp.asarray(C0))

    @jax.jit
    def last_states(d, x):
        return jax.vmap(lambda dk, xk: fojax.simulate(plant_of(dk), xk, ts).xs[-1])(d, x)

    got = last_states(jnp.asarray(delta[:2]), jnp.asarray(x0[:2]))
    ref = fojax.simulate(plant_of(delta[0]), jnp.asarray(x0[0]), jnp.asarray(TS)).xs[-1]
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(ref), rtol=1e-12, atol=1e-14)


def test_refuses_what_the_exact_kernel_cannot_step(batch_result):
    delta, x0, _, _, _ = batch_result
    bad_ts = study(delta, x0, np.eye(4), TS**2)  # not uniform: the exact kernel does not apply
    reason = fojax.studies.exact_refusal(bad_ts, ())
    assert reason is not None and "uniform" in reason
    with pytest.raises(fojax.errors.InputError, match="Metrics"):
        fojax.Metrics(kinds=("peak", "nonsense"))

    def f(x, u, th):
        return jnp.asarray(ACL) @ x

    nonlinear = fojax.NonlinearDescriptorSystem(jnp.asarray(E), f, lambda x, th: x[:3], {}, m=2, p=3)
    st = fojax.Study(nonlinear, X0, TS, np.eye(4))
    assert "not LTI" in fojax.studies.exact_refusal(st, ())
    with pytest.raises(fojax.errors.InputError, match="linear time-invariant"):
        fojax.run_study(st, stepper=fojax.Exact(), quiet=True)


def test_output_coordinates_path_matches_scipy(batch_result):
    # Few metric rows: |x| (4 rows, rank 3 since x4 is algebraic) on the 3 slow states, and the
    # observer error (2 rows) on the 5 joint states: the kernel steps in output coordinates
    delta, x0, out, _, _ = batch_result
    # private: the path is really taken (exact_problem's output basis) and tested itself
    from fojax.simulation._batch import _output_basis
    from fojax.studies._exact import exact_problem

    A = ACL + delta[0] * DA
    Tx = np.vstack([np.eye(3), -A[3:, :3] / A[3, 3]])  # x = Tx x_d (hand index partition)
    out_map = scipy.linalg.block_diag(Tx, np.eye(2))  # (6, 5): joint state from [x_d; xi]
    MX = np.hstack([np.eye(4), np.zeros((4, 2))])  # x and the error ξ − [x1; x2] on [x; ξ]
    ind, Nc = _output_basis(np.vstack([MX, np.hstack([-C0[:2], np.eye(2)])]) @ out_map)
    assert len(ind) == 5 and Nc.shape == (0, 5)  # 5 independent outputs span the 5 states
    for name, (L, observed) in SIGNALS.items():
        (_, basis, _), _ = exact_problem(study(delta, x0, L), (OBSERVER,) if observed else (), 0.05, 0)
        if name != "xi":  # ξ alone: 2 rows on 5 states, an orthonormal complement of 3 rows
            assert basis is not None, name
    for k in range(B):
        assert_close(out, scipy_reference(delta[k], x0[k]), k)


def test_independent_of_device_count(batch_result):
    # conftest forces 4 host devices: the default spreads blocks over all of them
    delta, x0, out, _, _ = batch_result
    assert jax.device_count() >= 2
    one, _ = run(delta, x0, names=("e",), chunk_size=8, devices=jax.devices()[:1])
    two, _ = run(delta, x0, names=("e",), chunk_size=2, devices=jax.devices()[:2])
    for name in ("e",):
        for kind in ("iae", "ise"):
            np.testing.assert_array_equal(one[name][kind], out[name][kind])
            np.testing.assert_array_equal(two[name][kind], out[name][kind])


def test_per_sample_E_matches_scipy(batch_result):
    # E_k = diag(e_k, 1, 1, 0): dividing the first equation by e_k gives the plant with E
    # and A's first row scaled by 1/e_k, which the independent SciPy reference uses. The
    # samples do not share E, so run_study steps them one by one (vmap of fojax.simulate).
    delta, x0, _, _, _ = batch_result
    e = np.random.default_rng(5).uniform(0.5, 2.0, B)
    E_k = np.stack([np.diag([ek, 1.0, 1.0, 0.0]) for ek in e])
    st = study(delta, x0, np.eye(4), E_k=E_k)
    res = fojax.run_study(st, save=SAVE, stepper=fojax.Exact(), quiet=True)
    assert res.attrs["engine"] == "vmap-simulate"
    for k in range(3):
        ref = scipy_reference(delta[k], x0[k], e[k])["x"]
        for kind in ("iae", "ise"):
            np.testing.assert_allclose(res.metrics[kind][0, k, 0], ref[kind], rtol=1e-10, err_msg=kind)


def test_forward_kernel_graph_does_not_grow_with_n():
    # The forward time loop of large loops (`_multistep_block`: m steps per pass as batched
    # matrix products) has a graph of the same size for every N (a batch-last matvec unrolled
    # over N columns would grow the compile time with n)
    # private: the kernel and the study problem are tested themselves
    from fojax.simulation._batch import _block_kernel
    from fojax.studies._exact import exact_problem

    def count(n, keep):
        plant = fojax.DescriptorSystem(jnp.eye(n), -jnp.eye(n), jnp.zeros((n, 1)), jnp.eye(n)[:1])
        fam = Family(-jnp.eye(n)[None].repeat(3, axis=0), ("plant", "A"))
        st = fojax.Study(plant, jnp.ones(n), jnp.linspace(0.0, 1.0, 11), jnp.eye(n), uncertainty=(fam,))
        (problem, _, idx), _ = exact_problem(st, (), 0.05, keep, kinds=("iae",))
        return count_equations(lambda p: _block_kernel(problem, p, 0.01, st.ts, None), idx)

    # from TRIANGULAR_MIN_N on (`_multistep_block`); below it `_multistep_last`'s column FMAs
    # grow linearly with N, as the step-by-step matvec below MULTISTEP_MIN_N does
    from fojax.simulation._batch import TRIANGULAR_MIN_N

    assert count(TRIANGULAR_MIN_N, 0) == count(40, 0)
    assert count(TRIANGULAR_MIN_N, 3) == count(40, 3)
