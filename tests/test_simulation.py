"""Simulation layer: index-1 reduction, consistent initial conditions, `simulate`.

References are independent of fojax: the descriptor systems used here have a
diagonal ``E``, so each is reduced *by hand* (NumPy, index partition of ``E``'s
zero diagonal) to an ODE in the differential variables and integrated with SciPy's
``solve_ivp`` (DOP853 / Radau, rtol 1e-12), piecewise across input jumps.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

# Thesis example 4.1.3 (closed loop u = Lx, eigenvalues -1.70 ± 1.99i, -39.78), from
# tests/closed_loop_413.py; X0_413 is inconsistent: x4 must equal x1 + 2 x2 = 14.
from closed_loop_413 import (
    ACL as ACL413,
    B0 as B413,
    C0 as C413,
    E as E413,
    X0 as X0_413,
)
from helpers import assert_eigenvalues_match
from scipy.integrate import solve_ivp

import fojax
from fojax.observer import AbstractObserver, LinearObserverMatrices

# private: TRACE_COUNTS, the no-retrace check
from fojax.simulation._simulate import TRACE_COUNTS


# --------------------------------------------------------------------------- models

# Thesis example of section 3.1 (finite-time observer): a stiff closed loop with a
# pole near -275. The thesis prints "A - BL"; its poles belong to A + BL.
E31 = np.diag([1.0, 1.0, 0.0, 1.0])
A31 = np.array(
    [[-1.0, 3.0, 0.0, 1.0], [1.0, -7.0, 2.5, 3.0], [3.0, -1.0, 1.0, 0.0], [2.0, -3.1, -2.2, 0.5]]
)
B31 = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0], [0.0, 0.0]])
C31 = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
L31 = np.array([[-30.09, -8.39, 67.22, -1.96], [12.83, -6.5, -47.24, 24.11]])
ACL31 = A31 + B31 @ L31
X0_31 = np.array([-0.5, 1.0, 2.5, -1.0])

TS = np.linspace(0.0, 5.0, 501)
STEP_T = 0.5
STEP_AMP = np.array([1.0, -0.5])
SINE_AMP = np.array([0.3, 0.2])
SINE_OMEGA = 3.0

# Flexible single-link robot arm (thesis eq. 3.188, Table 3.1), gravity restoring.
ROBOT = dict(Jm=0.01, Jl=0.08, m=0.15, lc=0.25, k=0.3, beta=0.05, Ktau=0.2, l=0.18, g=9.81)
ROBOT_TS = np.linspace(0.0, 5.0, 251)
ROBOT_X0 = np.array([0.2, 0.0, 0.5, 0.0, 0.3])  # x5 inconsistent (should be l sin x3)
ROBOT_U_AMP, ROBOT_U_OMEGA = 0.5, 2.0
ROBOT_TOL = dict(stepper=fojax.Auto(diffrax=fojax.Diffrax(rtol=1e-10, atol=1e-12)))
#: what `simulate` runs for each method name of the parametrized tests
STEPPERS = {"exact": fojax.Exact(), "diffrax": fojax.Diffrax()}


def robot_f(x, u, th):
    x1, x2, x3, x4, x5 = x
    return jnp.stack(
        [
            x2,
            -th["beta"] / th["Jm"] * x2 - th["k"] / th["Jm"] * (x1 - x3) + th["Ktau"] / th["Jm"] * u[0],
            x4,
            th["k"] / th["Jl"] * (x1 - x3) - th["lc"] * th["m"] * th["g"] / th["Jl"] * jnp.sin(x3),
            th["l"] * jnp.sin(x3) - x5,
        ]
    )


def robot_g(x, th):
    return jnp.stack([x[0], x[2]])


def robot_plant(**override):
    theta = {k: jnp.asarray(float(override.get(k, v))) for k, v in ROBOT.items()}
    return fojax.NonlinearDescriptorSystem(
        jnp.diag(jnp.array([1.0, 1.0, 1.0, 1.0, 0.0])), robot_f, robot_g, theta, m=1, p=2
    )


def robot_input():
    return fojax.Sine(jnp.array([ROBOT_U_AMP]), ROBOT_U_OMEGA)


# --------------------------------------------------------------------------- references


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def hand_reduced(E, A, B):
    """Reduce a descriptor system with *diagonal* E by index partition (no SVD).

    Returns ``(d, a, rhs(xd, u), full(xd, u))`` with differential indices ``d``,
    algebraic ``a``; ``x_a = -A_aa^{-1}(A_ad x_d + B_a u)``.
    """
    e = np.diag(E)
    d, a = np.flatnonzero(e != 0), np.flatnonzero(e == 0)
    Add, Ada, Aad, Aaa = A[np.ix_(d, d)], A[np.ix_(d, a)], A[np.ix_(a, d)], A[np.ix_(a, a)]
    Bd, Ba = B[d], B[a]

    def alg(xd, u):
        return -np.linalg.solve(Aaa, Aad @ xd + Ba @ u)

    def rhs(xd, u):
        return (Add @ xd + Ada @ alg(xd, u) + Bd @ u) / e[d]

    def full(xd, u):
        x = np.empty(E.shape[0])
        x[d], x[a] = xd, alg(xd, u)
        return x

    return d, a, rhs, full


def scipy_trajectory(rhs, xd0, ts, breaks=(), method="DOP853"):
    """Integrate ``ẋd = rhs(t, xd)`` piecewise between `breaks`; values on `ts`."""
    edges = [ts[0], *[b for b in breaks if ts[0] < b < ts[-1]], ts[-1]]
    out, x = np.empty((len(ts), len(xd0))), np.asarray(xd0, dtype=float)
    for a, b in zip(edges[:-1], edges[1:]):
        last = b == edges[-1]
        mask = (ts >= a) & ((ts <= b) if last else (ts < b))
        sol = solve_ivp(
            rhs, (a, b), x, method=method, rtol=1e-12, atol=1e-14, t_eval=ts[mask], dense_output=True
        )
        assert sol.success, sol.message
        out[mask] = sol.y.T
        x = sol.sol(b)
    return out


def u413(t, with_input):
    if not with_input:
        return np.zeros(2)
    return STEP_AMP * (t >= STEP_T) + SINE_AMP * np.sin(SINE_OMEGA * t)


def reference_413(with_input):
    d, _, rhs, full = hand_reduced(E413, ACL413, B413)
    xd = scipy_trajectory(
        lambda t, x: rhs(x, u413(t, with_input)), X0_413[d], TS, breaks=[STEP_T] if with_input else []
    )
    return np.stack([full(x, u413(t, with_input)) for t, x in zip(TS, xd)])


def robot_reference():
    p = ROBOT

    def rhs(t, x):
        u = ROBOT_U_AMP * np.sin(ROBOT_U_OMEGA * t)
        return [
            x[1],
            -p["beta"] / p["Jm"] * x[1] - p["k"] / p["Jm"] * (x[0] - x[2]) + p["Ktau"] / p["Jm"] * u,
            x[3],
            p["k"] / p["Jl"] * (x[0] - x[2]) - p["lc"] * p["m"] * p["g"] / p["Jl"] * np.sin(x[2]),
        ]

    xd = scipy_trajectory(rhs, ROBOT_X0[:4], ROBOT_TS)
    return np.column_stack([xd, p["l"] * np.sin(xd[:, 2])])


def input413(with_input):
    if not with_input:
        return None
    return fojax.Step(jnp.asarray(STEP_AMP), STEP_T) + fojax.Sine(jnp.asarray(SINE_AMP), SINE_OMEGA)


def zero_input413():
    """u = 0 with the step + sine's structure: a diffrax solve compiled for it is reused."""
    return jax.tree.map(jnp.zeros_like, input413(True))


