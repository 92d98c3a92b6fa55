"""Tunable parameterizations (`fojax.design.AbstractParameterization`): live parameters,
`certify`, jit/vmap/grad safety, one tuning stack (exactness of a.–d. at any parameter size:
``tests/test_parameterization_exact.py``).

Oracles:
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
    design_functional_observer,
    Disk,
    FixedCertificateDisk,
    observer_matrices,
    SteinDisk,
)


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
