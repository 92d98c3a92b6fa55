"""Verdicts and eigenvalues that do not depend on units (issue 15, items 1 and 5).

Oracles, independent of fojax:
- exact constructions: E = P E0 Q, A = P A0 Q with integer unimodular P, Q (products of
  unit triangular integer matrices, so det = ±1 exactly and every entry is an exact
  small integer in float64) and E0, A0 in Weierstrass form (identity, triangular
  integer J with known eigenvalues, nilpotent Jordan blocks N); the regularity, the
  number of finite poles, the index and the poles are read off E0, A0 by hand;
- sympy (exact rational arithmetic): det(sE - A) and the eigenvalues of small
  integer matrices;
- exact power-of-two diagonal scalings D_l (.) D_r: in float64 they add no rounding, so
  the scaled system is the same mathematical object and every verdict must be the same.
The issue's examples: E = diag(1, 1e-11), A = diag(-1, -1e-11) (regular, poles
[-1, -1]); A = T diag(D), E = T with T badly scaled (cond(T) > 1e10, n = 10 and 50;
eigenvalues exactly D); a 6x6 pencil with eigenvalues exactly 1..6 and E invertible,
badly scaled in the manner of Ward (1981), "Balancing the generalized eigenvalue
problem", SIAM J. Sci. Stat. Comput. 2(2):141-152 (constructed here, not Ward's
published matrices).
"""

import numpy as np
import pytest
import sympy

import fojax
from fojax import analysis as fa

# private: the balancing internals and rank helpers are tested themselves
from fojax.analysis._balance import _ward_exponents, tg01ad_scaling
from fojax.analysis._common import as_system, deflate
from fojax.analysis._observability import _i_ctrl, _i_obs, _r_ctrl, _r_obs
from fojax.analysis._pencil import _poles_from
from tests.helpers import assert_eigenvalues_match


def _two(e):
    return np.ldexp(1.0, np.asarray(e))


def _scaled(E, A, B, C, el, er):
    dl, dr = _two(el), _two(er)
    return dl[:, None] * E * dr, dl[:, None] * A * dr, dl[:, None] * B, C * dr


def test_issue_diag_example_regular_with_poles_minus_one():
    """E = diag(1, 1e-11), A = diag(-1, -1e-11) = diag(1, 1e-11)(s + 1): regular, poles
    [-1, -1]. Before balancing fojax said irregular (balance=False keeps that answer)."""
    E, A = np.diag([1.0, 1e-11]), np.diag([-1.0, -1e-11])
    s = sympy.symbols("s")
    det = sympy.Matrix([[s + 1, 0], [0, sympy.Rational(1, 10**11) * (s + 1)]]).det()
    assert sympy.roots(sympy.Poly(det, s)) == {-1: 2}
    assert fa.is_regular(E, A)
    assert_eigenvalues_match(fa.finite_poles(E, A), [-1.0, -1.0], rtol=1e-12)
    assert fa.nilpotency_index(E, A) == 0
    assert not fa.is_regular(E, A, balance=False)  # the old, unit-dependent verdict
    sysd = fojax.DescriptorSystem(E, A, np.ones((2, 1)), np.ones((1, 2)))
    rep = fa.structure_report(sysd)
    assert rep.regular and rep.rank_E == 2 and rep.kronecker.normal_rank == 2
    assert rep.scaling.method == "ward" and not rep.scaling.identity
    assert "scaling" in str(rep)


@pytest.mark.parametrize("n", [10, 50])
def test_badly_scaled_T_pencil_has_eigenvalues_exactly_D(n):
    """A = T diag(D), E = T, T = D_l T0 D_r with T0 a random Gaussian matrix and powers of
    two up to 2^±17: cond(T) > 1e10 yet (E, A) is regular with eigenvalues exactly D."""
    rng = np.random.default_rng(15 + n)
    T0 = rng.standard_normal((n, n))
    T = _two(rng.integers(-17, 18, n))[:, None] * T0 * _two(rng.integers(-17, 18, n))
    assert np.linalg.cond(T) > 1e10
    D = np.arange(1.0, n + 1.0)
    A = T * D[None, :]  # T @ diag(D), exact column scaling by integers
    assert fa.is_regular(T, A)
    assert fa.nilpotency_index(T, A) == 0
    assert_eigenvalues_match(fa.finite_poles(T, A), D, rtol=1e-9)
    ks = fa.kronecker_structure(T, A)
    assert ks.regular and ks.infinite_divisors == ()
    assert_eigenvalues_match(ks.finite_eigenvalues, D, rtol=1e-9)


