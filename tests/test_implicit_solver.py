"""The `fojax.Diffrax` stepper's default implicit solver (Kvaerno5 with the SmallLU Newton step)
inside `jax.vmap` and `shard_map`, and the small LU it solves with.

Oracles: ``numpy.linalg.solve`` (with and without transpose) and the factorisation ``PA = LU``
checked by multiplying back; the closed form ``expm(a M) y0`` (``scipy.linalg.expm``) of a
linear ODE solved inside ``shard_map(vmap(...))``; single `fojax.simulate` runs of the samples
of a faulty-plant `run_study` on the Diffrax path.
"""

import diffrax
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
import scipy.linalg
from jax.sharding import Mesh, PartitionSpec

import fojax
from fojax import studies as S
from fojax.design import design_functional_observer, Disk

# private: the implicit solver is tested itself
from fojax.simulation._implicit import (
    default_implicit_solver,
    lu_factor_small,
    lu_solve_small,
    SmallLU,
)


def test_small_lu_matches_numpy_with_pivoting_and_transpose(rng):
    for n in (1, 3, 7):
        A = rng.normal(size=(n, n))
        if n > 1:
            A[0, 0] = 0.0  # forces a row exchange
        b = rng.normal(size=n)
        LU, perm = jax.jit(lu_factor_small)(jnp.asarray(A))
        P = np.eye(n)[np.asarray(perm)]
        L = np.tril(np.asarray(LU), -1) + np.eye(n)
        np.testing.assert_allclose(L @ np.triu(np.asarray(LU)), P @ A, rtol=1e-12, atol=1e-12)
        for trans, M in ((False, A), (True, A.T)):
            x = lu_solve_small(LU, perm, jnp.asarray(b), transpose=trans)
            np.testing.assert_allclose(np.asarray(x), np.linalg.solve(M, b), rtol=1e-10, atol=1e-12)
    # through lineax, on an operator from a pytree (two blocks) to a vector: forward solve,
    # and the transposed state (`SmallLU.transpose`, used when differentiating a solve)
    A = rng.normal(size=(5, 5))
    struct = (jax.ShapeDtypeStruct((2,), jnp.float64), jax.ShapeDtypeStruct((3,), jnp.float64))
    op = lx.FunctionLinearOperator(lambda v: jnp.asarray(A) @ jnp.concatenate(v), struct)
    b = rng.normal(size=5)
    x = lx.linear_solve(op, jnp.asarray(b), SmallLU()).value
    assert [v.shape for v in x] == [(2,), (3,)]
    np.testing.assert_allclose(np.concatenate(x), np.linalg.solve(A, b), rtol=1e-10)
    state_t, _ = SmallLU().transpose(SmallLU().init(op, {}), {})
    xt, _, _ = SmallLU().compute(state_t, (jnp.asarray(b[:2]), jnp.asarray(b[2:])), {})
    assert xt.shape == (5,)
    np.testing.assert_allclose(np.asarray(xt), np.linalg.solve(A.T, b), rtol=1e-10)

def test_default_implicit_solver_inside_shard_map_matches_closed_form():
    # y' = a M y: with diffrax.Kvaerno5() (lineax LU) this fails to trace inside
    # shard_map(vmap(...)) with "pytree does not match out_structure" (lineax #185).
    M = jnp.array([[-1.0, 2.0], [0.0, -3.0]])

    def solve(a):
        # y0 made inside the shard map and `a` passed as args: a y0 or `a` closed over
        # from outside has no mesh sharding in its type, and equinox's closure conversion
        # (of the Jacobian's function) then fails on the same sharding-in-the-structure
        # comparison. fojax's studies pass every array through the shard map's arguments.
        y0 = jnp.ones(2)
        term = diffrax.ODETerm(lambda t, y, a: a * (M @ y))
        return diffrax.diffeqsolve(
            term, default_implicit_solver(), 0.0, 1.0, None, y0, args=a,
            stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-11),
        ).ys[-1]

    a = jnp.array([0.5, 1.0, 2.0, 4.0])
    mesh = Mesh(np.asarray(jax.devices()[:2]), ("batch",))
    f = jax.shard_map(jax.vmap(solve), mesh=mesh, in_specs=PartitionSpec("batch"),
                      out_specs=PartitionSpec("batch"), check_vma=False)
    got = np.asarray(jax.jit(f)(a))
    for k, ak in enumerate(np.asarray(a)):
        ref = scipy.linalg.expm(ak * np.asarray(M)) @ np.ones(2)
        np.testing.assert_allclose(got[k], ref, rtol=1e-7, atol=1e-9)


@pytest.fixture(scope="module")
def faulty_study():
    ex = fojax.models.example_3_3_7()
    T, nf = 0.5, 3
    k_u, k_f = jax.random.split(jax.random.PRNGKey(11))
    base = fojax.UncertainDescriptorSystem(ex.system, dA=ex.dA, delta=fojax.Constant(jnp.zeros(1)))
    plant = fojax.FaultyPlant(base, ex.Fa, ex.Fs, fault=fojax.plant.FaultProfile(jnp.zeros(nf)))
    study = S.Study(
        plant, jnp.full((6,), 0.5), jnp.linspace(0.0, T, 6), ex.L, fojax.Sine(jnp.ones(2), 1.0),
        uncertainty=(S.constant_delta(k_u, 2, 1, bounds=(-0.3, 0.3), path=("plant", "base", "delta")),),
        scenarios=(S.fault_scenarios(k_f, 2, nf, magnitude=(0.5, 1.5), onset=(0.05, 0.2)),),
        fault_targets=True,
    )
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="proportional", region=Disk(-2.0, 1.0))
    return study, d.observer


def test_faulty_plant_study_with_default_implicit_solver_matches_single_runs(faulty_study):
    # The regression of issue 5: the default solver inside run_study's shard_map + vmap.
    study, obs = faulty_study
    # method="diffrax": the exact batch kernel would take this LTI study otherwise
    res = S.run_study(study, obs, devices=jax.devices()[:2], quiet=True, stepper=fojax.Diffrax())
    assert res.metrics["iae"].shape == (1, 2, 2, 5) and res.metrics["success"].all()
    worst = 0.0
    for i in range(2):
        for j in range(2):
            plant, x0 = study.sample(i, j)
            assert float(jnp.max(jnp.abs(plant.fault.amplitude))) >= 0.5  # a fault is active
            sol = fojax.simulate(plant, x0, study.ts, study.u, observers=(obs,))
            assert sol.method == "diffrax"
            ref = S.error_metrics(study.ts, sol.estimates[0] - study.target(plant, study.ts, sol.xs))
            for name in S._runner.METRICS:
                got, want = np.asarray(res.metrics[name][0, i, j]), np.asarray(ref[name])
                np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12, err_msg=name)
                fin = np.isfinite(want) & (want != 0)
                worst = max(worst, float(np.max(np.abs(got[fin] - want[fin]) / np.abs(want[fin]), initial=0.0)))
    print(f"worst relative metric difference study vs single runs: {worst:.1e}")
