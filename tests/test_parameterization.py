"""Tunable parameterizations of `fojax.design`: `AbstractParameterization` and its finals (live
parameters, `certify`, jit/vmap/grad safety, one tuning stack), conditions a.–d. exact for free
parameters of any size (`project_parameters`), and the explicit gain maps `contraction`,
`disk_gain`, `lemma10_gain` (every parameter value gives a certified observer).

**Live parameters and `certify`.** Oracles:
- *A hand derivation* (live parameters). Plant $\\dot x = Ax + Bu$, $y = x_1$,
  $A = [[-1,0,0],[1,-2,0],[0,1,-3]]$, $z = x_2$, order $q_0 = 1$ ($R = L$). Every order-1
  functional observer is $\\zeta = x_2 + a x_1$: $\\dot\\zeta = -2\\zeta + (1 + a)y$,
  $\\hat z = \\zeta - a y$ (condition a. forces $N = -2$). So exactly **one** direction
  reaches $\\hat z$ (the transfer function $(1 - a - as)/(s + 2)$ changes with $a$), and it
  is carried by ``Z`` (through $T = R - KC$, $a = -K$); $[R; C]$ has full row rank, so
  $N_3 = F_3 = 0$: $Y_1, Y_2, Y_3$ enter no matrix, $S = M = 0$ and $J, G$ act on an
  unexcited $v$: all dead.
- *NumPy eigenvalues and SciPy's Stein solver* (`certify`), *central finite differences*
  (gradients).

**Conditions a.–d. at any parameter size.** Oracles:
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

Cases: the hand example above in generic coordinates ($[R;C]$ of
full row rank), the thesis's example 3.3.7 ($\\Sigma$ rank deficient: $N_3 \\ne 0$), and a
random index-1 plant with $\\Gamma$ rank deficient, so that $Z_{\\rm eff} = Z_0 + Z\\Pi_Z$
with $\\Pi_Z \\ne I$ (structure only, no LMI).

Before the fix (dead components multiplied into the matrices): 4e-8 (hand, ``Z``), 1.2e-5
(3.3.7, ``Y2``) at 1e8; 2e-4 … 1e-1 at 1e12.

**Explicit gain maps.** Oracles: NumPy eigenvalues of the error matrix (inside the disk, or
Hurwitz for Lemma 10) and ``eigvalsh`` of the region's LMI at the returned certificate; the
operator 2-norm of the contraction (< 1); the LMI design's own gain, reproduced by `disk_gain`;
central finite differences for the gradients, under `jax.vmap`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax import studies as S, tuning
from fojax.design import (
    certify,
    CommonCertificate,
    contraction,
    design_functional_observer,
    Disk,
    disk_gain,
    FixedCertificateDisk,
    lemma10_gain,
    observer_matrices,
    observer_structure,
    pieces,
    project_parameters,
    SteinDisk,
)

# private: the exact structure check and its scales are what this module tests
from fojax.design._functional import condition_scales, verify_structure_design


A_HAND = np.array([[-1.0, 0.0, 0.0], [1.0, -2.0, 0.0], [0.0, 1.0, -3.0]])
B_HAND = np.array([[1.0], [0.0], [0.0]])
C_HAND = np.array([[1.0, 0.0, 0.0]])
L_HAND = np.array([[0.0, 1.0, 0.0]])


def _hand(Sx=None):
    """The hand example, optionally in coordinates x = Sx x̃ (the same plant)."""
    Sx = np.eye(3) if Sx is None else Sx
    A, B, C, L = np.linalg.solve(Sx, A_HAND @ Sx), np.linalg.solve(Sx, B_HAND), C_HAND @ Sx, L_HAND @ Sx
    return fojax.DescriptorSystem(np.eye(3), A, B, C), L


@pytest.fixture(scope="module")
def hand_designs():
    sysm, L = _hand()
    opts = dict(region=Disk(-2.0, 1.0), R=L)
    return {"proportional": design_functional_observer(sysm, L, kind="proportional", **opts),
            "generalized": design_functional_observer(sysm, L, kind="generalized", q1=1, **opts)}


def test_live_parameters_known_by_hand(hand_designs):
    d = hand_designs["generalized"]
    par = SteinDisk(d)
    lv = par.live(par.init(d))
    total = sum(int(np.size(v)) for v in d.params.values())
    assert (lv.live, lv.total) == (1, total)  # one live direction (the hand derivation)
    assert lv.singular_values[1] <= 1e-12 * lv.singular_values[0]  # the others are zero, not small
    # it lies in Z: the rows of Y1, Y2, Y3, J, G in the live basis vanish
    offsets = np.cumsum([0] + [int(np.prod(shape)) for _, shape in lv.names])
    for (name, _), a, b in zip(lv.names, offsets[:-1], offsets[1:]):
        if name != "Z":
            assert np.abs(lv.basis[a:b]).max(initial=0.0) <= 1e-12, name
    assert "1 of" in str(lv)
    # the same verdict for the LMI design itself (all six parameters, Z included)
    lv_design = fojax.design.live_parameters(d)
    assert (lv_design.live, lv_design.total) == (1, total)
    # the "generalized" observer's extra freedom is void (issue 14 item 4): only Z is live, and it says so
    assert lv.live_blocks() == lv_design.live_blocks() == ("Z",)
    assert lv_design.void_generalized and "void" in str(lv_design) and "cannot: G, J, Y1, Y2, Y3" in str(lv)
    lv_p = fojax.design.live_parameters(hand_designs["proportional"])
    assert lv_p.live == 1 and not lv_p.void_generalized and "void" not in str(lv_p)


def test_tune_moves_only_live_directions_and_reports_them(hand_designs):
    d = hand_designs["generalized"]
    sysm, L = _hand()
    # the training study, optimizer and (square) coordinates of the whitened-tuning test below with
    # precondition="none": one compiled tuning step serves both tests
    st = S.Study(sysm, jnp.array([1.0, -1.0, 0.5]), jnp.linspace(0.0, 3.0, 31), L, fojax.Sine(jnp.array([1.0]), 1.0))
    res = tuning.tune(d, st, steps=3, optimizer=tuning.shared_optimizer("adam", learning_rate=0.1), stepper=fojax.Exact())
    assert res.live_parameters.live == 1
    assert res.design.solver["tuning"]["live_parameters"] == 1
    assert res.design.solver["tuning"]["free_parameters"] == res.live_parameters.total
    for name in ("Y1", "Y2", "Y3", "J", "G"):  # dead: never moved
        np.testing.assert_array_equal(np.asarray(res.params[name]), d.params[name])
    assert res.design.report.passed and all(res.history["accepted"])
    assert np.abs(np.asarray(res.params["Z"]) - d.params["Z"]).max() > 0  # the live one did move
    # one public call turns the tuned parameters into the same verified design (issue 14 item 6)
    again = certify(res.parameterization, res.params)
    assert again.report.passed
    for name in "NJFHSGMPQ":
        np.testing.assert_allclose(np.asarray(getattr(again.observer, name)),
                                   np.asarray(getattr(res.design.observer, name)), rtol=0, atol=1e-12)


def _scaled_twin(Dr, Dx):
    """The hand example with equations scaled by diag(Dr) and states x = diag(Dx) x̃."""
    Dr, Dx = np.diag(Dr), np.diag(Dx)
    sysm = fojax.DescriptorSystem(Dr @ Dx, Dr @ A_HAND @ Dx, Dr @ B_HAND, C_HAND @ Dx)
    return sysm, L_HAND @ Dx


def test_whitened_tuning_is_invariant_to_rescaling_rows_and_states():
    """The same model with rows scaled by (1e-3, 1, 1e3) and states by (1e3, 1e-3, 1): with
    precondition="whiten" both tune to the same held-out IAE (within 5 %; measured: equal to
    9 digits); with the raw parameters the rescaled twin barely moves in the same steps."""
    opt = tuning.shared_optimizer("adam", learning_rate=0.1)
    out = {}
    for name, (Dr, Dx) in {"plain": (np.ones(3), np.ones(3)),
                           "scaled": (np.array([1e-3, 1.0, 1e3]), np.array([1e3, 1e-3, 1.0]))}.items():
        sysm, L = _scaled_twin(Dr, Dx)
        d = design_functional_observer(sysm, L, kind="generalized", q1=1, region=Disk(-2.0, 1.0), R=L)
        u = fojax.Sine(jnp.array([1.0]), 1.0)
        ts = jnp.linspace(0.0, 3.0, 31)
        train = S.Study(sysm, jnp.asarray(np.array([1.0, -1.0, 0.5]) / Dx), ts, L, u)
        held = S.Study(sysm, jnp.asarray(np.array([-0.5, 1.0, 1.0]) / Dx), ts, L, u)
        for pre in ("whiten", "none"):
            r = tuning.tune(d, train, heldout=held, steps=10, optimizer=opt, stepper=fojax.Exact(), precondition=pre,
                            eval_every=100)
            out[name, pre] = (r.initial_heldout, r.final_heldout)
    print(out)
    w0, w1 = out["plain", "whiten"][1], out["scaled", "whiten"][1]
    assert abs(w1 - w0) <= 0.05 * w0
    assert w0 < 0.9 * out["plain", "whiten"][0]  # it did tune
    # the raw parameters are not invariant: the rescaled twin ends elsewhere
    assert abs(out["scaled", "none"][1] - out["plain", "none"][1]) > 0.05 * out["plain", "none"][1]


@pytest.mark.parametrize("cls", [SteinDisk, FixedCertificateDisk])
def test_certify_reproduces_the_design_and_refuses_outside(hand_designs, cls):
    d = hand_designs["generalized"]
    par = cls(d)
    p = par.init(d)
    out = certify(par, p)
    assert out.report.passed and out.report.relative_residual <= 1e-8
    for name in "NJFHSGMPQ":
        np.testing.assert_allclose(np.asarray(getattr(out.observer, name)), np.asarray(getattr(d.observer, name)),
                                   atol=1e-9)
    Aa = out.error_matrix + 2.0 * np.eye(out.error_matrix.shape[0])  # disk LMI at the certificate
    assert np.linalg.eigvalsh(Aa.T @ out.X @ Aa - out.X).max() < 0
    with pytest.raises(fojax.errors.InputError, match="AbstractParameterization"):
        certify(d, p)


def test_certify_raises_outside_the_region(hand_designs):
    """A tampered parameter set: the typed error names the eigenvalue outside and by how much
    (oracle: NumPy's eigenvalues of the error dynamics built here from N, J, S, G)."""
    d = hand_designs["generalized"]
    par = SteinDisk(d)
    p = dict(par.init(d), G=jnp.array([[5.0]]))  # v-mode at +5: outside Disk(-2, 1)
    assert float(par.margin(p)) < 0
    m = observer_matrices(d.structure, **par.design_params(p), xp=np)
    ev = np.linalg.eigvals(np.block([[m.N[0], m.J[0]], [m.S[0], m.G[0]]]))
    worst = ev[np.argmax(np.abs(ev + 2.0))]
    with pytest.raises(fojax.errors.DesignVerificationError, match=r"eigenvalue \S+ is outside the region \(disk centred at "
                       r"-2 with radius 1\) by [0-9.]+e[+-]\d+") as err:
        certify(par, p)
    assert f"by {abs(worst + 2.0) - 1.0:.3e}" in str(err.value)
    assert err.value.report.region_margin == pytest.approx(-(abs(worst + 2.0) - 1.0), rel=1e-9)
    assert par.host_check(p)[0] is False


def test_certify_docstring_example(hand_designs):
    """The example of `fojax.design.certify`'s docstring, on the hand example."""
    design = hand_designs["generalized"]
    par = SteinDisk(design)
    params = par.init(design)
    params["G"] = params["G"] - 0.5
    verified = certify(par, params)
    assert verified.report.passed and verified.report.relative_residual <= 1e-8
    assert verified.report.region_margin > 0 and verified.verify().passed
    np.testing.assert_allclose(np.asarray(verified.observer.G), np.asarray(design.observer.G) - 0.5, atol=1e-12)


def test_margin_and_barrier_jit_vmap_grad_and_no_retrace(hand_designs):
    d = hand_designs["generalized"]
    par = SteinDisk(d)
    p = par.init(d)
    f = eqx.filter_jit(eqx.debug.assert_max_traces(lambda pr, q: pr.barrier(q), max_traces=1))
    b0 = float(f(par, p))
    assert np.isfinite(b0)
    f(par, dict(p, G=p["G"] - 0.1))  # new numbers: no retrace
    other = SteinDisk(design_functional_observer(*_hand(), kind="generalized", q1=1, region=Disk(-2.0, 1.0),
                                                 R=_hand()[1]))
    f(other, p)  # another parameterization of the same shapes: data are leaves
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), p)
    np.testing.assert_allclose(np.asarray(jax.vmap(par.barrier)(batch)), [b0, b0], rtol=1e-12)
    g = jax.jit(jax.grad(par.barrier))(p)
    h = 1e-6
    for name, idx in (("G", (0, 0)), ("J", (0, 0))):
        fd = (float(par.barrier(dict(p, **{name: p[name].at[idx].add(h)})))
              - float(par.barrier(dict(p, **{name: p[name].at[idx].add(-h)})))) / (2 * h)
        np.testing.assert_allclose(float(g[name][idx]), fd, rtol=1e-6, atol=1e-9)


