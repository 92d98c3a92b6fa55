r"""Built-in robustness terms of `fojax.tuning.tune` (`fojax.tuning.H2Term`, `fojax.tuning.HinfTerm`).

Oracles, independent of the code under test:

- **the frequency-domain H2 integral** on the joint descriptor system (plant + observer written
  from the observer's own matrices, `helpers.joint_error_system`; `helpers.h2_by_integral`,
  `scipy.integrate.quad`), which also re-derives the error system (the plant modes cancel only
  if it is right), and the design's own norm from SciPy's ``solve_continuous_lyapunov``; the
  feedthrough part against the joint system's own $D_j = QW_yD_v$;
- **σ_max by NumPy** (``numpy.linalg.norm(·, 2)`` of the complex joint transfer matrix) on the
  term's own frequency grid, and SLICOT's AB13DD norm of the design (γ's independent check):
  the surrogate must lie in $[\max_k\sigma_k,\ \max_k\sigma_k + \tau\log K]$ and
  $\max_k\sigma_k \le \|T\|_\infty$;
- **central finite differences** (step 1e-6) for the gradients, under `jax.jit`, `jax.vmap`;
- **a dense frequency sweep** of the tuned observer's joint system: below the γ reported for
  the tuned design (`fojax.design._certify.riccati_gamma`), and equal to its AB13DD norm;
- **a closed form** for the tuning test: for $\dot x = ax + w$, $y = x + \nu$, $z = x$ every
  LTI estimator has $\|T\|_\infty \ge 1/\sqrt{1 + a^2}$ (`tests/test_hinf.py`'s module docstring),
  so every tuned design's AB13DD norm must respect it.
"""

from __future__ import annotations

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import channels_3_3_7, h2_by_integral, joint_error_system, scalar_plant

import fojax
from fojax import studies as S, tuning
from fojax.design import design_functional_observer, Disk
from fojax.errors import InputError

# private: TRACE_COUNTS: the no-retrace check
from fojax.tuning import _tune


@pytest.fixture(scope="module")
def ex337():
    """§3.3.7 with the δ channel (δ̄ = 0.3, on differential rows only: no feedthrough) for the H2
    design, plus output noise σ = 0.05 for the H∞ design (it feeds through at the default q0)."""
    ex, Bw, Dv = channels_3_3_7(0.3, 0.05)
    region = Disk(-3.0, 2.0)
    d2 = design_functional_observer(ex.system, ex.L, region=region, objective="h2", Bw=Bw)
    dh = design_functional_observer(ex.system, ex.L, region=region, objective="hinf", Bw=Bw, Dv=Dv)
    return ex, Bw, Dv, d2, dh


def _params(d):
    return {k: jnp.asarray(v) for k, v in d.params.items()}


def test_h2_term_is_the_h2_norm_squared_and_charges_the_feedthrough(ex337):
    ex, Bw, Dv, d2, dh = ex337
    term = tuning.H2Term(1.0).bind(d2)  # channels from the H2 certificate
    np.testing.assert_array_equal(np.asarray(term.Bw), Bw)
    value = float(term(d2.structure, _params(d2)))
    oracle = h2_by_integral(ex.system, ex.L, d2.observer, Bw, np.zeros((3, 0)))
    np.testing.assert_allclose(value, oracle**2, rtol=1e-8)
    np.testing.assert_allclose(np.sqrt(value), d2.h2.norm, rtol=1e-8)
    # the H∞ design passes the noise straight into ẑ − z: the term adds feedthrough_weight · ‖D‖_F²
    t0, t2 = (tuning.H2Term(1.0, feedthrough_weight=w).bind(dh) for w in (0.0, 2.0))
    _, _, _, _, Dj = joint_error_system(ex.system, ex.L, dh.observer, Bw, Dv)
    assert np.abs(Dj).max() > 1e-3
    v0, v2 = float(t0(dh.structure, _params(dh))), float(t2(dh.structure, _params(dh)))
    np.testing.assert_allclose(v0, h2_by_integral(ex.system, ex.L, dh.observer, Bw, Dv) ** 2, rtol=1e-8)
    np.testing.assert_allclose(v2 - v0, 2.0 * np.sum(Dj**2), rtol=1e-9)


