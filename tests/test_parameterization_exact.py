"""Conditions a.–d. stay exact for free parameters of any size (issue 14, item 5).

Oracles:
- *The conditions themselves*, evaluated in NumPy on the returned matrices and made relative
  to the norms of their own terms by the one verification routine (`fojax.design.verify`
  through `verify_structure_design` / `certify`): ≤ 1e-8 is the design tolerance.
- *Dead directions from an SVD computed here*: a component of ``Z`` is dead when
  $Z\\,\\Pi_Z(I - \\Gamma\\Gamma^+) = 0$ (it cannot change $T, K$); a row component of
  $Y_1, Y_2, Y_3$ is dead when it lies in the range of $\\Sigma = [R; \\Psi]$
  ($Y_i(I - \\Sigma\\Sigma^+) = 0$). Adding $10^{12}\\times$ such a direction must leave the
  observer unchanged up to the float64 representation of the parameter
  ($\\approx 10^{-16}\\times$ its size), and equal to the observer of
  `fojax.design.project_parameters` up to rounding.
- *Central finite differences* (gradients at parameters with huge dead components).

Cases: the hand example of ``tests/test_tunable.py`` in generic coordinates ($[R;C]$ of
full row rank), the thesis's example 3.3.7 ($\\Sigma$ rank deficient: $N_3 \\ne 0$), and a
random index-1 plant with $\\Gamma$ rank deficient, so that $Z_{\\rm eff} = Z_0 + Z\\Pi_Z$
with $\\Pi_Z \\ne I$ (structure only, no LMI).

Before the fix (dead components multiplied into the matrices): 4e-8 (hand, ``Z``), 1.2e-5
(3.3.7, ``Y2``) at 1e8; 2e-4 … 1e-1 at 1e12.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax.design import (
    design_functional_observer,
    Disk,
    observer_matrices,
    observer_structure,
    project_parameters,
    SteinDisk,
)

# private: the exact structure check and its scales are what this module tests
from fojax.design._functional import condition_scales, verify_structure_design


SIZES = (1e4, 1e8, 1e12)
BLOCKS = ("Z", "Y1", "Y2", "Y3")


def _hand_generic():
    A = np.array([[-1.0, 0.0, 0.0], [1.0, -2.0, 0.0], [0.0, 1.0, -3.0]])
    B, C, L = np.array([[1.0], [0.0], [0.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    Sx = np.random.default_rng(3).standard_normal((3, 3)) + 3 * np.eye(3)
    sysm = fojax.DescriptorSystem(np.eye(3), np.linalg.solve(Sx, A @ Sx), np.linalg.solve(Sx, B), C @ Sx)
    return design_functional_observer(sysm, L @ Sx, kind="generalized", q1=1, region=Disk(-2.0, 1.0), R=L @ Sx)


def _gamma_deficient():
    """Index-1 plant (n = 4, rank E = 3) with R = L of 1 row: rank Σ = 3 and Π_Z ≠ I."""
    rng = np.random.default_rng(0)
    Q1, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    Q2, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    E = Q1 @ np.diag([1.0, 1.0, 1.0, 0.0]) @ Q2
    A0 = rng.standard_normal((4, 4))
    A0[3, 3] += 2.0
    A = Q1 @ A0 @ Q2
    B, C, R = rng.standard_normal((4, 1)), rng.standard_normal((1, 4)), rng.standard_normal((1, 4))
    s = observer_structure(E, A, B, C, R, R, q1=1)
    assert np.linalg.norm(np.asarray(s.PiZ) - np.eye(s.PiZ.shape[0])) > 0.5  # the restriction is active
    params = {k: np.random.default_rng(1).standard_normal(v) for k, v in s.param_shapes().items()}
    return s, params


@pytest.fixture(scope="module")
def cases():
    hand = _hand_generic()
    ex = fojax.models.example_3_3_7()
    d337 = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    s, p = _gamma_deficient()
    return {"hand": (hand.structure, hand.params, hand), "3.3.7": (d337.structure, d337.params, d337),
            "gamma_deficient": (s, p, None)}


def _dead_bases(s):
    """Orthonormal bases (columns) of the dead row directions of Z and of Y1, Y2, Y3 (SVD here)."""
    E, A, C = np.asarray(s.E), np.asarray(s.rules_A())[0], np.asarray(s.C)
    Psi = np.vstack([np.asarray(s.Eperp) @ A, C])
    Gam = np.vstack([E, Psi])
    PG = np.eye(Gam.shape[0]) - Gam @ np.linalg.pinv(Gam)
    U, sv, _ = np.linalg.svd(np.asarray(s.PiZ) @ PG)
    Zdead = U[:, int(np.sum(sv > 1e-8)):]
    Sig = np.vstack([np.asarray(s.R), Psi])
    U, sv, _ = np.linalg.svd(Sig)
    Ydead = U[:, :int(np.sum(sv > 1e-10 * sv[0]))]
    return {"Z": Zdead, "Y1": Ydead, "Y2": Ydead, "Y3": Ydead}


def _dead(s, params, block, size, seed=0):
    """`params` with `size` × (a random dead direction, max-entry 1) added to `block`."""
    basis = _dead_bases(s)[block]
    v0 = np.asarray(params[block])
    dv = np.random.default_rng(seed).standard_normal((v0.shape[0], basis.shape[1])) @ basis.T
    return dict(params, **{block: v0 + size * dv / np.abs(dv).max()})


def _verify(s, p):
    """The one verification routine without the region (random parameters leave it): the report."""
    mats = _mats(s, p)
    res = fojax.design.design_residuals(s, mats, xp=np)
    scale = float(res.pop("scale"))
    return fojax.design.verify({k: float(v) for k, v in res.items()}, scale,
                               np.asarray(fojax.design.error_dynamics(mats, xp=np)), Disk(-2.0, 1.0),
                               raise_on_failure=False, scales=condition_scales(s, mats))


def _mats(s, p):
    return observer_matrices(s, **{k: np.asarray(v) for k, v in p.items()}, xp=np)


def _blocks(m):
    return {k: np.asarray(getattr(m, k)) for k in ("N", "F", "H", "S", "M", "P", "Q", "T", "K", "J", "G")}


@pytest.mark.parametrize("case", ["hand", "3.3.7", "gamma_deficient"])
def test_dead_components_of_every_block_keep_conditions_exact(cases, case):
    s, params, design = cases[case]
    base = _blocks(_mats(s, params))
    unit = max(1.0, max(np.abs(v).max(initial=0.0) for v in base.values()))
    region = Disk(-2.0, 1.0)
    X = None if design is None else design.X
    checked = 0
    for block in BLOCKS:
        if _dead_bases(s)[block].shape[1] == 0 or np.size(params[block]) == 0:
            continue
        for size in SIZES:
            p = _dead(s, params, block, size)
            if design is None:
                mats, rep = _mats(s, p), _verify(s, p)
            else:  # the same observer: the region and its certificate still hold (raises otherwise)
                mats, rep = verify_structure_design(s, p, region, X)
                assert rep.passed, (block, size, rep.failures)
            assert rep.relative_residual <= 1e-8, (block, size, rep.relative_residual)
            got = _blocks(mats)
            # the observer of the projected parameters, to rounding of its own size
            proj = _blocks(_mats(s, project_parameters(s, p, xp=np)))
            for k in got:
                np.testing.assert_allclose(got[k], proj[k], rtol=0, atol=1e-12 * unit, err_msg=f"{block} {size} {k}")
                # and the dead direction changed nothing beyond the float64 rounding of the parameter
                np.testing.assert_allclose(got[k], base[k], rtol=0, atol=1e-13 * size * unit,
                                           err_msg=f"{block} {size} {k}")
            checked += 1
    assert checked >= 3 * len(SIZES)


@pytest.mark.parametrize("case", ["hand", "3.3.7", "gamma_deficient"])
def test_huge_random_parameters_in_every_block_keep_conditions_exact(cases, case):
    """Live and dead parts together, all six blocks (J, G enter no condition but set N's partners)."""
    s, params, _ = cases[case]
    rng = np.random.default_rng(5)
    for size in SIZES:
        for block in ("Z", "Y1", "Y2", "Y3", "J", "G"):
            v0 = np.asarray(params[block])
            p = dict(params, **{block: v0 + size * rng.standard_normal(v0.shape)})
            rep = _verify(s, p)
            assert rep.relative_residual <= 1e-8, (block, size, rep.relative_residual)
        p = {k: np.asarray(v) + size * rng.standard_normal(np.shape(v)) for k, v in params.items()}
        assert _verify(s, p).relative_residual <= 1e-8, size


def test_certify_accepts_huge_dead_components_and_gives_the_same_observer(cases):
    """The public route: SteinDisk(design).certify at 1e12 × a dead direction of Z and of Y2."""
    s, params, d = cases["hand"]
    par = SteinDisk(d)
    p0 = par.init(d)
    p = _dead(s, _dead(s, {k: np.asarray(v) for k, v in p0.items()}, "Z", 1e12), "Y2", 1e12, seed=1)
    out = fojax.design.certify(par, {k: jnp.asarray(v) for k, v in p.items()})
    assert out.report.passed and out.report.relative_residual <= 1e-8
    assert float(par.margin(p)) > 0
    for name in "NJFHSGMPQ":
        np.testing.assert_allclose(np.asarray(getattr(out.observer, name)), np.asarray(getattr(d.observer, name)),
                                   rtol=0, atol=1e-3, err_msg=name)  # 1e12 · eps ≈ 2e-4: the parameter's rounding


def test_gradients_at_huge_dead_components_match_finite_differences(cases):
    """jit(grad) and vmap of a quadratic function of Z (through the matrices linear in it) at 1e8 × dead directions in Z
    and Y1: central differences (exact for a quadratic up to rounding) along a live and a dead
    direction; the dead one has zero derivative."""
    s, params, _ = cases["3.3.7"]
    p = _dead(s, _dead(s, params, "Z", 1e8), "Y1", 1e8, seed=2)
    p = {k: jnp.asarray(v) for k, v in p.items()}

    def f(q):
        m = observer_matrices(s, **q)
        return sum(jnp.sum(x**2) for x in (m.N, m.S, m.M, m.P, m.Q, m.T, m.K))  # F is quadratic in Z: left out

    g = jax.jit(jax.grad(f))(p)
    f = jax.jit(f)
    rng = np.random.default_rng(3)
    live_Z = np.asarray(project_parameters(s, {"Z": rng.standard_normal(p["Z"].shape)}, xp=np)["Z"])
    dead_Z = _dead(s, {"Z": np.zeros(p["Z"].shape)}, "Z", 1.0, seed=4)["Z"]
    h = 10.0  # the function is quadratic; h ≫ the parameters' rounding (1e8 · eps ≈ 1e-8)
    for direction in (live_Z, dead_Z):
        fd = (float(f(dict(p, Z=p["Z"] + h * direction))) - float(f(dict(p, Z=p["Z"] - h * direction)))) / (2 * h)
        ad = float(jnp.vdot(g["Z"], direction))
        scale = float(jnp.linalg.norm(g["Z"])) * np.linalg.norm(direction)
        assert abs(ad - fd) <= 1e-6 * scale, (ad, fd, scale)
    assert abs(float(jnp.vdot(g["Z"], dead_Z))) <= 1e-9 * float(jnp.linalg.norm(g["Z"]))
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), p)
    np.testing.assert_allclose(np.asarray(jax.vmap(f)(batch)), [float(f(p))] * 2, rtol=1e-12)