def test_ward_style_six_by_six_eigenvalues_one_to_six():
    """E0 = unit upper triangular integers, A0 = E0 U with U upper triangular with
    diagonal 1..6: det(sE0 - A0) = det(E0) det(sI - U) = prod (s - k). Badly scaled by
    D_l, D_r with exponents spanning 2^±30 (entries from 1e-18 to 1e18)."""
    E0 = np.triu(np.arange(1, 37).reshape(6, 6) % 5 - 2.0, 1) + np.eye(6)
    U = np.triu(np.arange(36).reshape(6, 6) % 3 - 1.0, 1) + np.diag(np.arange(1.0, 7.0))
    A0 = E0 @ U
    s = sympy.symbols("s")
    det = (s * sympy.Matrix(E0.astype(int)) - sympy.Matrix(A0.astype(int))).det()
    assert sympy.factor(det) == sympy.prod([s - k for k in range(1, 7)])
    el = np.array([30, -30, 12, -7, 25, -19])
    er = np.array([-28, 3, 30, -30, 0, 17])
    E, A, _, _ = _scaled(E0, A0, np.zeros((6, 0)), np.zeros((0, 6)), el, er)
    assert fa.is_regular(E, A) and fa.nilpotency_index(E, A) == 0 and fa.is_impulse_free(E, A)
    assert_eigenvalues_match(fa.finite_poles(E, A), np.arange(1.0, 7.0), rtol=1e-10)


def test_e_identity_similarity_keeps_the_complex_pair():
    """E = I, A = D^-1 A0 D (exact powers of two up to 2^±20) with A0 integer; its
    eigenvalues by sympy: the roots of s^3 + s^2 + s + 1 (-1, ±i) and 2, 3, -4.
    numpy.linalg.eigvals balances; fojax balances with SLICOT TB01ID (E stays I)."""
    comp = np.array([[0, 1, 0], [0, 0, 1], [-1, -1, -1.0]])  # s^3 + s^2 + s + 1
    A0 = np.zeros((6, 6))
    A0[:3, :3] = comp
    A0[3:, 3:] = np.array([[2, 1, 0], [0, 3, 1], [0, 0, -4.0]])
    Q = np.eye(6) + np.diag(np.ones(5), 1)  # unimodular, inverse exact in integers
    Qinv = np.array(sympy.Matrix(Q.astype(int)).inv(), dtype=float)
    A0 = Q @ A0 @ Qinv
    exact = [complex(v) for v in sympy.Matrix(A0.astype(int)).eigenvals(multiple=True)]
    d = _two([20, -20, 7, -13, 15, 0])
    A = A0 * d[None, :] / d[:, None]
    sysd = fojax.DescriptorSystem(np.eye(6), A, np.ones((6, 1)), np.ones((1, 6)))
    rep = fa.structure_report(sysd)
    assert rep.scaling.method == "tb01id"
    assert np.array_equal(rep.scaling.row_exponents, -rep.scaling.col_exponents)
    assert_eigenvalues_match(rep.finite_poles, exact, rtol=1e-10)


def test_observability_survives_an_exact_similarity():
    """(A0, C0) integer with an observable companion structure; A = D^-1 A0 D, C = C0 D
    with D = 2^(±30): R-, C-observability stay True (the issue's 5x5 case said False)."""
    A0 = np.diag(np.ones(4), 1) + np.diag([-1.0, 2.0, -3.0, 1.0, -2.0])
    C0 = np.array([[1.0, 0, 0, 0, 0]])
    O = np.vstack([C0 @ np.linalg.matrix_power(A0, k) for k in range(5)])
    assert sympy.Matrix(O.astype(int)).rank() == 5  # exact observability oracle
    d = _two([30, -30, 12, -25, 29])
    sysd = fojax.DescriptorSystem(np.eye(5), A0 * d[None, :] / d[:, None],
                                  np.zeros((5, 1)), C0 * d[None, :])  # fmt: skip
    assert fa.is_r_observable(sysd) and fa.is_c_observable(sysd) and fa.is_s_observable(sysd)