def test_hinf_surrogate_brackets_the_grid_maximum_below_the_norm(ex337):
    ex, Bw, Dv, _, dh = ex337
    term = tuning.HinfTerm(1.0).bind(dh)
    Ej, Aj, Bj, Cj, Dj = joint_error_system(ex.system, ex.L, dh.observer, Bw, Dv)
    ws = np.asarray(term.frequencies)
    sig = np.array([np.linalg.norm(Cj @ np.linalg.solve(1j * w * Ej - Aj, Bj) + Dj, 2) for w in ws])
    value, tau = float(term(dh.structure, _params(dh))), float(term.tau)
    assert sig.max() <= value <= sig.max() + tau * np.log(ws.size) * (1 + 1e-12), (value, sig.max())
    assert sig.max() <= dh.hinf.norm * (1 + 1e-9)  # a grid maximum, never above ‖T‖∞ (AB13DD)
    np.testing.assert_allclose(sig.max(), dh.hinf.norm, rtol=1e-6)  # the grid holds the peak (ω = 0 here)
    np.testing.assert_allclose(tau, 0.01 * sig.max(), rtol=1e-9)


@pytest.mark.parametrize("which", ["h2", "hinf"])
def test_gradients_match_central_differences_under_jit_and_vmap(ex337, which):
    _, _, _, d2, dh = ex337
    d = d2 if which == "h2" else dh
    term = (tuning.H2Term(1.0) if which == "h2" else tuning.HinfTerm(1.0, temperature=0.05)).bind(d)
    p0 = _params(d)
    rng = np.random.default_rng(0)
    dirs = [{k: jnp.asarray(rng.standard_normal(v.shape)) for k, v in p0.items()} for _ in range(3)]

    def along(t, direction):
        return term(d.structure, {k: p0[k] + t * direction[k] for k in p0})

    grad = jax.jit(jax.grad(along))
    h = 1e-6
    fd = np.array([(float(along(h, v)) - float(along(-h, v))) / (2 * h) for v in dirs])
    g = np.array([float(grad(0.0, v)) for v in dirs])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max())
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *dirs)
    np.testing.assert_allclose(np.asarray(jax.vmap(grad, in_axes=(None, 0))(0.0, stacked)), g, rtol=1e-10)


def test_new_weights_and_channels_do_not_recompile(ex337):
    _, Bw, Dv, _, dh = ex337
    counts = collections.Counter()

    @eqx.filter_jit
    def value(term, params):
        counts["trace"] += 1
        return term(dh.structure, params)

    for w, scale in ((1.0, 1.0), (3.0, 0.5)):
        for term in (tuning.H2Term(w, Bw=scale * Bw, Dv=scale * Dv), tuning.HinfTerm(w, Bw=scale * Bw, Dv=scale * Dv)):
            value(term.bind(dh), _params(dh))
    assert counts["trace"] == 2, counts  # one per term type


def test_bad_input_is_refused(ex337):
    ex, Bw, Dv, d2, dh = ex337
    region_only = design_functional_observer(ex.system, ex.L, region=Disk(-3.0, 2.0))
    with pytest.raises(InputError, match=r"no H∞/H2 certificate.*H2Term\(Bw=..., Dv=...\)"):
        tuning.H2Term(1.0).bind(region_only)
    with pytest.raises(InputError, match="weight=...\\) must be a finite number ≥ 0"):
        tuning.HinfTerm(-1.0)
    with pytest.raises(InputError, match="Bw maps the disturbance"):
        tuning.H2Term(1.0, Bw=np.ones((5, 1))).bind(d2)
    with pytest.raises(InputError, match="robustness must be a fojax.tuning.H2Term"):
        tuning.tune(d2, None, robustness="h2")