@pytest.fixture(scope="module")
def plant413():
    return fojax.DescriptorSystem(E413, ACL413, B413, C413)


@pytest.fixture(scope="module")
def refs413():
    return {w: reference_413(w) for w in (False, True)}


@pytest.fixture(scope="module")
def robot_solution():
    return fojax.simulate(robot_plant(), ROBOT_X0, ROBOT_TS, robot_input(), **ROBOT_TOL)


# --------------------------------------------------------------------------- reduction / IC


def test_reduce_index1_poles_and_maps(plant413):
    red = fojax.simulation.reduce_index1(plant413)
    poles = scipy.linalg.eigvals(ACL413, E413)
    poles = poles[np.isfinite(poles)]
    assert_eigenvalues_match(np.linalg.eigvals(red.As), poles, rtol=1e-10)
    # Thesis: eigenvalues of (E, A + BL) are -1.7 ± 1.99i and -39.78 (printed truncated;
    # -39.7897, -1.6977 ± 1.9907i).
    assert_eigenvalues_match(poles, [-39.79, -1.70 + 1.99j, -1.70 - 1.99j], atol=0.01, rtol=0.0)
    # Any slow state and input map back onto the constraint 0 = row 4 of (A x + B u).
    x1, u = jnp.array([0.3, -1.2, 2.0]), jnp.array([0.7, -0.4])
    x = red.state(x1, u)
    assert abs(float(ACL413[3] @ x + B413[3] @ u)) < 1e-12
    np.testing.assert_allclose(red.slow(x), x1, atol=1e-12)
    np.testing.assert_allclose(red.Cs @ x1 + red.Ds @ u, C413 @ x, atol=1e-12)


