"""Unknown-input functional observers (§3.2): `fojax.design_unknown_input_observer`,
`fojax.UnknownInputObserver`: design, verification, existence conditions and simulation.

Oracles: the unknown-input conditions a.–f. recomputed with NumPy from the returned matrices;
the §4.1.3 closed loop integrated by SciPy's ``solve_ivp`` (x4 eliminated by hand from the
algebraic row); the error's closed form ``expm(𝔸 t) σ(0)`` (``scipy.linalg.expm``); the
estimate of a constant unknown input; NumPy eigenvalues and ``eigvalsh`` of the region LMI at
the returned certificate; for the badly scaled twin, the same closed form in physical units.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

import fojax
from fojax.design import (
    design_unknown_input_observer,
    Disk,
    pieces,
    unknown_input_observer_matrices,
    unknown_input_residuals,
)
from fojax.models import example_4_1_3


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


# --------------------------------------------------------------------------- unknown input

UIO_D = np.eye(4)[:, [2]]  # unknown input in the differential row of x3 (not measured)
UIO_DVAL = 0.7
UIO_TS = np.linspace(0.0, 10.0, 201)
UIO_X0 = np.array([1.0, -0.5, 0.3, 0.0])  # consistent: x4 = x1 + 2 x2 (algebraic row of 4.1.3)


@pytest.fixture(scope="module")
def plant413cl():
    """§4.1.3's plant in closed loop with its state feedback u = Lx + u_r (stable)."""
    ex = example_4_1_3()
    E, A, B, C, L = (np.asarray(x) for x in (ex.E, ex.A, ex.B, ex.C, ex.L))
    return E, A + B @ L, B, C, L


@pytest.fixture(scope="module")
def uio(plant413cl):
    E, A, B, C, L = plant413cl
    return design_unknown_input_observer(fojax.DescriptorSystem(E, A, B, C), UIO_D, L)


def test_uio_design_verifies_conditions_a_to_f(plant413cl, uio):
    E, A, B, C, L = plant413cl
    o = uio.observer
    assert uio.report.passed and uio.report.relative_residual <= 1e-8
    assert set(uio.report.residuals) == set("abcdef")
    # E⊥ annihilates [E D]; conditions a.–f. of Lemma 9 recomputed here.
    Ep = np.asarray(uio.structure.Eperp)
    np.testing.assert_allclose(Ep @ np.hstack([E, UIO_D]), 0.0, atol=1e-14)
    Psi = np.vstack([Ep @ A, C])
    T = uio.T
    TE = T @ E
    s = 1e-10 * max(1.0, np.abs(np.asarray(o.F)).max(), np.abs(np.asarray(o.W)).max()) * np.abs(A).max()
    assert np.abs(o.N @ TE + o.F @ Psi - T @ A).max() <= s
    assert np.abs(o.H - T @ B).max() <= s
    assert np.abs(o.Delta - T @ UIO_D).max() <= s
    assert np.abs(o.S @ TE + o.M @ Psi).max() <= s
    assert np.abs(o.Phi @ TE - o.W @ Psi).max() <= s
    assert np.abs(o.P @ TE + o.Q @ Psi - L).max() <= s
    # Φ = -Y4 N3, W = Y4 F3 (the exact solution of e.).
    pc = pieces(uio.structure, xp=np)
    np.testing.assert_allclose(o.Phi, -uio.params["Y4"] @ np.asarray(pc.N3), atol=1e-12)
    # 𝔸 has the structure [[N, J, Δ], [S, G, 0], [Φ, Λ, 0]] and its eigenvalues in the disk.
    Aa = uio.error_matrix
    q0, q1 = o.q0, o.q1
    assert not np.any(Aa[q0 : q0 + q1, q0 + q1 :]) and not np.any(Aa[q0 + q1 :, q0 + q1 :])
    assert Disk(-2.0, 1.0).contains(np.linalg.eigvals(Aa))


