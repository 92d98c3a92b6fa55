"""Kronecker structure, zeros, properness and mode counts (issue 15, item 4).

Oracles, independent of fojax and of SLICOT:
- Kronecker canonical forms assembled by hand from the textbook blocks (Gantmacher 1959,
  Ch. XII): L_eps (eps x (eps+1), right minimal index eps), L_eta^T ((eta+1) x eta,
  left minimal index eta), N_k (an infinite elementary divisor of size k) and J (finite
  eigenvalues), mixed by integer unimodular P, Q (exact in float64) and exact power-of-two
  scalings; the indices are known by construction;
- sympy (exact rational arithmetic): the normal rank (rank of sE - A over Q(s), at
  rational points that are not eigenvalues), det,
  and the invariant zeros of square systems as the roots of det [[A - sE, B], [C, D]];
- closed-form transfer functions for the zeros and for properness;
- `fojax.analysis.finite_poles` (orthogonal deflation + QZ, no SLICOT) for the finite eigenvalues
  of regular pencils: two algorithms that must agree.
"""

import numpy as np
import pytest
import sympy

import fojax
from fojax import analysis as fa
from tests.helpers import assert_eigenvalues_match


def _L(eps):
    """L_eps = [I 0] s - [0 I]... as (E, A) with A - sE: rows eps, cols eps + 1."""
    E = np.hstack([np.eye(eps), np.zeros((eps, 1))])
    A = np.hstack([np.zeros((eps, 1)), np.eye(eps)])
    return E, A


def _N(k):
    E = np.diag(np.ones(k - 1), 1)
    return E, np.eye(k)


def _blkdiag(blocks):
    r = sum(b.shape[0] for b in blocks)
    c = sum(b.shape[1] for b in blocks)
    M = np.zeros((r, c))
    i = j = 0
    for b in blocks:
        M[i : i + b.shape[0], j : j + b.shape[1]] = b
        i, j = i + b.shape[0], j + b.shape[1]
    return M


def _unimodular(rng, n):
    L = np.tril(rng.integers(-1, 2, (n, n)), -1) + np.eye(n)
    U = np.triu(rng.integers(-1, 2, (n, n)), 1) + np.eye(n)
    return L @ U


def _kcf(right, left, inf, J):
    Es, As = [], []
    for e in right:
        E, A = _L(e)
        Es.append(E), As.append(A)
    for e in left:
        E, A = _L(e)
        Es.append(E.T), As.append(A.T)
    for k in inf:
        E, A = _N(k)
        Es.append(E), As.append(A)
    if len(J):
        J = np.atleast_2d(J)
        Es.append(np.eye(J.shape[0])), As.append(J)
    return _blkdiag(Es), _blkdiag(As)


def _sympy_normal_rank(E, A):
    """rank over Q(s) of A - sE, exactly: the rank at a rational point s0 equals the normal
    rank unless s0 is a finite eigenvalue; the cases' eigenvalues are integers, so the
    maximum over s0 = 7/13 and 11/17 is the normal rank."""
    Ez, Az = sympy.Matrix(E.astype(int)), sympy.Matrix(A.astype(int))
    return max((Az - sympy.Rational(*q) * Ez).rank() for q in ((7, 13), (11, 17)))