# ------------------------------------------------------------------ property test


def _unimodular(rng, n):
    L = np.tril(rng.integers(-2, 3, (n, n)), -1) + np.eye(n)
    U = np.triu(rng.integers(-2, 3, (n, n)), 1) + np.eye(n)
    return (L @ U)[rng.permutation(n)]


def _random_system(rng):
    """(E, A, B, C) = (P E0 Q, P A0 Q, B, C) with known Weierstrass structure; 15 % are
    made singular by a zero column of E0 and A0 (det(sE - A) = 0 exactly)."""
    n1 = int(rng.integers(0, 4))
    blocks = [int(b) for b in rng.integers(1, 4, rng.integers(0, 3))]
    n2 = sum(blocks)
    if n1 + n2 == 0:
        n1 = 1
    n = n1 + n2
    J = np.triu(rng.integers(-3, 4, (n1, n1)), 1) + np.diag(rng.integers(-4, 4, n1))
    E0, A0 = np.zeros((n, n)), np.zeros((n, n))
    E0[:n1, :n1], A0[:n1, :n1], A0[n1:, n1:] = np.eye(n1), J, np.eye(n2)
    pos = n1
    for b in blocks:
        for i in range(b - 1):
            E0[pos + i, pos + i + 1] = 1.0
        pos += b
    singular = bool(rng.random() < 0.15)
    if singular:
        k = int(rng.integers(0, n))
        E0[:, k] = A0[:, k] = 0.0
    P, Q = _unimodular(rng, n), _unimodular(rng, n)
    m, p = int(rng.integers(1, 3)), int(rng.integers(1, 3))
    B = rng.integers(-2, 3, (n, m)).astype(float)
    C = rng.integers(-2, 3, (p, n)).astype(float)
    truth = dict(regular=not singular, n1=n1, index=max(blocks) if n2 else 0,
                 poles=np.diag(J).astype(float))  # fmt: skip
    return (P @ E0 @ Q, P @ A0 @ Q, B, C), truth


def _verdicts(E, A, B, C):
    p = as_system(fojax.DescriptorSystem(E, A, B, C), "test")
    d = deflate(p, None)
    if d.failed is not None:
        return {"regular": False}, None
    v = dict(regular=True, n1=d.n1, index=d.index, ro=_r_obs(p, None, "t"),
             rc=_r_ctrl(p, None, "t"), io=_i_obs(p, None), ic=_i_ctrl(p, None))  # fmt: skip
    return v, _poles_from(p, d, "t") * p.pole_scale


def _same_poles(z, truth):
    """Simple poles to 1e-8 relative; a repeated (possibly defective) pole is only
    determined to O(sqrt(eps)), so there the characteristic polynomial's coefficients are
    compared (to 1e-7 of their scale) and the roots to 1e-4."""
    truth = np.asarray(truth, dtype=float)
    if len(np.unique(truth)) == len(truth):
        assert_eigenvalues_match(z, truth, rtol=1e-8, atol=1e-8)
        return
    c, c0 = np.real(np.poly(z)), np.poly(truth)
    assert np.max(np.abs(c - c0)) <= 1e-7 * max(1.0, np.max(np.abs(c0))), (z, truth)
    assert_eigenvalues_match(z, truth, rtol=1e-4, atol=1e-4)


def test_verdicts_and_poles_do_not_change_under_power_of_two_scalings():
    """200 random systems (n <= 9) with exactly known structure, each also under a random
    exact scaling of equations and states by 2^k, |k| <= 40. Every verdict (regularity,
    n1, index, R/I observability and controllability) and every pole (relative 1e-8)
    must agree; regularity, n1, index and poles also with the construction (repeated
    poles: see `_same_poles`)."""
    rng = np.random.default_rng(20261126)
    changed_without_balancing = 0
    for trial in range(200):
        (E, A, B, C), truth = _random_system(rng)
        n = E.shape[0]
        v0, z0 = _verdicts(E, A, B, C)
        assert v0["regular"] == truth["regular"], trial
        if truth["regular"]:
            assert (v0["n1"], v0["index"]) == (truth["n1"], truth["index"]), trial
            _same_poles(z0, truth["poles"])
        el, er = rng.integers(-40, 41, n), rng.integers(-40, 41, n)
        scaled = _scaled(E, A, B, C, el, er)
        v1, z1 = _verdicts(*scaled)
        assert v1 == v0, (trial, v0, v1, el, er)
        if truth["regular"]:
            _same_poles(z1, truth["poles"])
        if trial < 40:  # the test has teeth: without balancing, verdicts change
            p = as_system(fojax.DescriptorSystem(*scaled), "t", balance=False)
            changed_without_balancing += (deflate(p, None).failed is None) != v0["regular"] or (
                v0["regular"] and deflate(p, None).n1 != v0["n1"])
    assert changed_without_balancing >= 10