def _uio_reference(plant413cl, o):
    """SciPy on the hand-reduced ODE (x4 = x1 + 2 x2) and eq. 3.110 written out."""
    E, A, B, C, L = plant413cl
    N, J, F, H, De, S, G, M, Phi, Lam, W, P, Q, Wu, Wy = (
        np.asarray(getattr(o, k))
        for k in "N J F H Delta S G M Phi Lambda W P Q Wu Wy".split()
    )
    q0, q1 = o.q0, o.q1

    def u_of(t):
        return np.array([1.0, -0.5]) * (t >= 0.5) + np.array([0.3, 0.2]) * math.sin(3.0 * t)

    def full(xd):
        return np.array([xd[0], xd[1], xd[2], xd[0] + 2.0 * xd[1]])

    def rhs(t, s):
        x = full(s[:3])
        u = u_of(t)
        dx = (A @ x + B @ u + UIO_D[:, 0] * UIO_DVAL)[:3]
        y = C @ x
        w = Wu @ u + Wy @ y
        zeta, v, dh = s[3 : 3 + q0], s[3 + q0 : 3 + q0 + q1], s[3 + q0 + q1 :]
        return np.concatenate(
            [dx, N @ zeta + J @ v + F @ w + H @ u + De @ dh, S @ zeta + G @ v + M @ w, Phi @ zeta + Lam @ v - W @ w]
        )

    s0 = np.concatenate([UIO_X0[:3], np.zeros(o.state_size)])
    out = np.empty((len(UIO_TS), len(s0)))
    for a, b, mask in [(0.0, 0.5, UIO_TS < 0.5), (0.5, 10.0, UIO_TS >= 0.5)]:
        sol = solve_ivp(rhs, (a, b), s0, method="DOP853", rtol=1e-12, atol=1e-13, t_eval=UIO_TS[mask], dense_output=True)
        assert sol.success
        out[mask] = sol.y.T
        s0 = sol.sol(b)
    xs = np.stack([full(r[:3]) for r in out])
    return xs, out[:, 3:]


@pytest.fixture(scope="module")
def uio_runs(plant413cl, uio):
    E, A, B, C, L = plant413cl
    plant = fojax.DescriptorSystem(E, A, np.hstack([B, UIO_D]), C)  # input [u; d]
    u = (
        fojax.Step(jnp.array([1.0, -0.5, 0.0]), 0.5)
        + fojax.Sine(jnp.array([0.3, 0.2, 0.0]), 3.0)
        + fojax.Constant(jnp.array([0.0, 0.0, UIO_DVAL]))
    )
    sol = fojax.simulate(plant, UIO_X0, UIO_TS, u, observers=(uio.observer.with_extra_inputs(1),))
    return sol, _uio_reference(plant413cl, uio.observer)


def test_uio_simulation_matches_scipy_and_closed_form(plant413cl, uio, uio_runs):
    E = plant413cl[0]
    sol, (ref_x, ref_xi) = uio_runs
    assert sol.method == "exact"
    assert _rel(sol.xs, ref_x) <= 1e-8
    xi = np.asarray(sol.observer_states[0])
    assert _rel(xi, ref_xi) <= 1e-8
    # σ = [ζ - TEx; v; d̂ - d] follows expm(𝔸 t) σ(0) exactly, whatever u is.
    o = uio.observer
    xs = np.asarray(sol.xs)
    sig = np.column_stack([xi[:, : o.q0] - xs @ (uio.T @ E).T, xi[:, o.q0 :]])
    sig[:, -1] -= UIO_DVAL
    pred = np.stack([scipy.linalg.expm(uio.error_matrix * t) @ sig[0] for t in UIO_TS])
    assert np.abs(pred - sig).max() <= 1e-9 * np.abs(sig).max()


def test_uio_estimates_constant_unknown_input_and_functional(plant413cl, uio, uio_runs):
    L = plant413cl[4]
    sol, _ = uio_runs
    dh = np.asarray(uio.observer.unknown_input_estimate(sol.observer_states[0]))[:, 0]
    z = np.asarray(sol.xs) @ L.T
    ez = np.abs(np.asarray(sol.estimates[0]) - z).max(axis=1)
    assert dh[0] == 0.0 and abs(dh[-1] - UIO_DVAL) <= 1e-3 * UIO_DVAL
    assert ez[-1] <= 1e-3 * ez[0]
    # and the ẑ error is P ε exactly
    o = uio.observer
    eps = np.asarray(sol.observer_states[0])[:, : o.q0] - np.asarray(sol.xs) @ (uio.T @ plant413cl[0]).T
    np.testing.assert_allclose(np.asarray(sol.estimates[0]) - z, eps @ np.asarray(o.P).T, atol=1e-9 * ez[0])