@pytest.fixture(scope="module")
def scalar_runs():
    """ẋ = −x + w, y = x + ν, z = x; the H∞ design in Disk(−2.5, 2), tuned for 6 steps on a noise-free
    transient (x0 = 1) with `HinfTerm` of weight 0 (the plain tuning loss) and 10. The weight is a
    leaf: both runs share one compilation of the tuning step."""
    one = np.ones((1, 1))
    sys_ = scalar_plant(-1.0)
    d = design_functional_observer(sys_, one, kind="generalized", region=Disk(-2.5, 2.0), objective="hinf",
                                   Bw=one, Dv=one)
    ts = jnp.linspace(0.0, 2.0, 21)
    study = S.Study(sys_, jnp.ones(1), ts, one, fojax.Constant(jnp.zeros(1)))
    opt = tuning.shared_optimizer("adam", learning_rate=0.1)
    before = _tune.TRACE_COUNTS["tune_step"]
    plain = tuning.tune(d, study, steps=6, optimizer=opt, robustness=tuning.HinfTerm(0.0))
    termed = tuning.tune(d, study, steps=6, optimizer=opt, robustness=tuning.HinfTerm(10.0))
    return d, plain, termed, _tune.TRACE_COUNTS["tune_step"] - before


def test_tuning_with_the_term_keeps_the_hinf_norm_lower(scalar_runs):
    d, plain, termed, traces = scalar_runs
    assert traces == 1  # a new weight never recompiles the tuning step
    floor = 1.0 / np.sqrt(2.0)  # closed form, a = −1
    for r in (plain, termed):
        assert r.robustness["initial"]["hinf_norm"] == pytest.approx(d.hinf.norm, rel=1e-9)
        assert r.robustness["final"]["hinf_norm"] >= floor * (1 - 1e-8)
        # the tuned design's γ (bounded-real Riccati + the designs' float64 BRL check) bounds the gain
        # of the joint system written from the tuned observer's own matrices, on a dense grid
        final = r.robustness["final"]
        one = np.ones((1, 1))
        Ej, Aj, Bj, Cj, Dj = joint_error_system(scalar_plant(-1.0), one, r.design.observer, one, one)
        sweep = max(np.linalg.norm(Cj @ np.linalg.solve(1j * w * Ej - Aj, Bj) + Dj, 2)
                    for w in np.r_[0.0, np.logspace(-3, 3, 600)])
        assert final["gamma"] is not None, final
        assert final["hinf_norm"] * (1 - 1e-9) <= final["gamma"] <= final["hinf_norm"] * 1.03
        assert sweep <= final["gamma"] and sweep == pytest.approx(final["hinf_norm"], rel=1e-6)
        assert r.design.solver["tuning"]["robustness"] == r.robustness
        assert sum(r.history["accepted"]) > 0
    # the untermed run trades the noise gain for the transient; the term holds it near the optimum
    assert plain.robustness["final"]["hinf_norm"] > d.hinf.norm * 1.01, plain.robustness
    assert termed.robustness["final"]["hinf_norm"] < plain.robustness["final"]["hinf_norm"], termed.robustness
    assert termed.robustness["terms"] == ["HinfTerm(weight=10)"]


SCALAR_TOML = """
name = "scalar_robust"
[model]
E = [[1.0]]
A = [[-1.0]]
B = [[1.0]]
C = [[1.0]]
L = [[1.0]]
[[observer]]
name = "H2"
region = { disk = { center = -2.5, radius = 2.0 } }
objective = "h2"
Bw = [[1.0]]
Dv = [[1.0]]
[tuning]
steps = 3
robustness = { hinf = 2, h2 = 0.5 }
"""