def test_ward_least_squares_is_at_least_as_balanced_as_tg01ad():
    """Cross-check with SLICOT TG01AD (its factors rounded to powers of two): on scaled
    random systems, fojax's exact least-squares exponents give a Ward objective (the sum of
    squared log2 magnitudes of the balanced entries, about each block's mean) no larger
    than TG01AD's in the median, and never worse by more than one unit per entry
    (rounding to integers)."""
    rng = np.random.default_rng(7)

    def objective(E, A, B, C, s):
        Eb, Ab, Bb, Cb = (x for x in fa._balance.apply_scaling(s, E, A, B, C))
        tot = 0.0
        for M in (Eb, Ab, Bb, Cb):  # per block, about its mean (blocks are normalised)
            v = np.log2(np.abs(M[M != 0]))
            tot += float(np.sum((v - v.mean()) ** 2)) if v.size else 0.0
        return tot

    worse = []
    for _ in range(30):
        (E, A, B, C), _ = _random_system(rng)
        n = E.shape[0]
        E, A, B, C = _scaled(E, A, B, C, rng.integers(-30, 31, n), rng.integers(-30, 31, n))
        el, er = _ward_exponents(E, A, B, C)
        ours = fa.Scaling(el, er, "ward")
        ref = tg01ad_scaling(E, A, B, C)
        nnz = sum(int(np.count_nonzero(M)) for M in (E, A, B, C))
        worse.append(objective(E, A, B, C, ours) - objective(E, A, B, C, ref))
        assert worse[-1] <= nnz, worse[-1]
    assert np.median(worse) <= 0


# ------------------------------------------------------------------ one verdict, every layer


def test_every_layer_takes_the_analysis_verdict_on_a_badly_scaled_ode():
    """E = diag(1, 2^-40), A = diag(-1, -2^-40): an ODE with poles [-1, -1] (exact).
    Before: design's check_regular called it irregular-free but control's reduce_host
    split E at the unbalanced rank 1 and silently returned a 1-state model (pole -1 only),
    and simulation called it impulsive. Now the host split is analysis's: 2 slow states;
    simulation, whose traced split cannot balance, refuses with a typed InputError naming
    the scaling instead of simulating a wrong model."""
    # private: design's own regularity check is compared with analysis's
    from fojax.design._conditions import check_regular
    from fojax.simulation._reduction import check_index1_host, reduce_host

    E, A = np.diag([1.0, 2.0**-40]), np.diag([-1.0, -(2.0**-40)])
    sp = fa.index1_split(E, A)
    assert sp.rank == 2 and sp.regular and sp.index == 0 and sp.impulse_free
    check_regular(E, A, fname="test")  # no error: regular, as fa.is_regular says
    As, _, _, _, _ = reduce_host(E, A, np.ones((2, 1)))
    assert_eigenvalues_match(np.linalg.eigvals(As), fa.finite_poles(E, A), rtol=1e-12)
    assert_eigenvalues_match(np.linalg.eigvals(As), [-1.0, -1.0], rtol=1e-12)
    with pytest.raises(fojax.errors.InputError, match="too badly scaled for simulation"):
        check_index1_host(E, A)
    check_index1_host(np.eye(2), A)  # the same model in balanced units is accepted


def test_index1_split_verdicts_match_analysis():
    """On the random systems of the property test: index1_split's (regular, index, rank)
    are is_regular's, nilpotency_index's and structure_report's rank_E."""
    rng = np.random.default_rng(11)
    for _ in range(40):
        (E, A, B, C), truth = _random_system(rng)
        sp = fa.index1_split(E, A)
        assert sp.regular == fa.is_regular(E, A) == truth["regular"]
        if sp.regular:
            assert sp.index == fa.nilpotency_index(E, A) == truth["index"]
            assert sp.rank == np.linalg.matrix_rank(E)  # integer data: exact rank


