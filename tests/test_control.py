"""Observer-based control and fault-tolerant control (`fojax.control`, thesis Chapter 4).

Independent checks: finite poles with `scipy.linalg.eigvals(A, E)` (QZ, finite values),
impulse-freeness with Dai's rank test rank [[E, 0], [A, E]] = n + rank E (NumPy), the
closed-loop assembly against the observer module's own `vector_field`/`output`, steady
states with `numpy.linalg.solve`, and the delay loop against a method-of-steps
reference written here with `scipy.integrate.solve_ivp`.

Fault scenarios (Figures 4.5, 4.10 and 4.13 are not part of the text; our reading):
sensor faults f1 = +1 on y1 from t = 3 s and f2 = -0.5 on y2 from t = 6 s; actuator faults
f1 = +1 on u1 from t = 5 s and f2 = -0.5 on u2 from t = 15 s, with u_r = [sin t,
0.5 sin 2t].
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
import scipy.stats
from helpers import assert_eigenvalues_match, spectral_distance
from scipy.integrate import solve_ivp

import fojax
import fojax.models as fm
from fojax.control import (
    assemble,
    closed_loop,
    design_actuator_ftc,
    design_sensor_ftc,
    design_simultaneous_ftc,
    design_state_feedback,
    finite_time_loop,
    simulate_lti,
)
from fojax.design import design_finite_time_observer, design_functional_observer, Disk
from fojax.errors import AlgebraicLoopError, StabilizabilityError
from fojax.observer import GeneralizedFunctionalObserver
from fojax.plant import Sine, Stack, Step, Zero


# --------------------------------------------------------------------------- helpers


def eig_finite(A, E):
    w = sl.eigvals(np.asarray(A), np.asarray(E))
    return w[np.isfinite(w) & (np.abs(w) < 1e8)]


def impulse_free(E, A):
    E, A = np.asarray(E), np.asarray(A)
    n, r = E.shape[0], np.linalg.matrix_rank(E)
    M = np.block([[E, np.zeros_like(E)], [A, E]])
    return np.linalg.matrix_rank(M) == n + r


def regular(E, A):
    s0 = 1.2345 + 0.678j
    return np.linalg.cond(s0 * np.asarray(E) - np.asarray(A)) < 1e12


def scipy_admissible(E, A, decay=0.0):
    """Regular, impulse-free and every finite pole with Re < -decay (SciPy/NumPy only)."""
    if not (regular(E, A) and impulse_free(E, A)):
        return False
    p = eig_finite(A, E)
    return p.size == np.linalg.matrix_rank(np.asarray(E)) and bool(np.all(p.real < -decay))


def match(a, b):
    """Largest distance of the best one-to-one matching of two spectra (bottleneck)."""
    assert np.size(a) == np.size(b), (a, b)
    return spectral_distance(a, b)


def printed_observer(ex, E_perp=None):
    E_perp = np.asarray(ex.E_perp if E_perp is None else E_perp)
    p, m = ex.C.shape[0], ex.B.shape[1]
    r1 = E_perp.shape[0]
    Wu = np.vstack([-E_perp @ ex.B, np.zeros((p, m))])
    Wy = np.vstack([np.zeros((r1, p)), np.eye(p)])
    return GeneralizedFunctionalObserver(
        ex.N, ex.J, ex.F, ex.H, ex.S, ex.G, ex.M, ex.P, ex.Q, Wu, Wy
    )


# --------------------------------------------------------------------------- §4.1.3


@pytest.fixture(scope="module")
def ex413():
    return fm.example_4_1_3()


def test_printed_gains_closed_loop_poles(ex413):
    """Printed L and observer gains of §4.1.3: the implementable loop (eq. 4.13 with the
    algebraic loop solved) has the printed poles within one unit of the last printed digit
    (-4.48 and -39.790 are printed truncated as -4.47, -39.78)."""
    loop = closed_loop(ex413.system, printed_observer(ex413))
    assert isinstance(loop, fojax.DescriptorSystem)
    poles = eig_finite(loop.A, loop.E)
    printed = ex413.eig_loop
    unit = np.array([0.1, 0.1, 0.01, 0.1, 0.1, 0.1, 0.01])  # -1.7±1.99i → 0.1 on Re
    assert_eigenvalues_match(poles, printed, atol=unit, rtol=0.0)
    # and fojax's analysis layer agrees with QZ
    assert match(fojax.analysis.finite_poles(loop), poles) < 1e-9


@pytest.fixture(scope="module")
def design413(ex413):
    return design_functional_observer(ex413.system, ex413.L, region=Disk(-2.0, 1.0))


def test_separation_with_fojax_design(ex413, design413):
    s, L = ex413.system, np.asarray(ex413.L)
    loop = closed_loop(s, design413)
    poles = eig_finite(loop.A, loop.E)
    union = np.concatenate(
        [eig_finite(s.A + s.B @ L, s.E), np.linalg.eigvals(np.asarray(design413.error_matrix))]
    )
    assert poles.size == 7
    assert match(poles, union) < 1e-8
    obs_poles = np.linalg.eigvals(np.asarray(design413.error_matrix))
    assert np.all(np.abs(obs_poles + 2.0) < 1.0)  # requested Disk(-2, 1)
    # the thesis's coordinates [x; ε; v] (eq. 4.13) give the same finite poles
    loop_e = closed_loop(s, design413, coordinates="error")
    assert match(eig_finite(loop_e.A, loop_e.E), poles) < 1e-8
    assert impulse_free(loop.E, loop.A)


def test_fully_designed_loop_in_regions(ex413):
    s = ex413.system
    fb = design_state_feedback(s, region=Disk(-3.0, 2.0))
    d = design_functional_observer(s, fb.L, region=Disk(-8.0, 2.0))
    loop = closed_loop(s, d)
    poles = eig_finite(loop.A, loop.E)
    in_fb = np.abs(poles + 3.0) < 2.0
    in_obs = np.abs(poles + 8.0) < 2.0
    assert np.all(in_fb | in_obs)
    assert in_fb.sum() == 3 and in_obs.sum() == 4
    union = np.concatenate(
        [eig_finite(s.A + s.B @ fb.L, s.E), np.linalg.eigvals(np.asarray(d.error_matrix))]
    )
    assert match(poles, union) < 1e-8


def test_assembly_matches_observer_module(ex413):
    """The closed-loop matrices equal plant + `GeneralizedFunctionalObserver.vector_field`
    with u solved from u = ẑ(u) + u_r, on a plant with E⊥B ≠ 0 (an algebraic loop), and
    the separation property still holds."""
    B = np.array(ex413.B)
    B[3] = [0.5, 0.0]
    s = fojax.DescriptorSystem(ex413.E, ex413.A, B, ex413.C)
    fb = design_state_feedback(s, decay=0.5)
    d = design_functional_observer(s, fb.L, region=Disk(-3.0, 1.0))
    obs = d.observer
    assert np.abs(np.asarray(obs.Q @ obs.Wu)).max() > 0.1  # the loop is algebraic
    Fs = np.array([[1.0], [0.0], [0.5]])
    Fa = np.array([[0.0], [1.0], [0.0], [0.0]])
    system, maps = assemble(s.E, s.A, s.B, s.C, obs, Fa=Fa, Fs=Fs)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x, xi = rng.normal(size=4), rng.normal(size=obs.state_size)
        ur, f = rng.normal(size=2), rng.normal(size=1)
        y = np.asarray(s.C) @ x + Fs @ f
        g = lambda u: u - obs.output(0.0, jnp.asarray(xi), u, jnp.asarray(y)) - ur
        J = jax.jacobian(g)(jnp.zeros(2))
        u = np.asarray(jnp.linalg.solve(J, -g(jnp.zeros(2))))
        rhs = np.concatenate(
            [
                np.asarray(s.A) @ x + B @ u + Fa @ f,
                np.asarray(obs.vector_field(0.0, jnp.asarray(xi), jnp.asarray(u), jnp.asarray(y))),
            ]
        )
        X, r = np.concatenate([x, xi]), np.concatenate([ur, f])
        np.testing.assert_allclose(
            np.asarray(system.A) @ X + np.asarray(system.B) @ r, rhs, atol=1e-10
        )
        np.testing.assert_allclose(
            np.asarray(maps.K_X) @ X + np.asarray(maps.K_r) @ r, u, atol=1e-10
        )
    loop = closed_loop(s, d)
    union = np.concatenate(
        [eig_finite(s.A + s.B @ fb.L, s.E), np.linalg.eigvals(np.asarray(d.error_matrix))]
    )
    assert match(eig_finite(loop.A, loop.E), union) < 1e-8


def test_ill_posed_algebraic_loop_refused(ex413):
    B = np.array(ex413.B)
    B[3] = [1.0, 0.0]
    s = fojax.DescriptorSystem(ex413.E, ex413.A, B, ex413.C)
    Wu = np.vstack([-np.array([[0, 0, 0, 1.0]]) @ B, np.zeros((3, 2))])  # [[-1, 0], 0...]
    Wy = np.vstack([np.zeros((1, 3)), np.eye(3)])
    Q = np.zeros((2, 4))
    Q[0, 0] = -1.0  # ẑ1 = Q w = u1: I − Q Wu = diag(0, 1)
    z = np.zeros
    obs = GeneralizedFunctionalObserver(
        -np.eye(2),
        z((2, 2)),
        z((2, 4)),
        z((2, 2)),
        z((2, 2)),
        -np.eye(2),
        z((2, 4)),
        np.eye(2),
        Q,
        Wu,
        Wy,
    )
    with pytest.raises(AlgebraicLoopError, match="ill-posed algebraic loop"):
        closed_loop(s, obs)
    with pytest.raises(fojax.errors.ShapeError, match="one per plant input"):
        closed_loop(s, design_functional_observer(s, np.eye(3, 4), region=Disk(-2.0, 1.0)))


# --------------------------------------------------------------------------- state feedback


@pytest.mark.parametrize("name", ["example_3_1_2", "example_4_1_3", "example_4_2_2"])
@pytest.mark.parametrize(
    "kw, decay, disk",
    [({}, 0.0, None), ({"decay": 1.0}, 1.0, None), ({"region": Disk(-3.0, 2.0)}, 0.0, (-3.0, 2.0))],
)
def test_state_feedback_thesis_examples(name, kw, decay, disk):
    s = getattr(fm, name)().system
    fb = design_state_feedback(s, **kw)
    E, Acl = np.asarray(s.E), np.asarray(s.A) + np.asarray(s.B) @ fb.L
    assert scipy_admissible(E, Acl, decay)
    p = eig_finite(Acl, E)
    if disk is not None:
        assert np.all(np.abs(p - disk[0]) < disk[1])
    assert match(p, fb.poles) < 1e-8
    assert fojax.analysis.is_admissible(s.E, Acl, margin=decay)


def _random_stabilizable(rng):
    """Random unstable (or impulsive) but stabilizable descriptor system, n = 3..6.

    About a third are impulsive in open loop (Ã22 made singular) but impulse controllable.
    Screened with fojax.analysis (the design is then checked with SciPy only)."""
    while True:
        n = int(rng.integers(3, 7))
        r = int(rng.integers(max(1, n - 3), n))
        m = int(rng.integers(1, 3))
        U = scipy.stats.ortho_group.rvs(n, random_state=rng)
        V = scipy.stats.ortho_group.rvs(n, random_state=rng)
        E = U @ np.diag(np.r_[rng.uniform(0.5, 2.0, r), np.zeros(n - r)]) @ V.T
        A, B = rng.normal(size=(n, n)), rng.normal(size=(n, m))
        impulsive = rng.random() < 0.35
        if impulsive:
            At = U.T @ A @ V
            At[r:, r:] = At[r:, r:] @ np.diag(np.r_[0.0, np.ones(n - r - 1)])
            A = U @ At @ V.T
        s = fojax.DescriptorSystem(E, A, B)
        if not fojax.analysis.is_regular(s):
            continue
        p = fojax.analysis.finite_poles(s)
        if not ((p.size and p.real.max() > 0) or not fojax.analysis.is_impulse_free(s)):
            continue
        if fojax.analysis.is_stabilizable(s):
            return s, impulsive


@pytest.fixture(scope="module")
def random_systems():
    rng = np.random.default_rng(20261121)
    return [_random_stabilizable(rng) for _ in range(55)]


def test_state_feedback_random_systems(random_systems):
    n_impulsive = sum(imp for _, imp in random_systems)
    assert len(random_systems) >= 50 and n_impulsive >= 10
    for s, impulsive in random_systems:
        E, A, B = (np.asarray(x) for x in (s.E, s.A, s.B))
        assert not scipy_admissible(E, A)
        fb = design_state_feedback(s)
        assert scipy_admissible(E, A + B @ fb.L), (s, impulsive, fb)


def test_state_feedback_random_regions(random_systems):
    for s, _ in random_systems[:12]:
        E, A, B = (np.asarray(x) for x in (s.E, s.A, s.B))
        fb = design_state_feedback(s, region=Disk(-2.0, 1.5))
        p = eig_finite(A + B @ fb.L, E)
        assert scipy_admissible(E, A + B @ fb.L) and np.all(np.abs(p + 2.0) < 1.5)


def test_state_feedback_standard_system_and_methods():
    """E = I (no algebraic part) and each LMI method on its own."""
    A, B = np.array([[1.0, 2.0], [0.0, -1.0]]), np.array([[0.0], [1.0]])
    s = fojax.DescriptorSystem.from_state_space(A, B)
    for kw, check in [
        ({"method": "dual-lmi", "decay": 2.0}, lambda p: np.all(p.real < -2.0)),
        (
            {"method": "slow-subsystem", "region": Disk(-4.0, 1.0)},
            lambda p: np.all(np.abs(p + 4) < 1),
        ),
        ({"method": "place", "region": Disk(-4.0, 1.0)}, lambda p: np.all(np.abs(p + 4) < 1)),
    ]:
        fb = design_state_feedback(s, **kw)
        assert fb.method == kw["method"] and check(np.linalg.eigvals(A + B @ fb.L))
    with pytest.raises(ValueError, match=r"\(half-planes\) only"):
        design_state_feedback(s, method="dual-lmi", region=Disk(-4.0, 1.0))


def test_not_stabilizable_raises():
    # uncontrollable unstable finite mode s = 1 (x1 is not reached by u)
    s = fojax.DescriptorSystem(
        np.diag([1.0, 1.0, 0.0]), np.diag([1.0, -1.0, 1.0]), [[0.0], [1.0], [0.0]]
    )
    with pytest.raises(StabilizabilityError, match=r"stabilizability fails.*mode\(s\) 1"):
        design_state_feedback(s)
    # not impulse controllable: a nilpotent block [[0, 1], [0, 0]] that u does not reach
    E = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 0, 0]])
    s2 = fojax.DescriptorSystem(E, -np.eye(3), [[1.0], [0.0], [0.0]])
    assert not fojax.analysis.is_i_controllable(s2)
    with pytest.raises(StabilizabilityError, match="impulse controllability fails"):
        design_state_feedback(s2)
    # a stable uncontrollable mode outside the requested region
    s3 = fojax.DescriptorSystem(np.eye(2), np.diag([-0.5, 1.0]), [[0.0], [1.0]])
    fb = design_state_feedback(s3)  # stabilizable: fine
    assert scipy_admissible(np.eye(2), np.asarray(s3.A) + np.asarray(s3.B) @ fb.L)
    with pytest.raises(StabilizabilityError, match="pole-region assignability"):
        design_state_feedback(s3, decay=1.0)


# --------------------------------------------------------------------------- FTC


@pytest.fixture(scope="module")
def sensor_ftc():
    ex = fm.example_4_2_2()
    return ex, design_sensor_ftc(ex.system, ex.Fs, L=ex.L, region=Disk(-3.0, 2.0))


SENSOR_FAULT = Stack((Step(1.0, 3.0), Step(-0.5, 6.0)))
TS15 = jnp.linspace(0.0, 15.0, 1501)


def _equilibrium(system, r):
    """Steady state of E Ẋ = A X + B r for a constant r (NumPy solve)."""
    return np.linalg.solve(np.asarray(system.A), -np.asarray(system.B) @ r)


def test_sensor_ftc(sensor_ftc):
    ex, ftc = sensor_ftc
    tr = ftc.simulate(ex.x0, TS15, fault=SENSOR_FAULT)
    x, x_nft = np.asarray(tr.x), np.asarray(tr.x_ref)
    late = np.asarray(TS15) >= 13.0
    assert np.abs(x[late]).max() < 1e-4  # fault-tolerant: x -> 0 despite the faults
    assert np.abs(x_nft[-1]).max() > 0.05  # not fault-tolerant: x settles away from 0
    r = np.array([0.0, 0.0, 1.0, -0.5])  # [u_r; f] after t = 6
    X_ft = _equilibrium(ftc.closed_loop, r)
    X_nft = _equilibrium(ftc.comparison, r)
    assert np.abs(X_ft[:3]).max() < 1e-10  # the FT equilibrium is x = 0 exactly
    np.testing.assert_allclose(x_nft[-1], X_nft[:3], atol=1e-4)
    assert np.abs(X_nft[:3]).max() > 0.05
    # the estimate is the fault-free law Lx
    np.testing.assert_allclose(np.asarray(tr.u)[late], x[late] @ np.asarray(ex.L).T, atol=1e-4)


def test_sensor_ftc_vmap_and_backends(sensor_ftc):
    ex, ftc = sensor_ftc
    amps1, amps2 = jnp.array([1.0, 2.0, -0.7]), jnp.array([-0.5, 0.3, 1.0])
    t1, t2 = jnp.array([3.0, 4.0, 5.0]), jnp.array([6.0, 7.0, 8.0])
    faults = jax.vmap(lambda a, b, c, d: Stack((Step(a, c), Step(b, d))))(amps1, amps2, t1, t2)
    trs = jax.vmap(lambda f: ftc.simulate(ex.x0, TS15, fault=f))(faults)
    assert trs.x.shape == (3, 1501, 3)
    assert float(jnp.abs(trs.x[:, -1]).max()) < 1e-4
    assert np.all(np.abs(np.asarray(trs.x_ref[:, -1])).max(axis=1) > 0.05)
    single = ftc.simulate(ex.x0, TS15, fault=Stack((Step(2.0, 4.0), Step(0.3, 7.0))))
    np.testing.assert_allclose(trs.x[1], single.x, atol=1e-12)
    # the exact stepper and fojax.simulate (independent implementation) agree
    other = ftc.simulate(ex.x0, TS15, fault=SENSOR_FAULT, backend="fojax")
    ref = ftc.simulate(ex.x0, TS15, fault=SENSOR_FAULT)
    np.testing.assert_allclose(other.x, ref.x, atol=1e-10)
    np.testing.assert_allclose(other.x_ref, ref.x_ref, atol=1e-10)


def test_actuator_ftc():
    ex = fm.example_4_3_2()
    ftc = design_actuator_ftc(ex.system, L=ex.L, R=ex.R, region=Disk(-5.0, 3.0))
    assert np.allclose(ftc.Lbar, np.hstack([ex.L, -np.eye(2)]))
    x0 = np.array([1.0, -1.0, 3.0, -1.0])  # printed x4 = 1 violates the algebraic row
    ts = jnp.linspace(0.0, 25.0, 2501)
    fault = Stack((Step(1.0, 5.0), Step(-0.5, 15.0)))
    u_r = Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 2.0]))
    tr = ftc.simulate(x0, ts, fault=fault, u_r=u_r)
    err = np.linalg.norm(np.asarray(tr.x - tr.x_ref), axis=1)
    t = np.asarray(ts)
    for t_fault, t_next in [(5.0, 15.0), (15.0, 25.0)]:
        window = (t >= t_fault + 6.0) & (t <= t_next)
        assert err[window].max() <= 1e-3
    assert err[(t > 5.0) & (t < 6.0)].max() > 1e-2  # the fault does disturb x first
    # u -> L x - f + u_r (eq. 4.25)
    law = np.asarray(tr.x) @ ex.L.T - np.asarray(tr.f) + np.asarray(tr.u_r)
    assert np.abs(np.asarray(tr.u)[-1] - law[-1]).max() < 1e-6
    with pytest.raises(fojax.errors.ExistenceConditionError, match="actuator-fault matching"):
        design_actuator_ftc(ex.system, Fa=np.eye(4)[:, :1] + np.eye(4)[:, 3:], L=ex.L)


def test_ftc_designs_name_an_unknown_keyword():
    ex = fm.example_4_2_2()
    for design in (design_sensor_ftc, design_actuator_ftc, design_simultaneous_ftc):
        with pytest.raises(TypeError, match=f"{design.__name__}\\(\\) got an unexpected keyword argument 'regoin'"):
            design(ex.system, regoin=Disk(-3.0, 2.0))


def test_simultaneous_ftc():
    ex = fm.example_4_4_2()
    ftc = design_simultaneous_ftc(ex.system, Fs=ex.Fs, L=ex.L, region=Disk(-4.0, 2.0))
    np.testing.assert_allclose(ftc.Lbar, ex.Lbar)  # the resolved L̄ of the example
    tr = ftc.simulate(ex.x0, TS15, fault=SENSOR_FAULT)
    t = np.asarray(TS15)
    f, fh = np.asarray(tr.f), np.asarray(tr.f_hat)
    err = np.abs(fh - f).max(axis=1)
    assert err[(t > 3.0) & (t < 3.5)].max() > 0.1  # the step in f1 is seen ...
    assert err[(t >= 5.5) & (t < 6.0)].max() < 5e-3  # ... and tracked before f2 starts
    assert err[(t >= 9.0)].max() < 1e-3
    assert err[-1] < 1e-7
    assert np.abs(np.asarray(tr.x)[-1]).max() < 1e-6
    X = _equilibrium(ftc.closed_loop, np.array([0.0, 0.0, 1.0, -0.5]))
    assert np.abs(X[:3]).max() < 1e-10


def test_simultaneous_actuator_and_sensor(ex413):
    """Matched actuator faults (F_a = B, the '-I_a' block) and a sensor fault at once."""
    s = ex413.system
    Fs = np.array([[0.0], [0.0], [1.0]])
    ftc = design_simultaneous_ftc(s, Fa=np.asarray(s.B), Fs=Fs, L=ex413.L, region=Disk(-3.0, 2.0))
    assert ftc.Lbar.shape == (5, 7) and np.allclose(ftc.Lbar[:2, 4:6], -np.eye(2))
    fault = Stack((Step(0.5, 2.0), Step(-1.0, 4.0), Step(0.3, 6.0)))
    ts = jnp.linspace(0.0, 20.0, 2001)
    tr = ftc.simulate(np.array([1.0, 0.0, 0.0, -1.0]), ts, fault=fault)
    assert np.abs(np.asarray(tr.f_hat)[-1] - np.array([0.5, -1.0, 0.3])).max() < 1e-5
    assert np.abs(np.asarray(tr.x)[-1]).max() < 1e-5


# --------------------------------------------------------------------------- finite-time loop


@pytest.fixture(scope="module")
def ft_loop():
    ex = fm.example_3_1_2()
    d = design_finite_time_observer(
        ex.system, ex.L, h=ex.h, regions=((ex.alpha1, ex.tau1), (ex.alpha2, ex.tau2))
    )
    return ex, d, finite_time_loop(ex.system, d)


def _method_of_steps(ex, obs, t_end, rtol=1e-13, atol=1e-14):
    """Independent reference: x3 eliminated by hand (row 3 of A, B row 3 = 0), the linear
    right-hand side built column by column from the observer equations (3.5), and each
    interval [kh, (k+1)h] solved with solve_ivp using the previous interval's dense output."""
    E, A, B, C = (np.asarray(v) for v in (ex.E, ex.A, ex.B, ex.C))
    assert np.allclose(B[2], 0) and np.allclose(np.diag(E), [1, 1, 0, 1])
    o1, o2, h = obs.obs1, obs.obs2, float(obs.h)
    assert np.allclose(np.asarray(o1.Wu), 0)  # E⊥B = 0: no algebraic loop here

    def full_x(xd):
        x1, x2, x4 = xd
        return np.array([x1, x2, -(A[2, 0] * x1 + A[2, 1] * x2 + A[2, 3] * x4) / A[2, 2], x4])

    def gdo(o, xi, u, y):
        N, J, F, H, S, G, M = (np.asarray(getattr(o, k)) for k in "NJFHSGM")
        w = np.asarray(o.Wy) @ y
        z, v = xi[: N.shape[0]], xi[N.shape[0] :]
        return np.concatenate([N @ z + J @ v + F @ w + H @ u, S @ z + G @ v + M @ w])

    s1 = o1.state_size
    P1, Q1, Wy1 = (np.asarray(v) for v in (o1.P, o1.Q, o1.Wy))
    Gn, Gd = np.asarray(obs.Gamma_now), np.asarray(obs.Gamma_delay)

    def f(state, xid, delayed):
        x = full_x(state[:3])
        xi = state[3:]
        y = C @ x
        if delayed:
            u = P1 @ (Gn @ xi - Gd @ xid) + Q1 @ (Wy1 @ y)
        else:
            u = P1 @ xi[: o1.q0] + Q1 @ (Wy1 @ y)
        dx = A @ x + B @ u
        return np.concatenate([dx[[0, 1, 3]], gdo(o1, xi[:s1], u, y), gdo(o2, xi[s1:], u, y)])

    N = 3 + 2 * s1
    cols = lambda delayed: np.stack([f(e, np.zeros(2 * s1), delayed) for e in np.eye(N)], axis=1)
    M_pre, M_now = cols(False), cols(True)
    M_del = np.stack([f(np.zeros(N), e, True) for e in np.eye(2 * s1)], axis=1)
    x0 = np.asarray(ex.x0)
    state = np.concatenate([x0[[0, 1, 3]], np.zeros(2 * s1)])
    sols, prev = [], None
    for k in range(int(round(t_end / h))):
        if prev is None:
            rhs = lambda t, z: M_pre @ z
        else:
            rhs = (lambda p: lambda t, z: M_now @ z + M_del @ p.sol(t - h)[3:])(prev)
        sol = solve_ivp(
            rhs,
            (k * h, (k + 1) * h),
            state,
            method="DOP853",
            rtol=rtol,
            atol=atol,
            dense_output=True,
        )
        sols.append(sol)
        state, prev = sol.y[:, -1], sol

    def at(ts):
        out = []
        for t in ts:
            k = min(int(t / h + 1e-9), len(sols) - 1)
            z = sols[k].sol(t)
            out.append(np.concatenate([full_x(z[:3]), z[3:]]))
        return np.array(out)

    return at