def test_consistent_initial_condition_keeps_slow_part(plant413):
    x0c, dist = fojax.simulation.consistent_initial_condition(plant413, X0_413)
    np.testing.assert_allclose(x0c, [16.0, -1.0, 3.0, 14.0], atol=1e-12)  # x4 = x1 + 2 x2
    assert abs(float(dist) - 7.0) < 1e-12
    np.testing.assert_allclose(E413 @ np.asarray(x0c), E413 @ X0_413, atol=1e-12)
    # Nonlinear: x5 = l sin(x3), Newton from the given x5.
    x0c, dist = fojax.simulation.consistent_initial_condition(robot_plant(), ROBOT_X0, u=robot_input())
    x5 = ROBOT["l"] * np.sin(ROBOT_X0[2])
    np.testing.assert_allclose(x0c, [*ROBOT_X0[:4], x5], atol=1e-14)
    assert abs(float(dist) - abs(ROBOT_X0[4] - x5)) < 1e-14


# --------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("with_input", [False, True], ids=["autonomous", "step+sine"])
@pytest.mark.parametrize("method", ["exact", "diffrax"])
def test_thesis_413_against_scipy(plant413, refs413, method, with_input):
    u = input413(with_input)
    if method == "diffrax" and not with_input:
        u = zero_input413()
    sol = fojax.simulate(plant413, X0_413, TS, u, stepper=STEPPERS[method])
    assert sol.method == method
    assert rel_err(sol.xs, refs413[with_input]) <= 1e-6
    assert float(sol.stats["constraint_residual"]) <= 1e-8
    assert abs(float(sol.stats["projection_distance"]) - 7.0) < 1e-12
    np.testing.assert_allclose(sol.ys, sol.xs @ C413.T, atol=1e-12)
    np.testing.assert_allclose(sol.us[:, 0], [u413(t, with_input)[0] for t in TS], atol=1e-15)
    if method == "exact":  # exact for the zero input, Gauss product rule otherwise
        assert rel_err(sol.xs, refs413[with_input]) <= 1e-10


def test_auto_picks_exact_then_falls_back(plant413, refs413):
    assert fojax.simulate(plant413, X0_413, TS).method == "exact"
    # A step between grid points: the exact stepper would lose accuracy -> diffrax.
    u = fojax.Step(jnp.asarray(STEP_AMP), STEP_T + 0.003) + fojax.Sine(jnp.asarray(SINE_AMP), 1.0)
    assert fojax.simulate(plant413, X0_413, TS, u).method == "diffrax"
    # A non-uniform grid -> diffrax, and still right. (Zero input with the step + sine's
    # structure and a grid of the same length: the diffrax solve compiled for §4.1.3 above
    # is reused.)
    ts = TS + 0.004 * np.sin(np.pi * TS / 5.0) ** 2
    sol = fojax.simulate(plant413, X0_413, ts, zero_input413())
    assert sol.method == "diffrax"
    d, _, rhs, full = hand_reduced(E413, ACL413, B413)
    xd = scipy_trajectory(lambda t, x: rhs(x, np.zeros(2)), X0_413[d], ts)
    ref = np.stack([full(x, np.zeros(2)) for x in xd])
    assert rel_err(sol.xs, ref) <= 1e-6
    with pytest.raises(fojax.errors.InputError, match="uniform grid"):
        fojax.simulate(plant413, X0_413, ts, stepper=fojax.Exact())