def test_host_margin_is_one_compiled_program(hand_designs):
    """`host_check` (every tuning iterate) computes the margin with one compiled program per
    structure, shared with `SteinDisk.__init__`'s check; new numbers and another
    parameterization of the same shapes do not compile again (issue 13: eagerly it cost ~0.1 s
    a call). Oracle: the eager margin, and the sign from NumPy's eigenvalues (the disk test)."""
    # private: MARGIN_TRACES, the no-retrace check
    from fojax.design import _tunable

    d = hand_designs["generalized"]
    before = _tunable.MARGIN_TRACES["margin"]
    par = SteinDisk(d)  # __init__ checks the starting margin with the same program
    p = par.init(d)
    for q in (p, dict(p, G=p["G"] - 0.1), dict(p, G=jnp.array([[5.0]]))):
        m = par.host_margin(q)
        np.testing.assert_allclose(m, float(par.margin(q)), rtol=1e-12)
        mats = observer_matrices(d.structure, **par.design_params(q), xp=np)
        ev = np.linalg.eigvals(np.block([[mats.N[0], mats.J[0]], [mats.S[0], mats.G[0]]]))
        assert (m > 0) == bool(np.all(np.abs(ev + 2.0) < 1.0))
        par.host_check(q)
    other = SteinDisk(design_functional_observer(*_hand(), kind="generalized", q1=1, region=Disk(-2.0, 1.0),
                                                 R=_hand()[1]))
    other.host_check(p)
    assert _tunable.MARGIN_TRACES["margin"] - before <= 1  # 0 if an earlier test compiled it