# Badly scaled twin of the §4.1.3 unknown-input example: rows and states rescaled by 1e-6…1e6
# (E' = Dr E Dc, A' = Dr A Dc, B' = Dr B, C' = C Dc, D' = Dr D, L' = L Dc, x' = Dc⁻¹ x: the same
# u, y, z and d). Oracle: the twin's observer, driven by the *unscaled* plant's u and y in the
# SciPy reference above, must obey the error law σ(t) = expm(𝔸t) σ(0) with the physical
# T = T' Dr (conditions a.–f. in the model's own units), and estimate d.
UIO_TWIN_ROWS = np.array([1e-6, 1e6, 1e6, 1e-6])
UIO_TWIN_STATES = np.array([1e6, 1e-6, 1.0, 1e-6])


def _uio_twin(plant413cl, **kw):
    E, A, B, C, L = plant413cl
    Dr, Dc = np.diag(UIO_TWIN_ROWS), np.diag(UIO_TWIN_STATES)
    sys_ = fojax.DescriptorSystem(Dr @ E @ Dc, Dr @ A @ Dc, Dr @ B, C @ Dc)
    return design_unknown_input_observer(sys_, Dr @ UIO_D, L @ Dc, region=Disk(-3.0, 2.0), **kw)


def test_uio_badly_scaled_twin_on_the_raw_data_is_refused(plant413cl):
    # Regression: this design was returned (residual 2e-19 relative on the data as given, whose
    # terms are ~1e12) while a.–f. fail at 0.14–0.2 relative in the unit-free frame.
    with pytest.raises(fojax.errors.DesignVerificationError, match="unit-free frame"):
        _uio_twin(plant413cl, balance=False)


def test_uio_badly_scaled_twin_default_design_is_correct_in_physical_units(plant413cl):
    E = plant413cl[0]
    d = _uio_twin(plant413cl)  # balance=None: falls back to the unit-free design
    assert "balance" in d.report.extra and d.verify().passed
    assert d.report.extra["unit-free relative residual"] <= 1e-8
    o = d.observer
    T_phys = d.T @ np.diag(UIO_TWIN_ROWS)  # ζ - T'E'x' = ζ - T' Dr E x
    np.testing.assert_allclose(d.R @ np.diag(1.0 / UIO_TWIN_STATES), plant413cl[4], rtol=1e-12)
    xs, xi = _uio_reference(plant413cl, o)
    sig = np.column_stack([xi[:, : o.q0] - xs @ (T_phys @ E).T, xi[:, o.q0 :]])
    sig[:, -1] -= UIO_DVAL
    pred = np.stack([scipy.linalg.expm(d.error_matrix * t) @ sig[0] for t in UIO_TS])
    assert np.abs(pred - sig).max() <= 1e-7 * np.abs(sig).max()
    assert abs(xi[-1, -1] - UIO_DVAL) <= 1e-3 * UIO_DVAL


def test_uio_balance_true_maps_back_to_the_models_units(plant413cl, tmp_path):
    E, A, B, C, L = plant413cl
    d = design_unknown_input_observer(fojax.DescriptorSystem(E, A, B, C), UIO_D, L, balance=True)
    assert d.report.passed and "balance" in d.solver
    o = d.observer
    # conditions a.–f. written out in the model's units with the returned T, D, L (module docstring)
    Ep = np.asarray(d.structure.Eperp) * np.asarray(d.solver["balance"]["row_factors"])[None, :]
    np.testing.assert_allclose(Ep @ np.hstack([E, UIO_D]), 0.0, atol=1e-13)
    Psi, TE = np.vstack([Ep @ A, C]), d.T @ E
    np.testing.assert_array_equal(d.D, UIO_D)
    for lhs, terms in [(o.N @ TE + o.F @ Psi - d.T @ A, (o.N @ TE, o.F @ Psi, d.T @ A)),
                       (o.H - d.T @ B, (o.H, d.T @ B)), (o.Delta - d.T @ UIO_D, (o.Delta, d.T @ UIO_D)),
                       (o.S @ TE + o.M @ Psi, (o.S @ TE, o.M @ Psi)), (o.Phi @ TE - o.W @ Psi, (o.Phi @ TE, o.W @ Psi)),
                       (o.P @ TE + o.Q @ Psi - L, (o.P @ TE, o.Q @ Psi, L))]:
        assert np.abs(lhs).max() <= 1e-10 * max(np.abs(np.asarray(t)).max() for t in terms)
    path = fojax.save_design(d, tmp_path / "uio.npz")
    back = fojax.load_design(path)  # verified on load
    np.testing.assert_array_equal(back.R, d.R)
    assert back.verify().passed


