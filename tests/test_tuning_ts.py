"""`fojax.tune` of a Takagi–Sugeno functional observer on the nonlinear robot arm: the tuned
observer keeps the LMI design's common certificate, and its held-out IAE (physical-parameter
uncertainty on k, m, J_l; samples never seen in training) drops.

Oracles: the LMI design's own observer (the start, exactly); the common Lyapunov LMI of every
rule by ``eigvalsh`` at every accepted iterate and the float64 verification of the final
design; the held-out IAE of unseen samples; central finite differences of `study_loss`; the
uninterrupted run for a resumed one (bit for bit).
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import WeightedPenalty

import fojax
from fojax.design import (
    CommonCertificate,
    design_functional_observer,
    design_residuals,
    design_ts_observer,
    Disk,
    error_dynamics,
    observer_matrices,
    TakagiSugenoObserverDesign,
)
from fojax.models import example_3_3_7, robot_arm, robot_arm_ts
from fojax.studies import parameter_uncertainty, run_study, SimConfig, Study, study_loss
from fojax.tuning import tune

# private: TRACE_COUNTS, the no-retrace check
from fojax.tuning._tune import TRACE_COUNTS


def initial_ts_parameters(des, region=None):
    par = CommonCertificate(des, region)
    return par, par.init(des)


def ts_observer_from_parameters(par, params):
    return par.observer(params)


L_ARM = np.eye(5)[[1, 3]]  # z = [x2, x4] (x5 is refused by the T-S observer, see test_takagi_sugeno)
# q0 = 4, the GDO order of §3.3.6. With the default R (q0 = 2) N3 = 0: Y1, Y2, Y3 have no
# effect and v is never excited, so only the common Z would move.
R4 = np.eye(5)[[1, 3, 0, 2]]
SPREAD = {"k": 0.2, "m": 0.2, "J_l": 0.2}  # ±20 % on the physical parameters
N_TRAIN, N_HELDOUT = 8, 16
T_END = 3.0
TS = np.linspace(0.0, T_END, 61)
U = fojax.Sine(jnp.array([0.5]), 1.0)
STEPS, LR, BARRIER = 30, 0.1, 1e-3
OPT = optax.adam(optax.cosine_decay_schedule(LR, STEPS, alpha=0.05))
SOLVER = diffrax.Tsit5()  # the arm and the observer (poles in [-3, -1]) are not stiff
STEPPER = fojax.Auto(diffrax=fojax.Diffrax(SOLVER))


def _g_size(obs, p):  # a user term on the per-rule generalized-state gains G_i: Σ G²
    return jnp.sum(p["G"] ** 2)


G_WEIGHT = 0.1
NO_PENALTY = WeightedPenalty(0.0, _g_size)  # `run` and the resume test: one compiled step (helpers)


def _study(theta_family):
    arm = robot_arm()
    return Study(arm.system, robot_arm_ts().x0, TS, L_ARM, u=U, uncertainty=(theta_family,))


@pytest.fixture(scope="module")
def setup():
    des = design_ts_observer(robot_arm_ts().system, L_ARM, kind="generalized", R=R4)  # Disk(-2, 1)
    theta = robot_arm().system.theta
    train = _study(parameter_uncertainty(jax.random.PRNGKey(0), N_TRAIN, theta, SPREAD))
    heldout = _study(parameter_uncertainty(jax.random.PRNGKey(1), N_HELDOUT, theta, SPREAD))
    return des, train, heldout


@pytest.fixture(scope="module")
def run(setup):
    des, train, heldout = setup
    iterates = []
    before = TRACE_COUNTS["tune_step"]
    res = tune(des, train, heldout=heldout, steps=STEPS, optimizer=OPT, barrier=BARRIER,
               stepper=STEPPER, extra_loss=NO_PENALTY, callback=lambda k, rec: iterates.append(rec))
    return res, iterates, TRACE_COUNTS["tune_step"] - before


def _rule_matrices(des, params):
    p = {k: np.asarray(v) for k, v in params.items()}
    full = {k: p.get(k, np.asarray(des.params[k])) for k in des.params}
    mats = observer_matrices(des.structure, **full, xp=np)
    return mats, np.asarray(error_dynamics(mats, xp=np))


def test_starts_exactly_at_the_lmi_design(setup):
    des, _, _ = setup
    fx, params = initial_ts_parameters(des)
    for k, v in params.items():
        np.testing.assert_array_equal(np.asarray(v), des.params[k])
    obs = ts_observer_from_parameters(fx, params)
    for name in "NJFHSGMPQ":
        np.testing.assert_allclose(np.asarray(getattr(obs, name)), np.asarray(getattr(des.observer, name)),
                                   rtol=0, atol=1e-12 * max(1.0, np.abs(getattr(des.observer, name)).max()))


def test_tuning_reduces_heldout_iae_on_the_nonlinear_arm(setup, run):
    des, train, heldout = setup
    res, _, traces = run
    assert traces == 1  # one compiled step for the whole run
    # held-out IAE recomputed independently by the study runner (separate code path)
    out = run_study(heldout, [des.observer, res.design.observer], stepper=STEPPER, quantiles=(), quiet=True)
    assert out.metrics["success"].all()
    iae = out.metrics["iae"].mean(axis=(1, 2, 3))
    np.testing.assert_allclose(iae, [res.initial_heldout, res.final_heldout], rtol=1e-9)
    reduction = 1.0 - iae[1] / iae[0]
    print(f"\nT-S robot arm: held-out mean IAE {iae[0]:.4f} -> {iae[1]:.4f} ({100 * reduction:.1f} % lower; "
          f"{N_TRAIN} train / {N_HELDOUT} held-out samples, {STEPS} steps, adam cosine lr {LR})")
    assert reduction >= 0.35  # measured: 41 %
    assert res.history["train_loss"][-1] < res.history["train_loss"][0]


def test_every_accepted_iterate_satisfies_the_common_lmi(setup, run):
    """Disk Q(α, τ) LMI in Schur form, τ²X − (𝔸_i − αI)ᵀX(𝔸_i − αI) ≻ 0, and 𝔸_iᵀX + X𝔸_i ≺ 0 for
    every rule at the design's X — recomputed here from the recorded parameters."""
    des, _, _ = setup
    _, iterates, _ = run
    X, al, tau = des.X, des.region.center, des.region.radius
    assert sum(r["accepted"] for r in iterates) >= STEPS // 2
    for rec in iterates:
        _, As = _rule_matrices(des, rec["params"])
        for A in As:
            Ac = A - al * np.eye(A.shape[0])
            assert np.linalg.eigvalsh(tau**2 * X - Ac.T @ X @ Ac).min() > 0
            assert np.linalg.eigvalsh(A.T @ X + X @ A).max() < 0
            assert np.all(np.abs(np.linalg.eigvals(A) - al) < tau)