def test_common_certificate_refuses_lti_designs(hand_designs):
    with pytest.raises(fojax.errors.InputError, match="needs a TakagiSugenoObserverDesign"):
        CommonCertificate(hand_designs["generalized"])
    with pytest.raises(fojax.errors.InputError, match="parameterization must be one of"):
        tuning.make_parameterization(hand_designs["generalized"], "bogus")


# ==================================================================================================
# Conditions a.–d. stay exact for free parameters of any size (issue 14, item 5).
# ==================================================================================================


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


# ==================================================================================================
# Explicit gain parameterizations: every parameter value gives a certified observer.
# ==================================================================================================


@pytest.fixture(scope="module")
def design_data():
    ex = fojax.models.example_4_1_3()
    d = design_functional_observer(ex.system, ex.L, kind="generalized", region=Disk(-2.0, 1.0))
    s = d.structure
    pc = pieces(s, xp=np)
    q0, q1, c = s.q0, s.q1, pc.N3.shape[0]
    Z = d.params["Z"]
    A1 = np.block([[pc.N1[0] - Z @ pc.N2[0], np.zeros((q0, q1))], [np.zeros((q1, q0 + q1))]])
    A2 = np.block([[pc.N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    return d, A1, A2


def test_contraction_is_inside_unit_ball(rng):
    for scale in (0.1, 1.0, 100.0):
        Lc = np.asarray(contraction(jnp.asarray(scale * rng.normal(size=(5, 3)))))
        assert np.linalg.norm(Lc, 2) < 1.0


def test_disk_gain_every_parameter_is_in_the_disk(design_data, rng):
    d, A1, A2 = design_data
    X = d.X
    k = np.linalg.matrix_rank(A2)
    region = Disk(-2.0, 1.0)
    for _ in range(20):
        Lc = contraction(jnp.asarray(3.0 * rng.normal(size=(X.shape[0], k))))
        Yp = jnp.asarray(rng.normal(size=(X.shape[0], A2.shape[0])))
        Y, margin = disk_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, Lc, Yp, rank=k)
        assert float(margin) > 0
        Aa = A1 - np.asarray(Y) @ A2
        assert region.contains(np.linalg.eigvals(Aa))
        # X certifies it: the region LMI evaluated in float64 is negative definite
        assert np.linalg.eigvalsh(region.lmi_matrix(X, X @ Aa)).max() < 0


def test_disk_gain_reproduces_the_lmi_gain(design_data):
    # The LMI's own gain lies in the parameterized set: choosing Lc from it recovers 𝔸.
    d, A1, A2 = design_data
    Aa_lmi = d.error_matrix
    X = d.X
    k = np.linalg.matrix_rank(A2)
    Lx = np.linalg.cholesky(X)
    LxinvT = np.linalg.inv(Lx.T)
    M = Lx.T @ (Aa_lmi + 2.0 * np.eye(X.shape[0])) @ LxinvT
    U, s, Vt = np.linalg.svd(A2 @ LxinvT)
    Vb, Vp = Vt[:k].T, Vt[k:].T
    M0 = Lx.T @ (A1 + 2.0 * np.eye(X.shape[0])) @ LxinvT
    F = np.linalg.cholesky(np.eye(X.shape[0]) - (M0 @ Vp) @ (M0 @ Vp).T)
    Lc = np.linalg.solve(F, M @ Vb)
    assert np.linalg.norm(Lc, 2) < 1.0
    Y, _ = disk_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, jnp.asarray(Lc), rank=k)
    assert np.allclose(A1 - np.asarray(Y) @ A2, Aa_lmi, atol=1e-8)


def test_lemma10_gain_is_hurwitz_with_certificate(design_data, rng):
    d, A1, A2 = design_data
    X = d.X
    for gamma in (10.0, 100.0):
        Lc = contraction(jnp.asarray(rng.normal(size=(A2.shape[0], X.shape[0]))))
        Y, margin = lemma10_gain(jnp.asarray(X), jnp.asarray(A1), jnp.asarray(A2), Lc, gamma)
        if float(margin) <= 0:
            continue
        Aa = A1 - np.asarray(Y) @ A2
        assert np.linalg.eigvals(Aa).real.max() < 0
        assert np.linalg.eigvalsh(X @ Aa + Aa.T @ X).max() < 0


def test_disk_gain_gradients_match_finite_differences(design_data, rng):
    d, A1, A2 = design_data
    X = jnp.asarray(d.X)
    k = int(np.linalg.matrix_rank(A2))
    Theta0 = jnp.asarray(rng.normal(size=(X.shape[0], k)))

    def f(Theta):
        Y, _ = disk_gain(X, jnp.asarray(A1), jnp.asarray(A2), -2.0, 1.0, contraction(Theta), rank=k)
        Aa = jnp.asarray(A1) - Y @ jnp.asarray(A2)
        return jnp.sum(Aa**2)

    g = jax.jit(jax.grad(f))(Theta0)
    eps = 1e-6
    for idx in [(0, 0), (1, 0), (X.shape[0] - 1, k - 1)]:
        e = jnp.zeros_like(Theta0).at[idx].set(eps)
        fd = (f(Theta0 + e) - f(Theta0 - e)) / (2 * eps)
        assert np.isclose(float(g[idx]), float(fd), rtol=1e-5, atol=1e-8)
    # vmap over a batch of parameters
    batch = jnp.asarray(rng.normal(size=(4,) + Theta0.shape))
    vals = jax.vmap(f)(batch)
    assert np.allclose(np.asarray(vals), [float(f(b)) for b in batch])