def test_uio_block_diagonal_certificate_is_infeasible(uio, rng):
    # Documented claim: with X = diag(X_εv, X_d) the d̃-block of the region LMI is L_R ⊗ X_d,
    # which is never negative definite for a stable region. The full-X LMI (the design) is.
    # Proved algebraically, not by a solver status (which was "infeasible_inaccurate" with a
    # warning on some BLAS kernels, issue 17): the d̃ rows of 𝔸1 and the d̃ columns of 𝔸2 are
    # zero, so Φ = X𝔸1 - 𝒲𝔸2 has a zero d̃d̃ block for every block-diagonal X and every 𝒲,
    # and the d̃ principal submatrix of L⊗X + M⊗Φᵀ + Mᵀ⊗Φ is L_R ⊗ X_d. Its largest eigenvalue
    # is λmax(L_R)·λmax(X_d) > 0, a lower bound of λmax of the whole matrix (interlacing).
    s, D, Z = uio.structure, uio.D, uio.params["Z"]
    pc = pieces(s, xp=np)
    q0, q1, l = s.q0, s.q1, D.shape[1]
    N3 = np.asarray(pc.N3)
    c, d = N3.shape[0], q0 + q1 + l
    T = np.asarray(pc.T1) - (np.asarray(pc.Z0) + Z @ np.asarray(pc.PiZ)) @ np.asarray(pc.T2)
    A1 = np.zeros((d, d))
    A1[:q0, :q0] = np.asarray(pc.N1[0]) - Z @ np.asarray(pc.N2[0])
    A1[:q0, q0 + q1 :] = T @ D
    A2 = np.zeros((c + q1, d))
    A2[:c, :q0], A2[c:, q0 : q0 + q1] = N3, -np.eye(q1)
    LR, _ = uio.region.characteristic()
    assert np.linalg.eigvalsh(LR).max() > 0  # L_R is indefinite for every disk left of 0
    dd = [k * d + j for k in range(LR.shape[0]) for j in range(q0 + q1, d)]
    for _ in range(3):
        Ga, Gd = rng.standard_normal((q0 + q1, q0 + q1)), rng.standard_normal((l, l))
        Xa, Xd = Ga @ Ga.T + np.eye(q0 + q1), Gd @ Gd.T + np.eye(l)
        X = np.block([[Xa, np.zeros((q0 + q1, l))], [np.zeros((l, q0 + q1)), Xd]])
        Wv = 10.0 * rng.standard_normal((d, c + q1))
        Mx = uio.region.lmi_matrix(X, X @ A1 - Wv @ A2)
        block = np.kron(LR, Xd)
        np.testing.assert_allclose(Mx[np.ix_(dd, dd)], block, rtol=0, atol=1e-12 * np.abs(Mx).max())
        lam_block = np.linalg.eigvalsh(block).max()
        assert lam_block > 0 and np.linalg.eigvalsh(Mx).max() >= lam_block - 1e-12 * np.abs(Mx).max()


def test_uio_parameterization_holds_for_every_parameter_value(uio, rng):
    # Conditions a.–f. hold identically in (Z, Y1, Y2, Y3, J, G, Y4, Λ), also traced by JAX.
    import jax

    s, D = uio.structure, uio.D
    shapes = {k: np.shape(v) for k, v in uio.params.items()}
    for _ in range(3):
        p = {k: rng.standard_normal(sh) for k, sh in shapes.items()}
        m = unknown_input_observer_matrices(s, D, **p, xp=np)
        res = unknown_input_residuals(s, D, m)
        assert max(float(res[k]) for k in "abcdef") <= 1e-10 * float(res["scale"])

    @jax.jit
    def worst(p):
        res = unknown_input_residuals(s, D, unknown_input_observer_matrices(s, D, **p), xp=jnp)
        return jnp.max(jnp.stack([res[k] for k in "abcdef"])) / res["scale"]

    assert float(worst({k: jnp.asarray(rng.standard_normal(sh)) for k, sh in shapes.items()})) <= 1e-10