@pytest.fixture(scope="module")
def ft_runs(ft_loop):
    """Simulation 1 on [0, 5] s with Δt = h/25, h/50 and h/250 (2 ms)."""
    ex, _, loop = ft_loop
    t_end = 5.0
    runs = {}
    for D in (25, 50, 250):
        ts = jnp.linspace(0.0, t_end, int(round(t_end / ex.h)) * D + 1)
        tr = loop.simulate(ex.x0, ts)
        runs[D] = tuple(np.asarray(v) for v in (tr.ts, tr.x, tr.xi, tr.u))
    return runs


def test_finite_time_loop_stabilises_and_matches_reference(ft_loop, ft_runs):
    ex, d, loop = ft_loop
    h = ex.h
    t, x, xi, u = ft_runs[250]
    assert not fojax.analysis.is_stable(ex.system)  # the open loop is unstable
    assert np.abs(x[0] - ex.x0).max() < 1e-12  # x(0) = [-0.5, 1, 2.5, -1] is consistent
    assert np.abs(x[-1]).max() < 1e-8  # stabilised
    # finite time: for t >= h the estimate is the control law Lx exactly
    post = t >= h
    assert np.abs(u[post] - x[post] @ np.asarray(ex.L).T).max() < 1e-8
    assert np.abs(u[~post] - x[~post] @ np.asarray(ex.L).T).max() > 1e-2
    # independent reference (method of steps)
    ref = _method_of_steps(ex, d.observer, float(t[-1]))(t)
    scale = np.abs(ref[:, :4]).max()
    err = np.abs(x - ref[:, :4]).max() / scale
    assert err < 1e-8, err  # documented tolerance (measured ~3e-10, limited by DOP853)
    assert np.abs(xi - ref[:, 4:]).max() / np.abs(ref[:, 4:]).max() < 1e-8
    # for t >= h the states follow (E, A + BL) from x(h): closed form with SciPy expm
    E, A, B = (np.asarray(v) for v in (ex.E, ex.A, ex.B))
    Acl = A + B @ np.asarray(ex.L)
    k_h = int(np.argmax(post))
    idx = [0, 1, 3]
    # eliminate x3 with row 3 of A + BL (B row 3 = 0): x3 = -(Acl[2, idx] @ xd) / Acl[2, 2]
    elim = -Acl[2, idx] / Acl[2, 2]
    As = Acl[np.ix_(idx, idx)] + np.outer(Acl[idx, 2], elim)
    for j in (k_h + 100, k_h + 500, len(t) - 1):
        xd = sl.expm(As * (t[j] - t[k_h])) @ x[k_h, idx]
        assert np.abs(xd - x[j, idx]).max() < 1e-8 * max(1.0, np.abs(x[k_h]).max())