@pytest.fixture(scope="module")
def ref31():
    """SciPy's Radau reference of the stiff §3.1 loop on TS (computed once, for both methods)."""
    d, _, rhs, full = hand_reduced(E31, ACL31, B31)
    xd = scipy_trajectory(lambda t, x: rhs(x, np.zeros(2)), X0_31[d], TS, method="Radau")
    return np.stack([full(x, np.zeros(2)) for x in xd])


@pytest.mark.parametrize("method", ["exact", "diffrax"])
def test_stiff_thesis_31_against_scipy(method, ref31):
    poles = scipy.linalg.eigvals(ACL31, E31)
    assert np.min(poles[np.isfinite(poles)].real) < -270  # the stiff pole near -275
    # Same shapes as example 4.1.3 (and, for diffrax, the same zero input with the step +
    # sine's structure): the compiled simulations of test_thesis_413_against_scipy are reused.
    u = zero_input413() if method == "diffrax" else None
    plant = fojax.DescriptorSystem(E31, ACL31, B31, C31)
    sol = fojax.simulate(plant, X0_31, TS, u, stepper=STEPPERS[method])
    assert rel_err(sol.xs, ref31) <= 1e-6
    assert float(sol.stats["constraint_residual"]) <= 1e-8


def test_robot_arm_against_scipy(robot_solution):
    sol = robot_solution
    assert sol.method == "diffrax"
    assert rel_err(sol.xs, robot_reference()) <= 1e-6
    assert float(sol.stats["constraint_residual"]) <= 1e-8
    np.testing.assert_allclose(sol.ys, sol.xs[:, [0, 2]], atol=0)
    x5 = ROBOT["l"] * np.sin(ROBOT_X0[2])
    assert abs(float(sol.stats["projection_distance"]) - abs(ROBOT_X0[4] - x5)) < 1e-14