def test_final_design_is_verified(setup, run):
    des, _, _ = setup
    res, _, _ = run
    tuned = res.design
    assert isinstance(tuned, TakagiSugenoObserverDesign) and tuned.report.passed
    np.testing.assert_array_equal(tuned.X, des.X)  # the common certificate is unchanged
    mats, As = _rule_matrices(des, res.params)
    r = design_residuals(des.structure, mats, xp=np)
    scale = float(r.pop("scale"))
    assert max(float(v) for v in r.values()) / scale <= 1e-8
    for A, A_obs in zip(As, tuned.error_matrices):
        np.testing.assert_allclose(A_obs, A, rtol=0, atol=1e-12 * np.abs(A).max())
        assert des.region.contains(np.linalg.eigvals(A))
    assert tuned.report.extra["lyapunov_max_eig"] < 0
    # the gains did move
    assert np.abs(np.asarray(res.params["Y1"]) - des.params["Y1"]).max() > 1e-3


def test_study_loss_gradient_matches_central_differences(setup):
    """∂ loss / ∂ (one entry of rule 2's Y1, of rule 1's Y3, of the common Z), short horizon. (At the
    LMI design Y2 = 0, so v is not excited and J, G have no first-order effect yet.)"""
    des, _, _ = setup
    theta = robot_arm().system.theta
    arm = robot_arm()
    st = Study(arm.system, robot_arm_ts().x0, TS[:21], L_ARM, u=U,
               uncertainty=(parameter_uncertainty(jax.random.PRNGKey(2), 2, theta, SPREAD),))
    cfg = SimConfig(stepper=fojax.Auto(diffrax=fojax.Diffrax(SOLVER, rtol=1e-11, atol=1e-13)))
    fx, params = initial_ts_parameters(des)

    @jax.jit
    def vg(p):
        return jax.value_and_grad(lambda q: study_loss(st, ts_observer_from_parameters(fx, q), cfg=cfg))(p)

    _, g = vg(params)
    for name, idx in (("Y1", (1, 0, 2)), ("Y3", (0, 1, 3)), ("Z", (1, 0))):
        h = 1e-4 * max(1.0, abs(float(params[name][idx])))

        def at(d, name=name, idx=idx):
            return float(vg(dict(params, **{name: params[name].at[idx].add(d)}))[0])

        fd = (at(h) - at(-h)) / (2 * h)
        print(f"\nd loss / d {name}{list(idx)}: jax.grad {float(g[name][idx]):.10e}, central FD {fd:.10e}")
        assert abs(fd) > 1e-6, (name, fd)
        assert abs(float(g[name][idx]) - fd) <= 1e-5 * abs(fd), (name, float(g[name][idx]), fd)


