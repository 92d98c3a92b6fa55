"""`fojax.plant`: plants (validation messages, the float64 policy, sparse input), fault
augmentation, signals, memberships and uncertain systems.

Oracles: hand-written matrices (eq. 3.196's block structure of `augment_faults`, identity E of
``from_state_space``), closed forms of the signals (step, ramp, sine, piecewise constant,
intermittent, their sums) and of the sector membership (ρ = sin(y)/y as a convex
combination), the uncertain matrix A + δ(t) ΔA written out, and the typed error's
message for each bad input (a fresh 32-bit interpreter for the float64 policy).
"""

import dataclasses
import subprocess
import sys
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax


E2 = [[1.0, 0.0], [0.0, 0.0]]
A2 = [[-1.0, 1.0], [1.0, -2.0]]


def test_dimensions_are_derived_and_matrices_are_leaves():
    s = fojax.DescriptorSystem(E2, A2, [[1.0], [0.0]], [[1.0, 0.0]])
    assert (s.n, s.m, s.p) == (2, 1, 1)
    leaves = jax.tree_util.tree_leaves(s)
    assert len(leaves) == 5 and all(leaf.dtype == jnp.float64 for leaf in leaves)
    # defaults: autonomous (m = 0) and full-state output
    s0 = fojax.DescriptorSystem(E2, A2)
    assert s0.m == 0 and s0.p == 2 and np.array_equal(np.asarray(s0.C), np.eye(2))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(E=[[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], A=A2), r"E has shape \(2, 3\), expected \(2, 2\)"),
        (dict(E=E2, A=[[1.0, 2.0, 3.0], [0.0, 1.0, 2.0]]), r"A has shape \(2, 3\), expected \(2, 2\)"),
        (dict(E=E2, A=A2, B=[[1.0], [0.0], [0.0]]), r"B has shape \(3, 1\), expected \(2, 1\)"),
        (dict(E=E2, A=A2, C=[[1.0, 0.0, 0.0]]), r"C has shape \(1, 3\), expected \(1, 2\)"),
        (dict(E=E2, A=[1.0, 2.0]), r"A has shape \(2,\), expected a 2-d matrix"),
    ],
)
def test_shape_errors_name_the_matrix(kwargs, match):
    with pytest.raises(fojax.errors.ShapeError, match=match) as info:
        fojax.DescriptorSystem(**kwargs)
    assert isinstance(info.value, ValueError)


def test_non_finite_entries_are_refused():
    with pytest.raises(fojax.errors.NonFiniteError, match=r"A contains 1 non-finite .* index \(1, 0\)"):
        fojax.DescriptorSystem(E2, [[-1.0, 1.0], [np.nan, -2.0]])
    with pytest.raises(fojax.errors.NonFiniteError, match="B contains 2 non-finite"):
        fojax.DescriptorSystem(E2, A2, [[np.inf], [-np.inf]])


def test_float32_inputs_are_refused_with_how_to_fix():
    with pytest.raises(fojax.errors.Float64RequiredError, match="A has dtype float32.*jax_enable_x64"):
        fojax.DescriptorSystem(E2, np.asarray(A2, dtype=np.float32))


def test_complex_inputs_are_refused_as_complex_not_as_precision():
    # complex data is not a precision problem: its own message, saying what to do
    A = np.asarray(A2, dtype=complex) + 0.5j * np.eye(2)
    with pytest.raises(fojax.errors.InputError, match=r"A is complex \(complex128, largest \|imaginary part\| "
                       r"0\.5\);.* are real\..*np\.real\(A\).*\[\[Re M, -Im M\], \[Im M, Re M\]\]") as info:
        fojax.DescriptorSystem(E2, A)
    assert not isinstance(info.value, fojax.errors.Float64RequiredError)
    with pytest.raises(fojax.errors.InputError, match=r"^E is complex \(complex64"):
        fojax.DescriptorSystem(np.eye(2, dtype=np.complex64), A2)


def test_32_bit_jax_is_refused_without_changing_global_config():
    code = (
        "import jax, fojax\n"
        "try:\n"
        "    fojax.DescriptorSystem([[1.0]], [[-1.0]])\n"
        "except fojax.errors.Float64RequiredError as e:\n"
        "    print('REFUSED', 'jax_enable_x64' in str(e), jax.config.jax_enable_x64)\n"
    )
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert r.stdout.strip() == "REFUSED True False", r.stdout + r.stderr