def test_time_varying_uncertainty_against_scipy(plant413):
    # δ(t) = 0.5 sin(2t) moves A[0, 0] and the algebraic row (A[3, 0]).
    dA = np.zeros((1, 4, 4))
    dA[0, 0, 0], dA[0, 3, 0] = 1.0, 0.4
    uds = fojax.UncertainDescriptorSystem(plant413, dA=dA, delta=fojax.Sine(jnp.array([0.5]), 2.0))
    ts = np.linspace(0.0, 3.0, 301)
    sol = fojax.simulate(uds, X0_413, ts)
    assert sol.method == "diffrax"

    def parts(t):
        return hand_reduced(E413, ACL413 + 0.5 * np.sin(2 * t) * dA[0], B413)

    xd = scipy_trajectory(lambda t, x: parts(t)[2](x, np.zeros(2)), X0_413[:3], ts)
    ref = np.stack([parts(t)[3](x, np.zeros(2)) for t, x in zip(ts, xd)])
    assert rel_err(sol.xs, ref) <= 1e-6
    assert float(sol.stats["constraint_residual"]) <= 1e-8
    # A constant δ is time-invariant: the exact stepper is used and equals the frozen system.
    uds_c = fojax.UncertainDescriptorSystem(plant413, dA=dA, delta=jnp.array([0.3]))
    sol_c = fojax.simulate(uds_c, X0_413, TS)
    ref_c = fojax.simulate(fojax.DescriptorSystem(E413, ACL413 + 0.3 * dA[0], B413, C413), X0_413, TS)
    assert sol_c.method == "exact"
    np.testing.assert_allclose(sol_c.xs, ref_c.xs, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- compilation, vmap


def test_no_retrace_on_new_numbers(plant413, robot_solution):
    fojax.simulate(plant413, X0_413, TS)  # compiled (cached) structure
    before = TRACE_COUNTS["simulate"]
    other = fojax.DescriptorSystem(E413, ACL413 * 1.01, B413, C413)
    sol = fojax.simulate(other, X0_413 + 1.0, TS)
    rob = fojax.simulate(
        robot_plant(k=0.35, beta=0.06), ROBOT_X0 * 0.9, ROBOT_TS, robot_input(), **ROBOT_TOL
    )
    assert TRACE_COUNTS["simulate"] == before
    assert np.all(np.isfinite(sol.xs)) and np.all(np.isfinite(rob.xs))
    assert not np.allclose(rob.xs, robot_solution.xs)


def test_vmap_over_1000_parameter_samples(plant413):
    rng = np.random.default_rng(0)
    nb = 1000
    dA = np.zeros((nb, 4, 4))
    dA[:, :3, :] = 0.05 * rng.standard_normal((nb, 3, 4))  # the algebraic row stays put
    x0s = X0_413 + rng.standard_normal((nb, 4))
    ts = np.linspace(0.0, 2.0, 101)

    @eqx.debug.assert_max_traces(max_traces=1)
    def one(dA_i, x0_i):
        plant = fojax.DescriptorSystem(E413, ACL413 + dA_i, B413)
        sol = fojax.simulate(plant, x0_i, ts)
        return sol.xs, sol.stats["constraint_residual"]

    batched = eqx.filter_jit(jax.vmap(one))
    before = TRACE_COUNTS["simulate"]
    xs, res = batched(jnp.asarray(dA), jnp.asarray(x0s))
    xs2, _ = batched(jnp.asarray(dA[::-1]), jnp.asarray(x0s[::-1]))  # new numbers: no retrace
    assert TRACE_COUNTS["simulate"] == before + 1
    assert xs.shape == (nb, ts.size, 4)
    assert float(jnp.max(res)) <= 1e-8
    for i in (0, 17, nb - 1):
        single = fojax.simulate(fojax.DescriptorSystem(E413, ACL413 + dA[i], B413), x0s[i], ts)
        np.testing.assert_allclose(xs[i], single.xs, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(xs2[0], xs[-1], rtol=1e-12, atol=1e-10)


def test_vmap_diffrax_path_over_robot_parameters(robot_solution):
    ks = jnp.array([0.25, 0.3, 0.35, 0.4])

    def one(k):
        plant = robot_plant()
        plant = eqx.tree_at(lambda p: p.theta["k"], plant, k)
        return fojax.simulate(plant, ROBOT_X0, ROBOT_TS, robot_input(), throw=False, **ROBOT_TOL)

    sols = jax.vmap(one)(ks)
    assert bool(jnp.all(sols.stats["success"]))
    np.testing.assert_allclose(sols.xs[1], robot_solution.xs, rtol=1e-9, atol=1e-11)
    assert float(jnp.max(sols.stats["constraint_residual"])) <= 1e-8


# --------------------------------------------------------------------------- gradients


def test_grad_exact_path_matches_finite_differences(plant413):
    u = input413(True)
    ts = np.linspace(0.0, 2.0, 201)
    dt = ts[1] - ts[0]

    def cost(a):
        A = jnp.asarray(ACL413).at[0, 1].add(a)
        sol = fojax.simulate(fojax.DescriptorSystem(E413, A, B413, C413), X0_413, ts, u)
        return jnp.sum(sol.xs**2) * dt

    # One compiled program (the cost and its reverse pass) gives the gradient and the three
    # cost values the central difference needs: jax.grad outside jit and cost() besides it
    # compiled three (forward with residuals, transpose, forward alone).
    vg = jax.jit(jax.value_and_grad(cost))
    g = float(vg(jnp.asarray(0.0))[1])
    h = 1e-3  # cost ~157 is evaluated to ~1e-12 relative: smaller h amplifies that noise
    fd = (float(vg(jnp.asarray(h))[0]) - float(vg(jnp.asarray(-h))[0])) / (2 * h)
    assert abs(g - fd) <= 1e-5 * abs(fd)


def test_grad_diffrax_path_matches_finite_differences():
    # Reverse mode through the reduction, the algebraic (Newton) solve for x5 and the
    # adaptive diffrax solve, over the first 1.5 s of the robot run. Tsit5 rather than the
    # default Kvaerno5: the fojax parts differentiated are the same, and compiling the
    # reverse pass of the implicit solver took 44 s alone (the whole test 130 s of the CI
    # run); Tsit5 15 s. Forward Kvaerno5 is checked against SciPy above and under vmap below.
    ts = ROBOT_TS[:76]
    dt = ts[1] - ts[0]
    u = robot_input()

    def cost(k):
        plant = eqx.tree_at(lambda p: p.theta["k"], robot_plant(), k)
        sol = fojax.simulate(plant, ROBOT_X0, ts, u,
                             stepper=fojax.Auto(diffrax=fojax.Diffrax(diffrax.Tsit5(), rtol=1e-10, atol=1e-12)))
        return jnp.sum(sol.xs**2) * dt

    k0 = ROBOT["k"]
    # One compiled program (the cost and its reverse pass) gives the gradient and the cost
    # values of the central difference (as in test_tuning_ts): jax.grad outside jit and
    # cost() besides it compiled three programs, the adaptive solve in each.
    vg = jax.jit(jax.value_and_grad(cost))
    g = float(vg(jnp.asarray(k0))[1])
    h = 1e-4
    fd = (float(vg(jnp.asarray(k0 + h))[0]) - float(vg(jnp.asarray(k0 - h))[0])) / (2 * h)
    assert abs(g - fd) <= 1e-5 * abs(fd)


# --------------------------------------------------------------------------- observers


class FilterObserver(AbstractObserver):
    """An LTI filter ``ξ̇ = Ao ξ + Bu u + By y``, ``ẑ = Co ξ + Du u + Dy y``."""

    Ao: jax.Array
    Bu: jax.Array
    By: jax.Array
    Co: jax.Array
    Du: jax.Array
    Dy: jax.Array
    linear: bool = eqx.field(static=True, default=True)

    @property
    def state_size(self):
        return self.Ao.shape[0]

    @property
    def output_size(self):
        return self.Co.shape[0]

    def vector_field(self, t, xi, u, y):
        return self.Ao @ xi + self.Bu @ u + self.By @ y

    def output(self, t, xi, u, y):
        return self.Co @ xi + self.Du @ u + self.Dy @ y

    def linear_matrices(self):
        if not self.linear:
            return None  # forces the diffrax path
        return LinearObserverMatrices(self.Ao, self.Bu, self.By, self.Co, self.Du, self.Dy)


def _filter(linear):
    # A stiff filter: a pole at -2000 and gains in the thousands, as in the thesis.
    return FilterObserver(
        Ao=jnp.array([[-3.0, 1.0], [0.0, -2000.0]]),
        Bu=jnp.array([[1.0, 0.0], [0.5, -1.0]]),
        By=jnp.array([[2.0, -1.0, 0.5], [0.0, 1500.0, 3000.0]]),
        Co=jnp.eye(2),
        Du=jnp.array([[0.1, 0.0], [0.0, 0.2]]),
        Dy=jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),
        linear=linear,
    )


def test_observer_estimates_equal_joint_system(plant413):
    obs = _filter(True)
    xi0 = jnp.array([1.0, -2.0])
    u = input413(True)
    # Hand-assembled joint descriptor system [x; ξ] with output ẑ - Du u = Co ξ + Dy C x.
    Ej = scipy.linalg.block_diag(E413, np.eye(2))
    Aj = np.block([[ACL413, np.zeros((4, 2))], [np.asarray(obs.By) @ C413, np.asarray(obs.Ao)]])
    Bj = np.vstack([B413, np.asarray(obs.Bu)])
    Cj = np.hstack([np.asarray(obs.Dy) @ C413, np.asarray(obs.Co)])
    joint = fojax.DescriptorSystem(Ej, Aj, Bj, Cj)
    ref = fojax.simulate(joint, np.concatenate([X0_413, xi0]), TS, u, stepper=fojax.Exact())
    ref_z = ref.ys + ref.us @ np.asarray(obs.Du).T
    sol = fojax.simulate(plant413, X0_413, TS, u, observers=(obs,), observer_x0=(xi0,))
    assert sol.method == "exact"
    np.testing.assert_allclose(sol.xs, ref.xs[:, :4], rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sol.observer_states[0], ref.xs[:, 4:], rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sol.estimates[0], ref_z, rtol=1e-11, atol=1e-11)
    # The same observer without linear_matrices() goes through diffrax.
    sol_d = fojax.simulate(plant413, X0_413, TS, u, observers=(_filter(False),), observer_x0=(xi0,))
    assert sol_d.method == "diffrax"
    assert rel_err(sol_d.estimates[0], ref_z) <= 1e-6
    assert rel_err(sol_d.xs, ref.xs[:, :4]) <= 1e-6


# --------------------------------------------------------------------------- bad input


def test_irregular_pencil_is_refused():
    sys = fojax.DescriptorSystem(np.diag([1.0, 0.0]), np.diag([-1.0, 0.0]))
    with pytest.raises(fojax.errors.IrregularSystemError, match=r"singular for every s.*not regular"):
        fojax.simulate(sys, np.zeros(2), TS)
    with pytest.raises(fojax.errors.IrregularSystemError):
        fojax.simulation.reduce_index1(sys)


def test_impulsive_system_is_refused():
    # E nilpotent, A = I: regular (det(sE - A) = 1) but index 2.
    E = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    A = np.diag([-1.0, 1.0, 1.0])
    sys = fojax.DescriptorSystem(E, A)
    msg = r"Ã22 = U2ᵀ A V2 .* is singular .*impulsive modes \(index > 1\); fojax simulates index-1"
    with pytest.raises(fojax.errors.ImpulsiveSystemError, match=msg):
        fojax.simulate(sys, np.zeros(3), TS)
    with pytest.raises(fojax.errors.ImpulsiveSystemError, match="impulsive modes"):
        fojax.simulation.reduce_index1(sys)


def _index2_f(x, u, th):
    return jnp.stack([-x[0] + x[1], x[0] - x[1] ** 3])


def test_nonlinear_index_check_at_initial_point():
    # ∂(x1 - x2³)/∂x2 = -3 x2² vanishes at x2 = 0: index > 1 at the initial point.
    plant = fojax.NonlinearDescriptorSystem(
        np.diag([1.0, 0.0]), _index2_f, lambda x, th: x, {}, m=0, p=2
    )
    with pytest.raises(fojax.errors.ImpulsiveSystemError, match=r"U2ᵀ ∂f/∂x V2.*at the initial point"):
        fojax.simulate(plant, np.array([0.0, 0.0]), TS)


def test_inconsistent_x0_strict_raises(plant413):
    with pytest.raises(
        fojax.errors.InconsistentInitialConditionError, match=r"violates the algebraic constraints by 7\.0"
    ):
        fojax.simulate(plant413, X0_413, TS, strict=True)
    with pytest.raises(fojax.errors.InconsistentInitialConditionError):
        fojax.simulation.consistent_initial_condition(plant413, X0_413, strict=True)
    x0c, _ = fojax.simulation.consistent_initial_condition(plant413, X0_413)
    sol = fojax.simulate(plant413, x0c, TS, strict=True)  # consistent: accepted
    assert float(sol.stats["projection_distance"]) < 1e-12


def test_bad_shapes_and_arguments(plant413):
    with pytest.raises(fojax.errors.ShapeError, match=r"x0 has shape \(3,\), expected \(4,\)"):
        fojax.simulate(plant413, np.zeros(3), TS)
    with pytest.raises(fojax.errors.ShapeError, match="input signal"):
        fojax.simulate(plant413, X0_413, TS, fojax.Step(jnp.ones(3)))
    with pytest.raises(fojax.errors.ShapeError, match=r"observer_x0\[0\]"):
        fojax.simulate(plant413, X0_413, TS, observers=(_filter(True),), observer_x0=(jnp.ones(3),))
    with pytest.raises(fojax.errors.InputError, match="strictly increasing"):
        fojax.simulate(plant413, X0_413, TS[::-1])
    with pytest.raises(fojax.errors.InputError, match=r"stepper Exact\(\) needs a linear time-invariant"):
        fojax.simulate(robot_plant(), ROBOT_X0, ROBOT_TS, robot_input(), stepper=fojax.Exact())


def test_batch_of_plants_with_different_E_inside_jit():
    # E is traced here, and differs between samples (E and 2E: slow dynamics halved).
    ts = np.linspace(0.0, 2.0, 101)
    scales = jnp.array([1.0, 2.0])

    def one(c):
        sol = fojax.simulate(fojax.DescriptorSystem(c * E413, ACL413, B413), X0_413, ts)
        return sol.xs

    xs = eqx.filter_jit(jax.vmap(one))(scales)
    for i, c in enumerate((1.0, 2.0)):
        ref = fojax.simulate(fojax.DescriptorSystem(c * E413, ACL413, B413), X0_413, ts).xs
        np.testing.assert_allclose(xs[i], ref, rtol=1e-12, atol=1e-11)
    assert not np.allclose(xs[0], xs[1])
    with pytest.raises(fojax.errors.InputError, match="rank_E"):
        jax.jit(lambda E: fojax.simulation.reduce_index1(fojax.DescriptorSystem(E, ACL413, B413)).As)(E413)