CASES = {
    # name: (right indices, left indices, infinite divisor sizes, J)
    "regular_index2": ((), (), (2,), np.array([[-3.0]])),
    "L1_only": ((1,), (), (), np.zeros((0, 0))),
    "L0_and_L0T": ((0,), (0,), (), np.array([[-1.0]])),
    "nonsquare_L2_N1_J": ((2,), (), (1,), np.array([[1.0, 1.0], [0.0, 2.0]])),
    "nonsquare_L1T_N3": ((), (1,), (3,), np.array([[-2.0]])),
    "mixed_all": ((1, 0), (2,), (2, 1), np.array([[0.0, 1.0], [-2.0, -3.0]])),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_kronecker_structure_of_hand_built_pencils(name):
    right, left, inf, J = CASES[name]
    E0, A0 = _kcf(right, left, inf, J)
    rng = np.random.default_rng(len(name))
    l, n = E0.shape
    P, Q = _unimodular(rng, l), _unimodular(rng, n)
    dl = np.ldexp(1.0, rng.integers(-25, 26, l))
    dr = np.ldexp(1.0, rng.integers(-25, 26, n))
    E = dl[:, None] * (P @ E0 @ Q) * dr
    A = dl[:, None] * (P @ A0 @ Q) * dr
    ks = fa.kronecker_structure(E, A)
    assert ks.shape == (l, n)
    assert ks.normal_rank == _sympy_normal_rank(P @ E0 @ Q, P @ A0 @ Q)
    assert sorted(ks.right_indices) == sorted(right)
    assert sorted(ks.left_indices) == sorted(left)
    assert sorted(ks.infinite_divisors) == sorted(inf)
    exact = np.linalg.eigvals(J) if len(J) else np.zeros(0)  # J is 1x1, 2x2 integer
    assert_eigenvalues_match(ks.finite_eigenvalues, exact, rtol=1e-9, atol=1e-9)
    assert ks.regular == (l == n and not right and not left)
    assert "minimal indices" in str(ks)


def test_finite_eigenvalues_agree_with_finite_poles_on_regular_pencils():
    """Two algorithms: SLICOT AG08BD's regular part vs fojax's deflation + QZ."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        right, left = (), ()
        inf = tuple(int(k) for k in rng.integers(1, 4, rng.integers(0, 3)))
        J = np.triu(rng.integers(-3, 4, (3, 3)).astype(float))
        E0, A0 = _kcf(right, left, inf, J)
        n = E0.shape[0]
        P, Q = _unimodular(rng, n), _unimodular(rng, n)
        E, A = P @ E0 @ Q, P @ A0 @ Q
        ks = fa.kronecker_structure(E, A)
        assert ks.regular and sorted(ks.infinite_divisors) == sorted(inf)
        assert_eigenvalues_match(ks.finite_eigenvalues, fa.finite_poles(E, A),
                                 rtol=1e-6, atol=1e-6)  # fmt: skip
        assert fa.nilpotency_index(E, A) == (max(inf) if inf else 0)


def test_invariant_zeros_of_a_descriptor_system_against_sympy():
    """Square system (m = p = 1): the invariant zeros are the roots of
    det [[A - sE, B], [C, D]] (sympy). G(s) = 1/(s + 3) - 1 = -(s + 2)/(s + 3)."""
    E = np.array([[1.0, 0, 0], [0, 0, 1], [0, 0, 0]])
    A = np.array([[-3.0, 0, 0], [0, 1, 0], [0, 0, 1]])
    B = np.array([[1.0], [0], [1]])
    C = np.array([[1.0, 0, 1]])
    s = sympy.symbols("s")
    S = sympy.Matrix(np.block([[A, B], [C, np.zeros((1, 1))]]).astype(int))
    S[:3, :3] -= s * sympy.Matrix(E.astype(int))
    roots = sympy.roots(sympy.Poly(S.det(), s))
    assert roots == {-2: 1}
    z = fa.system_zeros(fojax.DescriptorSystem(E, A, B, C))
    assert_eigenvalues_match(z.invariant_zeros, [-2.0], rtol=1e-10)
    assert z.normal_rank == 4


def test_invariant_zeros_with_feedthrough_closed_form():
    """E = I: G(s) = (s + 2)/((s + 1)(s + 3)) + 1 = (s^2 + 5s + 5)/((s + 1)(s + 3));
    zeros (-5 ± sqrt 5)/2. In units 2^±20 of the states."""
    A = np.array([[0.0, 1.0], [-3.0, -4.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[2.0, 1.0]])
    d = np.ldexp(1.0, np.array([20, -20]))
    sysd = fojax.DescriptorSystem(np.eye(2), A * d[None, :] / d[:, None], B / d[:, None],
                                  C * d[None, :])  # fmt: skip
    z = fa.system_zeros(sysd, D=np.array([[1.0]]))
    assert_eigenvalues_match(z.invariant_zeros, [(-5 + 5**0.5) / 2, (-5 - 5**0.5) / 2],
                             rtol=1e-10)  # fmt: skip
    z0 = fa.system_zeros(sysd)
    assert_eigenvalues_match(z0.invariant_zeros, [-2.0], rtol=1e-10)


def test_properness_closed_form():
    """E x' = x + B u with E = [[0, 1], [0, 0]]: x2 = -b2 u, x1 = -b1 u - b2 u'. y = x1:
    improper iff b2 != 0 (y = -u' for B = [0; 1])."""
    E = np.array([[0.0, 1.0], [0.0, 0.0]])
    C = np.array([[1.0, 0.0]])
    bad = fa.properness(fojax.DescriptorSystem(E, np.eye(2), np.array([[0.0], [1.0]]), C))
    good = fa.properness(fojax.DescriptorSystem(E, np.eye(2), np.array([[1.0], [0.0]]), C))
    assert not bad.proper and bad.markov[0] == pytest.approx(1.0)
    assert good.proper


def test_mode_counts_and_the_report():
    """Weierstrass form with one finite mode (-3), one N_2 block (1 non-dynamic + 1
    impulsive mode, Dai 1989); C sees x1 + x3 only, so the finite mode is observable and
    the input reaches x1: no decoupling zeros. Adding an unobserved, uncontrolled finite
    mode (-5) gives one of each."""
    E = np.array([[1.0, 0, 0], [0, 0, 1], [0, 0, 0]])
    A = np.array([[-3.0, 0, 0], [0, 1, 0], [0, 0, 1]])
    sysd = fojax.DescriptorSystem(E, A, np.array([[1.0], [0], [1]]), np.array([[1.0, 0, 1]]))
    mc = fa.mode_counts(sysd)
    assert (mc.finite, mc.nondynamic, mc.impulsive) == (1, 1, 1)
    assert (mc.uncontrollable, mc.unobservable) == (0, 0)
    E4 = np.eye(4)
    E4[:3, :3] = E
    A4 = np.zeros((4, 4))
    A4[:3, :3], A4[3, 3] = A, -5.0
    s4 = fojax.DescriptorSystem(E4, A4, np.array([[1.0], [0], [1], [0]]),
                                np.array([[1.0, 0, 1, 0]]))  # fmt: skip
    mc4 = fa.mode_counts(s4)
    assert (mc4.uncontrollable, mc4.unobservable) == (1, 1)
    assert_eigenvalues_match(mc4.uncontrollable_modes, [-5.0], rtol=1e-10)
    rep = fa.structure_report(s4)
    assert rep.modes.unobservable == 1 and rep.kronecker.infinite_divisors == (2,)
    assert rep.proper is True
    text = str(rep)
    for word in ("Kronecker", "invariant zeros", "modes", "proper", "scaling"):
        assert word in text


def test_singular_pencil_gets_its_minimal_indices_in_the_report():
    """det(sE - A) = 0 for E = diag(1, 0), A = diag(-1, 0): one L_0 and one L_0^T block
    (a zero row and a zero column), normal rank 1 (sympy)."""
    E, A = np.diag([1.0, 0.0]), np.diag([-1.0, 0.0])
    assert _sympy_normal_rank(E, A) == 1
    rep = fa.structure_report(fojax.DescriptorSystem(E, A, np.ones((2, 1)), np.ones((1, 2))))
    assert not rep.regular and rep.normal_rank == 1
    assert rep.kronecker.right_indices == (0,) and rep.kronecker.left_indices == (0,)
    assert rep.proper is None


def test_bad_input_names_the_matrix():
    with pytest.raises(fojax.errors.ShapeError, match="A"):
        fa.kronecker_structure(np.eye(2), np.eye(3))
    with pytest.raises(fojax.errors.InputError, match="DescriptorSystem"):
        fa.system_zeros(np.eye(2))
    with pytest.raises(fojax.errors.ShapeError, match="D"):
        fa.system_zeros(fojax.DescriptorSystem(np.eye(2), -np.eye(2), np.ones((2, 1)),
                                               np.ones((1, 2))), D=np.ones((2, 2)))  # fmt: skip