def test_fault_augmentation_matches_eq_3_196():
    E = np.diag([1.0, 1.0, 0.0])
    A = np.arange(9.0).reshape(3, 3)
    B = np.array([[1.0], [0.0], [2.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])
    Fa = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 3.0]])
    Fs = np.array([[0.0, 0.0], [0.0, 1.0]])
    aug = fojax.plant.augment_faults(fojax.DescriptorSystem(E, A, B, C), Fa=Fa, Fs=Fs)
    # hand-written blocks
    assert np.array_equal(np.asarray(aug.E), np.diag([1.0, 1.0, 0.0, 1.0, 1.0]))
    assert np.array_equal(np.asarray(aug.A)[:3, :3], A)
    assert np.array_equal(np.asarray(aug.A)[:3, 3:], Fa)
    assert not np.asarray(aug.A)[3:].any()
    assert np.array_equal(np.asarray(aug.C), np.hstack([C, Fs]))
    assert np.array_equal(np.asarray(aug.B), np.vstack([B, np.zeros((2, 1))]))
    # ramp faults: [x; f; f'] with d/dt f = f', d/dt f' = 0
    r = fojax.plant.augment_faults(fojax.DescriptorSystem(E, A, B, C), Fa=Fa, ramp=True)
    assert r.n == 7
    assert np.array_equal(np.asarray(r.A)[3:5, 5:7], np.eye(2))
    assert not np.asarray(r.A)[5:].any()
    with pytest.raises(fojax.errors.ShapeError, match="Fa has shape"):
        fojax.plant.augment_faults(fojax.DescriptorSystem(E, A, B, C), Fa=np.ones((2, 1)))


def test_from_state_space_has_identity_E():
    s = fojax.DescriptorSystem.from_state_space([[0.0, 1.0], [-2.0, -3.0]], [[0.0], [1.0]])
    assert np.array_equal(np.asarray(s.E), np.eye(2))


def test_signals_closed_forms_and_vmap():
    t = jnp.asarray(1.3)
    assert float(fojax.Step([2.0], 1.0)(t)[0]) == 2.0
    assert float(fojax.Step([2.0], 1.5)(t)[0]) == 0.0
    assert np.isclose(float(fojax.Ramp([0.5], 1.0)(t)[0]), 0.15)
    assert np.isclose(float(fojax.Ramp([0.5], 1.0, 1.2)(t)[0]), 0.1)
    assert np.isclose(float(fojax.Sine([2.0], 3.0, 0.5, 1.0)(t)[0]), 1.0 + 2.0 * np.sin(3.9 + 0.5))
    pc = fojax.PiecewiseConstant([1.0, 2.0], [[0.0], [5.0], [-1.0]])
    assert [float(pc(jnp.asarray(x))[0]) for x in (0.5, 1.0, 1.9, 2.0, 9.0)] == [0, 5, 5, -1, -1]
    f = fojax.plant.intermittent([1.0], [(1.0, 2.0), (3.0, 4.0)])
    assert [float(f(jnp.asarray(x))[0]) for x in (0.5, 1.5, 2.5, 3.5, 4.5)] == [0, 1, 0, 1, 0]
    total = fojax.Step([1.0], 0.0) + fojax.Sine([1.0], 1.0)
    assert np.isclose(float(total(t)[0]), 1.0 + np.sin(1.3))
    # a family of step faults with random magnitudes and onsets vmaps (scenarios)
    mags = jnp.array([[1.0], [2.0], [3.0]])
    onsets = jnp.array([0.5, 1.5, 1.0])
    fam = jax.vmap(lambda a, t0: fojax.Step(a, t0))(mags, onsets)
    vals = jax.vmap(lambda s: s(t))(fam)
    assert np.array_equal(np.asarray(vals)[:, 0], [1.0, 0.0, 3.0])


def test_sector_membership_is_a_convex_combination_and_exact():
    # rho = sin(y)/y in [rho_min, 1]: w1 = (1 - rho)/(1 - rho_min) is the weight of the rho_min rule
    m = fojax.plant.SectorMembership(fojax.plant.SincPremise(0), -0.2173, 1.0)
    for y in (0.0, 0.7, 2.0, 4.49):
        w = np.asarray(m(jnp.array([y]), jnp.zeros(0)))
        rho = np.sinc(y / np.pi)
        assert np.isclose(w.sum(), 1.0) and (w >= 0).all()
        assert np.isclose(w[0] * -0.2173 + w[1] * 1.0, rho)