def test_e_perp_decides_rank_e_after_balancing():
    """E = diag(1, 2^-40, 0) has rank 2 exactly: one row in E⊥ (was two without
    balancing, which made E⊥A contain an equation of the dynamics)."""
    E = np.diag([1.0, 2.0**-40, 0.0])
    N = fa.e_perp(E)
    assert N.shape == (1, 3) and np.allclose(np.abs(N), [[0.0, 0.0, 1.0]], atol=0)
    assert fa.e_perp(E, balance=False).shape == (2, 3)


def test_functional_observability_does_not_change_under_scalings():
    """Assumption 1 for random L on the random systems, with equations, states (and L's
    columns with them) scaled by 2^k, |k| <= 40: the same verdict (the rank pair is
    invariant: L D_r, D_l E D_r, ... have the ranks of L, E, ...)."""
    rng = np.random.default_rng(5)
    seen = set()
    for _ in range(60):
        (E, A, B, C), truth = _random_system(rng)
        n = E.shape[0]
        L = rng.integers(-2, 3, (int(rng.integers(1, 3)), n)).astype(float)
        v0 = fa.is_functionally_observable(fojax.DescriptorSystem(E, A, B, C), L)
        el, er = rng.integers(-40, 41, n), rng.integers(-40, 41, n)
        Es, As, Bs, Cs = _scaled(E, A, B, C, el, er)
        v1 = fa.is_functionally_observable(fojax.DescriptorSystem(Es, As, Bs, Cs),
                                           L * _two(er)[None, :])  # fmt: skip
        assert v0 == v1
        seen.add(v0)
    assert seen == {True, False}


def test_balance_system_is_an_exact_power_of_two_equivalence():
    """The balanced matrices are exactly D_l E D_r, ... (bit for bit: powers of two), the
    exponents are integers, and balancing undoes a scaling of the issue's 2^36 size."""
    E, A = np.diag([1.0, 1e-11]), np.diag([-1.0, -1e-11])
    b = fa.balance_system(E, A)
    dl, dr = b.scaling.left, b.scaling.right
    assert np.array_equal(b.E, dl[:, None] * E * dr) and np.array_equal(b.A, dl[:, None] * A * dr)
    assert np.array_equal(np.log2(dl), np.rint(np.log2(dl)))
    assert np.max(np.abs(b.E)) / np.min(np.abs(b.E[b.E != 0])) < 4.0
    assert fa.balance_system(E, A, balance=False).scaling.identity


def test_example_4_1_3_in_tiny_units_of_x4_is_regular_again():
    """Stop 20's known consequence: thesis example 4.1.3 with x4 in units of 2^-34 was
    refused by design as irregular (unit-dependent verdict). Now analysis and design's
    check_regular accept it, with the poles of the unscaled model."""
    import tomllib
    from importlib.resources import files

    # private: design's own regularity check is compared with analysis's
    from fojax.design._conditions import check_regular

    d = tomllib.loads(files("fojax").joinpath("examples", "example_4_1_3.toml").read_text())
    E, A = (np.array(d["model"][k], float) for k in ("E", "A"))
    dr = np.array([1.0, 1.0, 1.0, 2.0**-34])
    assert not fa.is_regular(E * dr, A * dr, balance=False)  # the old verdict
    assert fa.is_regular(E * dr, A * dr)
    check_regular(E * dr, A * dr, fname="test")
    assert_eigenvalues_match(fa.finite_poles(E * dr, A * dr), fa.finite_poles(E, A), rtol=1e-10)