def test_refusals():
    ex = example_3_3_7()
    lti = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    with pytest.raises(fojax.errors.InputError, match=r"needs a TakagiSugenoObserverDesign .* got FunctionalObserverDesign"):
        initial_ts_parameters(lti)
    ts_sys = robot_arm_ts().system
    pi = design_ts_observer(ts_sys, L_ARM, kind="PI")
    with pytest.raises(fojax.errors.InputError, match=r"generalized and proportional designs; got kind='PI'"):
        initial_ts_parameters(pi)
    des = design_ts_observer(ts_sys, L_ARM, kind="generalized")
    with pytest.raises(fojax.errors.InputError, match=r"does not satisfy the LMI of disk centred at -2 with radius 0.3"):
        initial_ts_parameters(des, Disk(-2.0, 0.3))
    arm = robot_arm()
    one_signal = Study(arm.system, robot_arm_ts().x0, TS, L_ARM[:1], u=U)
    with pytest.raises(fojax.errors.InputError, match=r"the study has 1 signals but the observer estimates 2"):
        tune(des, one_signal, steps=1)


def test_proportional_design_parameters():
    """q1 = 0: the empty v-blocks (Y2, J, G) are not tuning parameters; the start is the design."""
    des = design_ts_observer(robot_arm_ts().system, L_ARM, kind="proportional", R=R4)
    fx, params = initial_ts_parameters(des)
    assert sorted(params) == ["Y1", "Y3", "Z"]
    obs = ts_observer_from_parameters(fx, params)
    assert obs.q1 == 0 and obs.kind == "proportional"
    for name in "NFHPQ":
        np.testing.assert_allclose(np.asarray(getattr(obs, name)), np.asarray(getattr(des.observer, name)),
                                   rtol=0, atol=1e-12 * max(1.0, np.abs(getattr(des.observer, name)).max()))


def test_resume_from_checkpoint_equals_uninterrupted(setup, run, tmp_path):
    des, train, _ = setup
    opts = dict(optimizer=OPT, barrier=BARRIER, stepper=STEPPER, extra_loss=NO_PENALTY)  # `run`'s compiled step
    ref = tune(des, train, steps=5, **opts)
    path = str(tmp_path / "ckpt")
    tune(des, train, steps=3, checkpoint=path, **opts)
    res = tune(des, train, steps=5, checkpoint=path, resume=True, **opts)
    for k in ref.params:
        np.testing.assert_array_equal(np.asarray(res.params[k]), np.asarray(ref.params[k]))
    assert res.history["step"] == [1, 2, 3, 4, 5]
    assert res.history["train_loss"] == ref.history["train_loss"]


def test_common_lmi_margin_for_non_disk_regions():
    """The traced margin (Kronecker form with the region's L_R, M_R) equals the float64 one from
    `AbstractRegion.lmi_matrix` and the Lyapunov matrix, at the design and at perturbed gains."""
    region = fojax.HalfPlane(1.0) & fojax.Sector(0.8)
    des = design_ts_observer(robot_arm_ts().system, L_ARM, kind="generalized", R=R4, region=region)
    fx, params = initial_ts_parameters(des)
    X = des.X
    rng = np.random.default_rng(0)
    signs = set()
    for scale in (0.0, 0.05, 1.0):
        p = {k: v + scale * rng.standard_normal(v.shape) for k, v in params.items()}
        _, As = _rule_matrices(des, p)
        ref = min(
            min(-np.linalg.eigvalsh(region.lmi_matrix(X, X @ A)).max(), -np.linalg.eigvalsh(A.T @ X + X @ A).max())
            for A in As
        ) / np.linalg.norm(X, 2)
        margin, logdet = fx.margin(p), -fx.barrier(p)
        np.testing.assert_allclose(float(margin), ref, rtol=1e-9, atol=1e-12)
        assert np.isfinite(float(logdet)) == (ref > 0)
        signs.add(bool(ref > 0))
    assert signs == {True, False}  # admissible and inadmissible points were both compared
    assert float(fx.margin(params)) > 0  # the design itself is admissible


def test_extra_loss_is_part_of_the_ts_objective(setup, run):
    des, train, _ = setup
    opts = dict(steps=2, optimizer=OPT, barrier=BARRIER, stepper=STEPPER)
    before = TRACE_COUNTS["tune_step"]
    plain = tune(des, train, extra_loss=NO_PENALTY, **opts)  # both: the step compiled by `run`
    pen = tune(des, train, extra_loss=WeightedPenalty(G_WEIGHT, _g_size), **opts)
    assert TRACE_COUNTS["tune_step"] == before
    # step 0 is evaluated at the LMI design: the objectives differ by the term (NumPy, design's G)
    np.testing.assert_allclose(pen.history["train_loss"][0] - plain.history["train_loss"][0],
                               G_WEIGHT * np.sum(np.asarray(des.params["G"]) ** 2), rtol=1e-10)
    # its gradient acts: the penalized run ends with the smaller G
    normG = [float(np.linalg.norm(np.asarray(r.params["G"]))) for r in (plain, pen)]
    assert normG[1] < normG[0]
    assert pen.design.solver["tuning"]["extra_loss"] == "WeightedPenalty"