def test_finite_time_loop_fourth_order(ft_loop, ft_runs):
    """Self-convergence of the delay integrator: halving Δt divides the error by ~16."""
    ex, _, loop = ft_loop
    fine = ft_runs[250][1]
    e25 = np.abs(ft_runs[25][1] - fine[::10]).max()
    e50 = np.abs(ft_runs[50][1] - fine[::5]).max()
    assert 8.0 < e25 / e50 < 32.0, (e25, e50)
    with pytest.raises(fojax.errors.InputError, match="multiple of the grid step"):
        loop.simulate(ex.x0, jnp.linspace(0.0, 1.0, 8))
    # vmap over initial states (linear loop: the trajectory from 2 x0 is twice that from x0)
    ts = jnp.linspace(0.0, 5.0, 10 * 25 + 1)
    batch = jax.vmap(lambda x0: loop.simulate(x0, ts).x)(jnp.stack([ex.x0, 2.0 * ex.x0]))
    np.testing.assert_allclose(batch[0], ft_runs[25][1], atol=1e-12)
    np.testing.assert_allclose(batch[1], 2.0 * ft_runs[25][1], atol=1e-11)


def test_simulate_lti_matches_scipy(ex413, design413):
    """The exact stepper against a SciPy expm solution of the reduced loop (zero input)."""
    loop = closed_loop(ex413.system, design413, u_r=np.zeros((2, 0)))
    x0 = np.concatenate([[16.0, -1.0, 3.0, 14.0], np.zeros(4)])
    ts = jnp.linspace(0.0, 2.0, 201)
    xs, _ = simulate_lti(loop, x0, ts, Zero(0))
    # reduce by hand: the algebraic row of E is row 4 (index 3)
    E, A = np.asarray(loop.E), np.asarray(loop.A)
    assert np.allclose(E, np.diag([1, 1, 1, 0, 1, 1, 1, 1]))
    d = [i for i in range(8) if i != 3]
    elim = -A[3, d] / A[3, 3]
    As = A[np.ix_(d, d)] + np.outer(A[d, 3], elim)
    for j in (50, 200):
        z = sl.expm(As * float(ts[j])) @ x0[d]
        np.testing.assert_allclose(np.asarray(xs[j])[d], z, atol=1e-10)
        assert abs(float(xs[j][3]) - elim @ z) < 1e-10