def test_uio_matrices_are_observer_matrices_of_its_parameters(uio):
    """The UIO has one map from parameters to T, N, F, ...: `observer_matrices`; Δ = TD,
    Φ = -Y4 N3, W = Y4 F3 with N3, F3 from the projector I - ΣΣ⁺ = U0 U0ᵀ (U0 an orthonormal
    basis of the left null space of Σ = [R; Ψ], scipy.linalg.null_space: independent)."""
    from fojax.design import observer_matrices

    s, D, p, o = uio.structure, uio.D, uio.params, uio.observer
    m = observer_matrices(s, *(p[k] for k in ("Z", "Y1", "Y2", "Y3", "J", "G")), xp=np)
    for name in "NJFHSGMPQ":
        np.testing.assert_allclose(np.asarray(getattr(o, name)), np.asarray(getattr(m, name))[0],
                                   rtol=0, atol=1e-12 * max(1.0, np.abs(getattr(m, name)).max()), err_msg=name)
    for name in ("T", "K", "Z_eff"):
        np.testing.assert_allclose(getattr(uio, name), np.asarray(getattr(m, name)),
                                   rtol=0, atol=1e-12 * max(1.0, np.abs(getattr(m, name)).max()), err_msg=name)
    E, A, C, R, Ep = (np.asarray(x) for x in (s.E, s.A, s.C, s.R, s.Eperp))
    Psi = np.vstack([Ep @ A, C])
    U0 = scipy.linalg.null_space(np.vstack([R, Psi]).T)
    PS = U0 @ U0.T
    K = np.asarray(m.K)
    N3, F3 = PS[:, : s.q0], PS @ np.vstack([K, np.eye(s.nw)])
    scale = max(1.0, np.abs(p["Y4"]).max())
    np.testing.assert_allclose(np.asarray(o.Delta), uio.T @ D, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(o.Phi), -p["Y4"] @ N3, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(np.asarray(o.W), p["Y4"] @ F3, rtol=0, atol=1e-10 * scale * max(1.0, np.abs(K).max()))


def test_uio_lmi_certifies_the_error_matrix_of_the_returned_observer(uio, rng):
    """Regression: the LMI data 𝔸1 (N1 - Z N2 and TD) came from a second copy of
    ``T = T1 - (Z0 + Z Π_Z) T2``, while the observer uses `observer_matrices`, which
    projects the dead components of Z out first. With a dead component of size 1e10 in Z
    (rows in the row space of Γ = [E; Ψ], which T, K ignore: (I - ΓΓ⁺)Γ = 0) the two
    differed by ~1e-6 (ε·1e10 in different directions); now 𝔸1 - 𝕐𝔸2 is the observer's
    error matrix [N J Δ; S G 0; Φ Λ 0] to rounding, for the designed Z and for that one."""
    from fojax.design import unknown_input_error_dynamics

    # private: the LMI data are checked
    from fojax.design._unknown_input import _lmi_data

    s, D, p = uio.structure, uio.D, uio.params
    E, A, C, Ep = (np.asarray(x) for x in (s.E, s.A, s.C, s.Eperp))
    Gam = np.vstack([E, Ep @ A, C])
    dead = (Gam @ rng.standard_normal((s.n, s.q0))).T
    for Z in (p["Z"], p["Z"] + 1e10 * dead / np.abs(dead).max()):
        q = {**p, "Z": Z}
        mats = unknown_input_observer_matrices(s, D, **q, xp=np)
        Aobs = np.asarray(unknown_input_error_dynamics(mats, xp=np))
        A1, A2 = _lmi_data(s, D, Z)
        Yb = np.block([[q["Y1"], q["J"]], [q["Y2"], q["G"]], [q["Y4"], q["Lambda"]]])
        np.testing.assert_allclose(A1 - Yb @ A2, Aobs, rtol=0, atol=1e-12 * np.abs(Aobs).max())


# --------------------------------------------------------------------------- UIO existence errors


def test_uio_rejects_dependent_unknown_inputs(plant413cl):
    E, A, B, C, L = plant413cl
    D = np.column_stack([UIO_D[:, 0], 2.0 * UIO_D[:, 0]])
    with pytest.raises(fojax.errors.RankConditionError, match=r"full column rank of D fails: D is 4 x 2 but has rank 1"):
        design_unknown_input_observer(fojax.DescriptorSystem(E, A, B, C), D, L)


def test_uio_functional_observability_uses_annihilator_of_E_D():
    # 0 = x2 - x3 (+ d): without d, x3 = x2 is known; the unknown input in the algebraic row
    # removes that constraint (E⊥ of [E D] is empty), so z = x3 is not observable.
    E = np.diag([1.0, 1.0, 0.0])
    A = np.array([[-1.0, 1.0, 0.0], [0.0, -2.0, 0.0], [0.0, 1.0, -1.0]])
    sys = fojax.DescriptorSystem(E, A, np.array([[1.0], [0.0], [0.0]]), np.array([[1.0, 0.0, 0.0]]))
    L = np.array([[0.0, 0.0, 1.0]])
    assert design_unknown_input_observer(sys, np.array([[0.0], [1.0], [0.0]]), L).report.passed
    with pytest.raises(
        fojax.errors.FunctionalObservabilityError,
        match=r"E⊥ annihilating \[E D\]\) fails: rank \[L; E; E⊥A; C\] = 3 but rank \[E; E⊥A; C\] = 2",
    ):
        design_unknown_input_observer(sys, np.array([[0.0], [0.0], [1.0]]), L)


def test_uio_unknown_input_in_unobservable_direction_is_undetectable():
    # d drives x2, which no output sees: a constant d cannot be estimated (every R, every Z).
    sys = fojax.DescriptorSystem.from_state_space(
        np.diag([-1.0, -2.0]), np.array([[1.0], [0.0]]), np.array([[1.0, 0.0]])
    )
    with pytest.raises(
        fojax.errors.DetectabilityError,
        match=r"mode s = 0 of d̃.*rank \[\[N1 - Z N2, T D\], \[N3, 0\]\] = \d < q0 \+ l = \d for every Z",
    ):
        design_unknown_input_observer(sys, np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]))