def test_uncertain_system_matrices():
    nom = fojax.DescriptorSystem(E2, A2, [[1.0], [0.0]])
    dA = np.zeros((1, 2, 2))
    dA[0, 0, 1] = 1.0
    unc = fojax.UncertainDescriptorSystem(nom, dA=dA, delta=fojax.Sine([0.3], 2.0))
    A_t, _, _ = unc.matrices(jnp.asarray(0.25))
    assert np.isclose(float(A_t[0, 1]), 1.0 + 0.3 * np.sin(0.5))
    with pytest.raises(fojax.errors.ShapeError, match="delta"):
        fojax.UncertainDescriptorSystem(nom, dA=dA, delta=fojax.Sine([0.3, 0.1], 2.0))


def test_scipy_sparse_matrices_are_densified():
    """Issue 16 item 3: a `scipy.sparse` model used to fail with "E has shape ()" (np.asarray
    wraps it in a 0-d object array). Oracle: the same model built from `.toarray()`."""
    import scipy.sparse as sp

    E, A = np.array(E2), np.array(A2)
    B, C = np.array([[1.0], [0.0]]), np.array([[1.0, 0.0]])
    for make in (sp.csr_matrix, sp.csc_array, sp.coo_matrix):
        s = fojax.DescriptorSystem(make(E), make(A), make(B), make(C))
        dense = fojax.DescriptorSystem(E, A, B, C)
        for a, b in zip(jax.tree_util.tree_leaves(s), jax.tree_util.tree_leaves(dense), strict=True):
            assert a.dtype == jnp.float64 and np.array_equal(np.asarray(a), np.asarray(b))
    # wrong shapes are still named with the sparse matrix's real shape
    with pytest.raises(fojax.errors.ShapeError, match=r"A .*\(3, 3\)"):
        fojax.DescriptorSystem(sp.eye(2), sp.eye(3))


def test_huge_sparse_matrix_is_refused_before_densifying():
    import scipy.sparse as sp

    big = sp.eye(20_000, format="csr")  # 4e8 dense entries (3 GiB) > the 2^27 limit
    with pytest.raises(fojax.errors.InputError, match=r"E is a sparse 20000x20000 matrix .*GiB"):
        fojax.DescriptorSystem(big, big)


def test_design_accepts_a_sparse_model_and_functional():
    """The design entry point on a sparse plant and sparse L verifies like the dense one."""
    import scipy.sparse as sp

    ex = fojax.models.example_4_1_3()
    plant = fojax.DescriptorSystem(sp.csr_matrix(np.asarray(ex.E)), ex.A + ex.B @ ex.L, ex.B, ex.C)
    d = fojax.design_functional_observer(plant, sp.csr_matrix(np.asarray(ex.L)), kind="proportional",
                                         region=fojax.Disk(-2.0, 1.0))
    assert d.report.passed


class _Decay(fojax.plant.AbstractPlant):
    """A user plant E ẋ = A x, y = x₁ whose subclasses give its sizes in three ways."""

    A: eqx.AbstractVar[jax.Array]
    linear_in_state: ClassVar[bool] = True

    def rhs(self, t, x, u):
        return self.A @ x

    def output(self, t, x, u):
        return x[:1]


class _PropertySizes(_Decay):
    """Sizes as properties."""

    E: jax.Array
    A: jax.Array

    @property
    def m(self):
        return 0

    @property
    def p(self):
        return 1


class _FieldSizes(_Decay):
    """Sizes as static fields with defaults."""

    E: jax.Array
    A: jax.Array
    m: int = eqx.field(static=True, default=0)
    p: int = eqx.field(static=True, default=1)


class _RequiredFieldSizes(_Decay):
    """Sizes as static fields the caller must give."""

    E: jax.Array
    A: jax.Array
    m: int = eqx.field(static=True)
    p: int = eqx.field(static=True)


@pytest.mark.parametrize("cls", [_PropertySizes, _FieldSizes, _RequiredFieldSizes])
def test_a_user_plant_may_define_its_sizes_as_properties_or_fields(cls):
    # oracle: x(t) = exp(-t) x0 for A = -I, E = I (closed form)
    sizes = {"m": 0, "p": 1} if cls is _RequiredFieldSizes else {}
    plant = cls(jnp.eye(2), -jnp.eye(2), **sizes)
    assert (plant.n, plant.m, plant.p) == (2, 0, 1)
    assert [f.name for f in dataclasses.fields(plant)][:2] == ["E", "A"]
    ts = jnp.linspace(0.0, 1.0, 11)
    sol = fojax.simulate(plant, jnp.array([1.0, 2.0]), ts)
    np.testing.assert_allclose(sol.xs[-1], np.exp(-1.0) * np.array([1.0, 2.0]), rtol=1e-7)