def test_config_key_and_the_study_command_helpers(scalar_runs):
    import tomllib

    # private: the CLI's robustness lines are tested
    from fojax.cli._study import _robustness_line, _robustness_terms
    from fojax.config import parse_config
    from fojax.errors import ConfigError

    cfg = parse_config(tomllib.loads(SCALAR_TOML))
    assert cfg.tuning.robustness == (("h2", 0.5), ("hinf", 2.0))
    d, _, termed, _ = scalar_runs  # an objective="hinf" design: the terms take its channels
    terms = _robustness_terms(tuning, cfg.tuning, d)
    assert [t.describe() for t in terms] == ["H2Term(weight=0.5)", "HinfTerm(weight=2)"]
    region_only = design_functional_observer(scalar_plant(-1.0), np.ones((1, 1)), region=Disk(-2.5, 2.0))
    assert _robustness_terms(tuning, cfg.tuning, region_only) is None  # no channels: tuned without
    line = _robustness_line(termed.robustness)
    assert line.startswith("‖T‖∞ (AB13DD) ") and "HinfTerm(weight=10)" in line and "certified γ 0." in line
    for bad, match in (("hinf = 2, h2 = 0.5", r"tuning\.robustness\.hinff.*Did you mean 'hinf'"),
                       ("hinf = -1", r"tuning\.robustness\.hinf")):
        text = SCALAR_TOML.replace("hinf = 2, h2 = 0.5", bad.replace("hinf =", "hinff =") if "2" in bad else bad)
        with pytest.raises(ConfigError, match=match):
            parse_config(tomllib.loads(text))


def test_h2_term_of_a_balanced_design_takes_the_channel_in_the_models_units():
    """Regression (issue 14): a ``balance=True`` design holds the unit-free structure, and a
    user's ``Bw`` (rows = the model's equations) was used there as if it were unit-free: the
    term was the H2 norm of another disturbance. Oracle: the frequency-domain H2 integral of
    the joint plant + observer system written in the model's units (`helpers.h2_by_integral`).
    Plant: the LC filter of ``benchmarks/lc_filter.py`` (its unit-free row factors are not 1)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import lc_filter

    m = lc_filter.lc_filter()
    plant = fojax.DescriptorSystem(m["E"], m["A"], m["B"], m["C"])
    d = design_functional_observer(plant, m["L"], q0=3, region=Disk(-3.0, 2.0), balance=True)
    assert not np.allclose(d.solver["balance"]["row_factors"], 1.0)
    Bw = np.zeros((6, 1))
    Bw[2, 0] = Bw[3, 0] = 1.0  # a disturbance voltage in the output inductor's loop, a current into node 2
    Dv = np.zeros((2, 0))
    term = tuning.H2Term(Bw=Bw, Dv=Dv).bind(d)
    value = float(term(d.structure, {k: jnp.asarray(v) for k, v in d.params.items()}))
    np.testing.assert_allclose(value, h2_by_integral(plant, m["L"], d.observer, Bw, Dv) ** 2, rtol=1e-8)


def test_h2_term_of_a_balanced_h2_design_takes_the_certificates_channel_as_it_is():
    """A ``balance=True`` H2 design (``balance`` applies to H∞/H2 designs since issue 14's
    units work) holds its certificate's channel in the unit-free frame (``D_l B_w``), the frame
    of its structure: the term built from the certificate must not map it again. Oracle: the
    frequency-domain H2 integral of the joint plant + observer system in the model's units, and
    the design's own norm (SciPy's Lyapunov solver)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import lc_filter

    m = lc_filter.lc_filter()
    plant = fojax.DescriptorSystem(m["E"], m["A"], m["B"], m["C"])
    Bw = np.zeros((6, 1))
    Bw[2, 0] = Bw[3, 0] = 1.0
    d = design_functional_observer(plant, m["L"], q0=3, region=Disk(-3.0, 2.0), objective="h2", Bw=Bw,
                                   balance=True)
    assert "balance" in d.solver and d.verify().passed
    term = tuning.H2Term().bind(d)  # channels from the certificate
    value = float(term(d.structure, {k: jnp.asarray(v) for k, v in d.params.items()}))
    np.testing.assert_allclose(value, h2_by_integral(plant, m["L"], d.observer, Bw, np.zeros((2, 0))) ** 2,
                               rtol=1e-8)
    np.testing.assert_allclose(value, d.h2.norm ** 2, rtol=1e-8)