def test_round_off_entries_do_not_steer_the_balancing():
    """A 4-state piece of the finite-time control loop of thesis 3.1.2 (test_control's
    fixture): round-off entries ~1e-18 where a product should be zero. With them in the
    balancing problem, balancing blew them up, ‖A‖ grew ~1e10 and A11 = 1 fell below the
    rank threshold: analysis called the pencil irregular (and control's reduce_host
    refused the loop). Oracle: the pencil is block diagonal up to the round-off, so it is
    regular, index 1, with the eigenvalues (numpy) of the noise-free 3x3 block."""
    E = np.diag([0.0, 1.0, 1.0, 1.0])
    A = np.array([[1.0, 0.0, 0.0, 0.0],
                  [0.0, -120.35401544936049, 29.530807218858346, 6.3776977327104736e-19],
                  [0.0, 77.202514483225698, -31.434411964668762, 1.2542281895845844e-18],
                  [0.0, -5.1048823683723647e-19, -1.3107690997533078e-18, -4.5260579795644258]])
    A0 = np.where(np.abs(A) < 1e-15, 0.0, A)
    assert fa.is_regular(E, A) and fa.nilpotency_index(E, A) == 1
    assert_eigenvalues_match(fa.finite_poles(E, A), np.linalg.eigvals(A0[1:, 1:]), rtol=1e-12)


def test_design_takes_the_rank_of_e_from_analysis():
    """Issue 15 item 2: design's E⊥ (the annihilator of E in w = [-E⊥Bu; y]) comes from
    `fojax.analysis.e_perp`, so design and analysis agree on rank E under any units. Thesis
    example 4.1.3 with one state in units of 2^-40: analysis (balanced) keeps rank E = 3;
    the raw SVD of E saw rank 2 and gave design a second E⊥ row. Oracles: rank E of the
    unscaled model (NumPy), and the observer of the scaled model, driven by the same u and
    y, estimating z = L x of the plant in its original units (fojax.simulate)."""
    import jax.numpy as jnp

    ex = fojax.models.example_4_1_3()
    E, A, B, C, L = (np.asarray(x) for x in (ex.E, ex.A + ex.B @ ex.L, ex.B, ex.C, ex.L))
    n, r = E.shape[0], np.linalg.matrix_rank(E)
    j = int(np.argmax(np.abs(E).sum(0)))
    D = np.ones(n)
    D[j] = 2.0**-40  # x = D x': state j in tiny units
    scaled = fojax.DescriptorSystem(E * D, A * D, B, C * D)
    assert fojax._linalg.left_null_space(E * D).shape[0] == n - r + 1  # the unbalanced rank decision
    d = fojax.design_functional_observer(scaled, L * D, kind="proportional", region=fojax.Disk(-2.0, 1.0))
    assert d.report.passed
    assert d.structure.Eperp.shape[0] == n - r
    assert np.abs(np.asarray(d.structure.Eperp) @ (E * D)).max() <= 1e-12
    ts = jnp.linspace(0.0, 20.0, 1001)
    sol = fojax.simulate(fojax.DescriptorSystem(E, A, B, C), jnp.asarray(ex.x0), ts, observers=(d.observer,))
    err = np.abs(np.asarray(sol.estimates[0]) - np.asarray(sol.xs) @ L.T)
    assert err[np.asarray(ts) >= 15.0].max() < 1e-4 * max(1.0, err[0].max())


def test_e_perp_with_unknown_inputs_is_unit_independent():
    """`e_perp(E, D=D)` (the unknown-input observer's annihilator of [E D]): its number of
    rows is n - rank [E D] by sympy's exact rank of the integer matrices, under exact
    power-of-two scalings of the equations and states up to 2^±40, and it annihilates [E D]."""
    rng = np.random.default_rng(7)
    for trial in range(20):
        n, l = 5, 1 + trial % 2
        E = rng.integers(-3, 4, size=(n, n)).astype(float)
        E[:, -2:] = 0.0  # rank E <= 3
        D = rng.integers(-3, 4, size=(n, l)).astype(float)
        exact = n - sympy.Matrix(np.hstack([E, D]).astype(int)).rank()
        dl = 2.0 ** rng.integers(-40, 41, size=n)
        dr = 2.0 ** rng.integers(-40, 41, size=n)
        Es, Ds = dl[:, None] * E * dr[None, :], dl[:, None] * D
        N = fa.e_perp(Es, D=Ds)
        assert N.shape == (exact, n), (trial, N.shape, exact)
        K = np.hstack([Es, Ds])  # orthonormal rows, normwise backward stable
        assert np.linalg.norm(N @ K, 2) <= 1e-12 * np.linalg.norm(K, 2)
        assert np.allclose(N @ N.T, np.eye(exact), atol=1e-12)