def test_uio_needs_an_observer_order_at_least_the_number_of_unknown_inputs(plant413cl):
    E, A, B, C, L = plant413cl
    D = np.eye(4)[:, [0, 2]]
    sys = fojax.DescriptorSystem(E, A, B, C)
    R = np.array([[1.0, 0.0, 0.0, 0.0]])
    with pytest.raises(fojax.errors.DetectabilityError, match=r"observer order q0 \(now 1; at least l = 2 is needed\)"):
        design_unknown_input_observer(sys, D, R, R=R)


def _uio_matrices(q0=2, q1=1, l=1, nw=3, m=1, p=2, q=1):
    """Zero matrices of the sizes of the unknown-input observer (§3.2: N q0×q0, J q0×q1, F q0×nw,
    H q0×m, Δ q0×l, S q1×q0, G q1×q1, M q1×nw, Φ l×q0, Λ l×q1, W l×nw, P q×q0, Q q×nw,
    Wu nw×m, Wy nw×p)."""
    z = np.zeros
    return dict(N=z((q0, q0)), J=z((q0, q1)), F=z((q0, nw)), H=z((q0, m)), Delta=z((q0, l)),
                S=z((q1, q0)), G=z((q1, q1)), M=z((q1, nw)), Phi=z((l, q0)), Lambda=z((l, q1)),
                W=z((l, nw)), P=z((q, q0)), Q=z((q, nw)), Wu=z((nw, m)), Wy=z((nw, p)))


@pytest.mark.parametrize("name, shape, expected", [
    ("N", (2, 3), (2, 2)), ("J", (3, 1), (2, 1)), ("F", (2, 4), (2, 3)), ("H", (2, 2), (2, 1)),
    ("S", (1, 3), (1, 2)), ("M", (1, 2), (1, 3)), ("Q", (1, 2), (1, 3)), ("Wu", (2, 1), (3, 1)),
    ("Delta", (3, 1), (2, 1)), ("Phi", (1, 3), (1, 2)), ("Lambda", (1, 2), (1, 1)),
    ("W", (1, 2), (1, 3)),
])
def test_uio_shape_errors_name_the_matrix(name, shape, expected):
    mats = _uio_matrices()
    fojax.UnknownInputObserver(**mats)  # the sizes of the docstring fit
    mats[name] = np.zeros(shape)
    with pytest.raises(fojax.errors.ShapeError, match=rf"{name} has shape \({shape[0]}, {shape[1]}\), "
                       rf"expected \({expected[0]}, {expected[1]}\)"):
        fojax.UnknownInputObserver(**mats)
