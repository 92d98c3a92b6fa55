"""The scripts of ``benchmarks/`` build what they claim, checked independently; no timing here.

**The reference workload** (``benchmarks/_workload.py``).
The workload is built with NumPy in benchmarks/_workload.py; these tests check its
construction against the pencil eigenvalues (SciPy's QZ), the separation structure of
the observer-based loop, the descriptor equation itself, and that the peers agree
with each other (and with fojax, when `fojax.simulate` exists) to their accuracy.

**The scaling benchmarks' generators and report writer:**

- `benchmarks/scaling.py`: the random descriptor systems are regular, index 1 (exactly
  rank E finite poles), stable with every finite pole (nominal and every sample) left of
  -0.5, the hand reduction (slow matrix, output map T, consistent x0) solves the descriptor
  equation, and the generic exact-discretisation peer (d) equals the closed form
  x(t) = T V exp(Λt) V⁻¹ z0 on the grid in both axis orders.
- `benchmarks/design_scaling.py`: the design problems have the documented sizes and are
  functionally observable (fojax and an independent NumPy rank test).
- `benchmarks/tuning_scaling.py`: the batch factorisation.
- `benchmarks/make_readme.py`: copies numbers from the JSON files, skips unknown schemas,
  and writes the whole of benchmarks/README.md (its text, then the tables).
- `benchmarks/lc_filter.py` (the circuit of `tuning_circuit.py`): index 1 with 4 finite
  poles equal (by matching) to those of the hand-reduced ODE (the divider gives
  $v_3 = v_2/2$, $i_L = v_2/(2R_a)$), and its badly scaled twin has the same finite poles,
  outputs and functional for the same physical state.
- `benchmarks/tuning_circuit.py --model flexible_drive`: the drive's badly scaled twin has the
  drive's finite poles (oracle: the plain model's QZ), the same y and z for the same physical
  state, and the studies draw the same physical initial states.
- `benchmarks/hinf_vs_region.py`, case ``lc`` (issue 18): the plant is lc_filter's, the
  initial state satisfies the algebraic rows (oracle: the same hand reduction), the H∞
  channel reproduces ΔA for |δ| ≤ 1, and the study draws δ in [-1, 1] and noise on both outputs.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import design_scaling  # noqa: E402
import lc_filter  # noqa: E402
import make_readme  # noqa: E402
import scaling  # noqa: E402
import tuning_scaling  # noqa: E402
from helpers import assert_eigenvalues_match  # noqa: E402

import fojax  # noqa: E402


def _finite_poles(A, E):
    """Finite generalized eigenvalues of (A, E) from QZ's homogeneous pairs (alpha, beta)."""
    ab = scipy.linalg.eigvals(A, E, homogeneous_eigvals=True)
    alpha, beta = ab
    scale = max(1.0, np.linalg.norm(A, 2), np.linalg.norm(E, 2))
    fin = np.abs(beta) > 1e-9 * scale
    return alpha[fin] / beta[fin]


@pytest.mark.parametrize("n", [4, 8, 16])
def test_random_loop_is_regular_index1_and_stable(n):
    loop = scaling.random_stable_index1(n, seed=100 + n)
    E, A = loop.E, loop.A
    r = np.linalg.matrix_rank(E)
    assert r == loop.r == n - max(1, n // 4)
    # regular: det(sE - A) != 0 at a random s
    s = 0.37 + 1.1j
    assert abs(np.linalg.det(s * E - A)) > 1e-8
    samples = scaling.make_samples(loop, 6, seed=3)
    for Ak in [A, A + scaling.DELTA * loop.dA, A - scaling.DELTA * loop.dA, *samples.A]:
        lam = _finite_poles(Ak, E)
        # impulse free (index 1 since E is singular): exactly rank E finite poles
        assert lam.size == r
        assert lam.real.max() < -0.5
    # the construction's bound: log-norm of every slow matrix <= -1 (hence poles <= -1)
    for Ask in samples.As:
        assert np.linalg.eigvalsh(0.5 * (Ask + Ask.T)).max() <= scaling.ABSCISSA_BOUND + 1e-12


@pytest.mark.parametrize("n", [4, 9])
def test_hand_reduction_solves_the_descriptor_equation(n):
    loop = scaling.random_stable_index1(n, seed=7 * n)
    samples = scaling.make_samples(loop, 3, seed=1)
    T = loop.T
    for Ak, Ask, z0, x0 in zip(samples.A, samples.As, samples.z0, samples.x0):
        # x = T z with z' = As z solves E x' = A_k x:  E T As = A_k T
        np.testing.assert_allclose(loop.E @ T @ Ask, Ak @ T, atol=1e-11 * np.abs(Ak).max())
        np.testing.assert_allclose(x0, T @ z0, rtol=1e-14)
        # x0 is consistent: A_k x0 lies in the range of E (no component along E's left null space)
        U, sv, _ = np.linalg.svd(loop.E)
        null_left = U[:, sv < 1e-10]
        assert np.abs(null_left.T @ Ak @ x0).max() <= 1e-11 * np.abs(Ak @ x0).max()
        # its poles are the pencil's finite poles (a multiset: matched, not sorted)
        assert_eigenvalues_match(_finite_poles(Ak, loop.E), np.linalg.eigvals(Ask), rtol=1e-8, atol=1e-9)


def test_samples_do_not_depend_on_the_batch_size():
    loop = scaling.random_stable_index1(6, seed=2)
    a, b = scaling.make_samples(loop, 3, seed=5), scaling.make_samples(loop, 10, seed=5)
    # the random draws and the elementwise A_k are bit-identical ...
    np.testing.assert_array_equal(a.delta, b.delta[:3])
    np.testing.assert_array_equal(a.z0, b.z0[:3])
    np.testing.assert_array_equal(a.A, b.A[:3])
    # ... x0 = T z0 comes from one matrix product over the batch, whose blocking (hence the
    # rounding) depends on B and on the BLAS kernel (Nehalem differs in the last bit, issue
    # 17): equal within the dot-product rounding bound r·eps·|T||z0| per entry
    bound = loop.r * np.finfo(float).eps * (np.abs(a.z0) @ np.abs(loop.T).T)
    assert np.all(np.abs(a.x0 - b.x0[:3]) <= bound)


def test_generic_expm_peer_equals_closed_form():
    loop = scaling.random_stable_index1(4, seed=11)
    samples = scaling.make_samples(loop, 2, seed=4)
    ts = scaling.grid()
    dt = ts[1] - ts[0]
    want = []
    for Ask, z0 in zip(samples.As, samples.z0):
        # x(t) = T V diag(exp(λ t)) V⁻¹ z0 on the whole grid at once (As is diagonalisable)
        lam, V = np.linalg.eig(Ask)
        assert np.linalg.cond(V) < 1e6
        c = np.linalg.solve(V, z0)
        x = (loop.T @ V @ (np.exp(np.outer(lam, ts)) * c[:, None])).real  # (n, T)
        f = np.abs(x).sum(0)
        want.append(dt * (f.sum() - 0.5 * (f[0] + f[-1])))
    for fn in scaling.PEER_VARIANTS.values():
        got = fn(samples.As, loop.T, samples.z0)
        np.testing.assert_allclose(got, want, rtol=1e-10)


@pytest.mark.parametrize("n", [4, 6, 12])
def test_design_problems_are_functionally_observable(n):
    pb = design_scaling.random_design_problem(n, seed=9)
    assert pb.B.shape == (n, 2)
    assert pb.C.shape == (max(1, n // 4), n)
    assert pb.L.shape == (max(1, n // 2), n) and pb.q0 == max(1, n // 2)
    sysm = fojax.DescriptorSystem(pb.E, pb.A, pb.B, pb.C)
    assert fojax.analysis.is_functionally_observable(sysm, pb.L)
    # independently: rank [L; E; E⊥A; C] = rank [E; E⊥A; C] (Darouach's condition)
    U, sv, _ = np.linalg.svd(pb.E)
    Eperp = U[:, sv < 1e-10].T
    base = np.vstack([pb.E, Eperp @ pb.A, pb.C])
    rk = np.linalg.matrix_rank
    assert rk(np.vstack([pb.L, base]), tol=1e-9) == rk(base, tol=1e-9) == n
    again = design_scaling.random_design_problem(n, seed=9)
    np.testing.assert_array_equal(again.L, pb.L)


@pytest.mark.parametrize("B", [1, 8, 12, 32, 2048, 97])
def test_tuning_batch_factorisation(B):
    nu, nf = tuning_scaling.factor(B)
    assert nu * nf == B and nf <= nu
    assert all(B % d for d in range(nf + 1, int(np.sqrt(B)) + 1))


# ------------------------------------------------------------------ make_readme
MACHINE = {"date": "2031-01-02T03:04:05+00:00", "cpu": "Test CPU", "cores_available": 2, "git_commit": "abc1234",
           "versions": {"jax": "9.9.9", "fojax": "0.0.1"}, "load_average_at_start": [0.5, 0.5, 0.5]}


def _write(folder, name, payload):
    (folder / f"{name}_latest.json").write_text(json.dumps(payload))


def test_make_readme_copies_numbers_and_skips_unknown_schemas(tmp_path):
    rows = [
        {"method": "expm", "label": "(d)", "B": 10, "median_s": 0.25, "first_s": 0.3, "extrapolated": False,
         "fojax_speedup": 0.625},
        {"method": "solve_ivp", "label": "(a)", "B": 10, "median_s": 3.5, "first_s": 3.5, "extrapolated": True,
         "fojax_speedup": 8.75},
        {"method": "fojax", "label": "fojax", "B": 10, "median_s": 0.4, "first_s": 6.125, "compile_s": 5.725,
         "extrapolated": False},
    ]
    _write(tmp_path, "reference_workload", {"status": "complete", "machine": MACHINE, "rows": rows,
                                            "agreement_check": {"B": 10, "max_rel_diff_vs_expm": {"fojax": 3e-14}}})
    _write(tmp_path, "time_varying", {"status": "complete", "machine": MACHINE, "something_else": [1, 2]})
    text = make_readme.render(tmp_path)
    assert "2031-01-02T03:04:05+00:00" in text and "Test CPU" in text and "jax 9.9.9" in text
    assert "| 10 | 0.4 | 25 | 5.72 | 8.75 *extrap.* | 0.625 |" in text
    assert "3.0e-14" in text
    assert "fojax is slower than (d) expm + recurrence at B = 10 (0.62×)" in text
    assert "6.12 s" in text  # first call at the smallest B, compilation included
    assert "no table renderer for this file" in text and "something_else" in text
    assert "`scaling`" in text and "`design_scaling`" in text  # listed as not measured


def test_benchmarks_readme_is_the_generated_page():
    # benchmarks/README.md is written by make_readme.py: its text, then the tables between the markers
    text = (ROOT / "benchmarks" / "README.md").read_text()
    assert text.startswith(make_readme.INTRO) and make_readme.NARRATIVE in text
    i, j = text.find("\n" + make_readme.START + "\n"), text.find("\n" + make_readme.END + "\n")
    assert 0 <= i < j and "## Results" in text[:i]
    # the top-level README keeps one sentence and a link, no measurement section
    readme = (ROOT / "README.md").read_text()
    assert "benchmarks/README.md" in readme and make_readme.START not in readme


def test_readmes_cite_only_shipped_result_files():
    # issue 17: the README cited benchmarks/results/*.json files that were not in the
    # repository. Every results/<name>_latest.json a README names must exist.
    import re

    for readme in (ROOT / "README.md", ROOT / "benchmarks" / "README.md"):
        for name in re.findall(r"results/(\w+_latest\.json)", readme.read_text()):
            assert (ROOT / "benchmarks" / "results" / name).exists(), (readme, name)


def test_make_readme_renders_what_is_shipped_and_any_new_benchmark(tmp_path):
    empty = tmp_path / "none"
    empty.mkdir()
    assert "No benchmark result is shipped" in make_readme.render(empty)
    # a benchmark without a renderer of its own (e.g. a new study_latest.json) gets a table of its rows
    _write(tmp_path, "study", {"status": "complete", "machine": MACHINE,
                               "rows": [{"B": 64, "command": "fojax study", "wall_s": 12.3456},
                                        {"B": 256, "command": "fojax study", "wall_s": 40.5}]})
    _write(tmp_path, "tuning_scaling", {"status": "complete", "machine": MACHINE, "settings": {"extra_steps": 5},
                                        "rows": [{"B": 8, "t_cold_s": 29.5, "per_step_s": 0.138,
                                                  "compile_s": 29.4, "retraced_on_warm_calls": False,
                                                  "status": "ok"}]})
    text = make_readme.render(tmp_path)
    assert text.index("One gradient-tuning step") < text.index("### study")  # registered first
    assert "| B | command | wall_s |" in text and "| 64 | fojax study | 12.35 |" in text
    assert "| 8 | 29.5 | 0.138 | 29.4 | no | ok |" in text
    assert "`reference_workload`" in text.split("No shipped result yet")[1]
    assert "`tuning_scaling`" not in text.split("No shipped result yet")[1]
    page = make_readme.build(tmp_path)  # the whole page: the text, then these tables
    assert page.startswith(make_readme.INTRO) and page.count(make_readme.START) == 1
    assert text in page


def test_latest_results_are_tracked_and_the_rest_ignored():
    import shutil
    import subprocess

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")

    def ignored(path):
        return subprocess.run(["git", "check-ignore", "--no-index", "-q", path], cwd=ROOT).returncode == 0

    assert not ignored("benchmarks/results/study_latest.json")
    assert ignored("benchmarks/results/study_2031-01-02.json")
    assert ignored("benchmarks/results/study_latest.md")


def test_make_readme_renders_the_time_varying_study(tmp_path):
    row = {"B": 1000, "fojax_samples_per_s": 254.98, "peer_samples_per_s": 4.1083, "speedup_vs_solve_ivp": 62.064,
           "fojax_error_vs_reference_max_rel": 5.115e-10, "peer_error_vs_reference_max_rel": 2.455e-6,
           "fojax_first_call_s": 60.84, "load_average_start": "[17.95, 17.87, 15.15]"}
    _write(tmp_path, "study_time_varying", {"status": "complete", "machine": MACHINE, "rows": [row]})
    text = make_readme.render(tmp_path)
    assert "| 1000 | 255 | 4.11 | 62.1× | 5.1e-10 | 2.5e-06 | 60.8 | 17.9 |" in text
    assert "took 60.8 s, the time the solve_ivp loop needs for 250 samples" in text


def test_lc_filter_is_index1_and_its_twin_is_the_same_circuit():
    p = lc_filter.PARAMS
    # hand reduction: rows 5-6 give v3 = v2/2 and i_L = v2/(2 Ra); states (i1, v1, i2, v2)
    Ared = np.array([[-p["R1"] / p["L1"], -1 / p["L1"], 0, 0],
                     [1 / p["C1"], 0, -1 / p["C1"], 0],
                     [0, 1 / p["L2"], -p["R2"] / p["L2"], -1 / p["L2"]],
                     [0, 0, 1 / p["C2"], -1 / (2 * p["Ra"] * p["C2"])]])
    want = np.linalg.eigvals(Ared)
    plain, twin = lc_filter.lc_filter(), lc_filter.lc_filter(scaled=True)
    # unbalanced QZ is backward stable relative to the pencil's norm: on the twin, whose rows and
    # states span 1e-3 .. 1e3, it keeps about 6 fewer digits (measured 1.5e-9 relative under
    # OPENBLAS_CORETYPE=Sandybridge, 1e-10 under the default kernel), hence its own tolerance
    for m, rtol in ((plain, 1e-9), (twin, 1e-6)):
        sys_ = fojax.DescriptorSystem(m["E"], m["A"], m["B"], m["C"])
        assert fojax.analysis.nilpotency_index(sys_) == 1
        assert_eigenvalues_match(_finite_poles(m["A"], m["E"]), want, rtol=rtol)
    S = twin["Dc"]
    assert np.ptp(np.log10(np.diag(S))) == 6 and np.ptp(np.log10(lc_filter.TWIN_ROWS)) == 6  # 1e-3 .. 1e3
    x = np.arange(1.0, 7.0)
    np.testing.assert_allclose(twin["C"] @ np.linalg.solve(S, x), plain["C"] @ x, rtol=1e-14)
    np.testing.assert_allclose(twin["L"] @ np.linalg.solve(S, x), plain["L"] @ x, rtol=1e-14)


def test_hinf_vs_region_lc_case_is_the_lc_filter_with_consistent_x0():
    import hinf_vs_region

    p = lc_filter.PARAMS
    _, sys_, plant, x0 = hinf_vs_region.lc_model()
    ref = lc_filter.lc_filter()
    for k in ("E", "A", "C"):
        np.testing.assert_array_equal(np.asarray(getattr(sys_, k)), ref[k])
    np.testing.assert_array_equal(np.asarray(plant.dA)[0], ref["dA"])
    # hand reduction: v3 = v2/2, i_L = (v2 - v3)/Ra; x0 keeps 0.5 on (i1, v1, i2, v2)
    np.testing.assert_allclose(np.asarray(x0), [0.5, 0.5, 0.5, 0.5, 0.25, 0.25 / p["Ra"]], rtol=1e-12)
    np.testing.assert_allclose((ref["A"] @ np.asarray(x0))[4:], 0.0, atol=1e-14)  # the algebraic rows
    Bw, Cd = fojax.design.hinf_uncertainty_channel(ref["dA"], hinf_vs_region.LC_DELTA_MAX)
    np.testing.assert_allclose(Bw @ Cd, ref["dA"], atol=1e-14)  # w = delta Cd x with |delta| <= 1
    st = hinf_vs_region.study(None, "lc", 16, 1, 0.5, 0.05, seed=3)
    delta, noise = (f.values for f in st.uncertainty)
    delta, noise = np.asarray(delta.value), np.asarray(noise.values)
    assert delta.shape == (16, 1) and np.all(np.abs(delta) <= 1.0) and np.ptp(delta) > 1.0
    assert noise.shape[0] == 16 and noise.shape[-1] == 2  # (i1, v2)
    assert st.signal_names == ("i2",)
    np.testing.assert_array_equal(np.asarray(st.x0), np.asarray(x0))
    assert not np.any(np.asarray(hinf_vs_region.study(None, "lc_noise", 2, 1, 0.5, 0.05, seed=3).x0))  # at rest


def _twin_is_the_same_system(tc, model, rows, states, n):
    """The rescaled twin of `tuning_circuit.py --model <model>`: scale factors spanning
    1e-3…1e3, the plain model's finite poles (oracle: its QZ), the same y and z for the same
    physical state, and studies drawing the same physical initial states (x0' = Dc⁻¹ x0).
    Returns the plain study's initial states and the plain study."""
    plain, twin = getattr(tc, model)(), getattr(tc, model)(scaled=True)
    assert np.ptp(np.log10(rows)) == 6 and np.ptp(np.log10(states)) == 6
    assert_eigenvalues_match(_finite_poles(twin["A"], twin["E"]), _finite_poles(plain["A"], plain["E"]), rtol=1e-6)
    S = twin["Dc"]
    x = np.arange(1.0, n + 1.0)
    for k in ("C", "L"):
        np.testing.assert_allclose(twin[k] @ np.linalg.solve(S, x), plain[k] @ x, rtol=1e-14)
    _, _, st_plain = tc.build(False, 2, 3, seed=0, model=model)
    _, _, st_twin = tc.build(True, 2, 3, seed=0, model=model)
    x0p, x0t = (np.asarray(st.scenarios[0].values) for st in (st_plain, st_twin))
    assert x0p.shape == (3, n)
    np.testing.assert_allclose(x0t * np.diag(S), x0p, rtol=1e-12)
    return x0p, st_plain


def test_tuning_benchmark_flexible_drive_twin_is_the_same_drive():
    """`tuning_circuit.py --model flexible_drive`: the twin (rows and states rescaled by
    1e-3 .. 1e3) has the drive's finite poles (oracle: the plain model's QZ), the same y and z
    for the same physical state, and the studies draw the same physical initial states
    (x0' = Dc^-1 x0) on the five differential states only."""
    import tuning_circuit as tc

    x0p, st_plain = _twin_is_the_same_system(tc, "flexible_drive", tc.DRIVE_TWIN_ROWS, tc.DRIVE_TWIN_STATES, 8)
    assert st_plain.signal_names == ("tau2",)
    assert not np.any(x0p[:, 5:]) and np.all(np.abs(x0p[:, :5]) <= 1.0) and np.ptp(x0p[:, :5]) > 0.5


def test_tuning_benchmark_two_area_power_twin_is_the_same_system():
    """`tuning_circuit.py --model two_area_power`: the twin has the plain model's finite poles
    (oracle: the plain model's QZ), the same y and z for the same physical state, the studies
    draw the same physical initial states on the seven differential states, with the model's
    own input amplitude (0.1 pu), region and order, and `delta_bound`/`x0_scale` = 0 keep the
    other draws."""
    import tuning_circuit as tc

    x0p, st_plain = _twin_is_the_same_system(tc, "two_area_power", tc.POWER_TWIN_ROWS, tc.POWER_TWIN_STATES, 10)
    assert st_plain.signal_names == ("Pm1",)
    assert not np.any(x0p[:, 7:]) and np.all(np.abs(x0p[:, [0, 2]]) <= 0.002) and np.ptp(x0p[:, 3:7]) > 0.01
    np.testing.assert_allclose(np.asarray(st_plain.u(np.asarray(np.pi / 4))), [0.1], rtol=1e-12)
    assert tc.region_of("two_area_power").describe() != tc.region_of("flexible_drive").describe()
    assert tc.MODELS["two_area_power"]["q0"] == 5 and "q0" not in tc.MODELS["flexible_drive"]
    _, _, no_delta = tc.build(False, 2, 3, seed=0, model="two_area_power", delta_bound=0.0)
    _, _, no_x0 = tc.build(False, 2, 3, seed=0, model="two_area_power", x0_scale=0.0)
    assert not np.any(np.asarray(no_delta.uncertainty[0].values.value))
    np.testing.assert_array_equal(np.asarray(no_delta.scenarios[0].values), x0p)
    assert not np.any(np.asarray(no_x0.scenarios[0].values))


# ==================================================================================================
# The reference workload of benchmarks/ (issue 7), checked independently; no timing here.
# ==================================================================================================


BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import _workload as wl  # noqa: E402
import peers  # noqa: E402
import peers_tv  # noqa: E402


def _finite(lam):
    return lam[np.isfinite(lam)]


@pytest.fixture(scope="module")
def batch3():
    return wl.make_workload(3, seed=7)


@pytest.fixture(scope="module")
def reference3(batch3):
    return peers.expm_reference(batch3)


def test_algebraic_loop_vanishes():
    # w = [-E_perp B u; y] and u = zhat = P zeta + Q w: the loop in u is void iff E_perp B = 0.
    np.testing.assert_array_equal(wl.E_PERP @ wl.B, np.zeros((1, 2)))
    np.testing.assert_array_equal(wl.W, np.vstack([np.zeros((1, 4)), wl.C]))


def test_nominal_finite_poles_match_issue_and_pencil():
    lam = wl.nominal_finite_poles()
    assert lam.shape == (7,)
    # The numbers quoted in issue 7 (two decimals).
    assert_eigenvalues_match(lam, wl.EXPECTED_POLES, atol=0.011)
    # the script's own check (reference_workload.py) is a matching too, in any order
    assert wl.poles_match(lam[::-1], wl.EXPECTED_POLES, atol=0.011)
    assert not wl.poles_match(lam + 0.02, wl.EXPECTED_POLES, atol=0.011)
    assert not wl.poles_match(lam[:-1], wl.EXPECTED_POLES[:-1] + [0.0], atol=0.011)
    # Independently: the finite generalized eigenvalues of the 8x8 pencil (E_cl, A_cl) (QZ).
    pencil = _finite(scipy.linalg.eigvals(wl.closed_loop_A(wl.A), wl.E_CL))
    assert_eigenvalues_match(lam, pencil, rtol=1e-9)


def test_separation_principle_holds_for_the_printed_gains():
    # Thesis §4.1.2: poles of the loop = poles of (E, A + BL) ∪ eig([[N, J], [S, G]]);
    # with the two-decimal printed gains only to about 1e-2.
    plant = _finite(scipy.linalg.eigvals(wl.A + wl.B @ wl.L, wl.E))
    obs = np.linalg.eigvals(np.block([[wl.N, wl.J], [wl.S, wl.G]]))
    union = _finite(np.concatenate([plant, obs]))
    assert_eigenvalues_match(wl.nominal_finite_poles(), union, atol=0.02)


def test_reduction_solves_the_descriptor_equation():
    A_cl = wl.closed_loop_A(wl.A + 0.17 * wl.DELTA_A)
    A_red, T = wl.reduce_index1(A_cl)
    # x = T x_d satisfies E_cl d/dt x = A_cl x for every x_d with d/dt x_d = A_red x_d.
    np.testing.assert_allclose(wl.E_CL @ T @ A_red, A_cl @ T, atol=1e-12)
    np.testing.assert_allclose(T[wl.DIFF], np.eye(7))


def test_samples(batch3):
    big = wl.make_workload(50, seed=7)
    # sample k does not depend on B
    np.testing.assert_array_equal(big.A_plant[:3], batch3.A_plant)
    np.testing.assert_array_equal(big.x0_cl[:3], batch3.x0_cl)
    assert np.all(np.abs(big.delta) <= wl.DELTA_MAX)
    # only entries (1,3) and (2,2) are perturbed, by delta
    D = big.A_plant - wl.A
    np.testing.assert_allclose(D[:, 0, 2], big.delta)
    np.testing.assert_allclose(D[:, 1, 1], big.delta)
    D[:, 0, 2] = D[:, 1, 1] = 0
    assert not D.any()
    # x(0) consistent with the algebraic row (x4 = x1 + 2 x2 here), observer states zero
    np.testing.assert_allclose(big.x0_cl[:, 3], big.x0_cl[:, 0] + 2 * big.x0_cl[:, 1], rtol=1e-14)
    assert not big.x0_cl[:, 4:].any()
    # every sample stable, and indeed the whole delta interval
    assert np.max(np.linalg.eigvals(big.A_red).real) < -1.0
    assert wl.max_real_pole_over_interval() < -1.0


def test_expm_peer_against_closed_form(batch3, reference3):
    # x_d(t) = expm(A_red t) x_d(0) at every grid time, without the recurrence.
    k = 1
    X = np.stack([scipy.linalg.expm(batch3.A_red[k] * t) @ batch3.xd0[k] for t in batch3.ts])
    Y = X @ batch3.C_out.T
    expected = np.array([np.trapezoid(np.abs(Y[:, :4]).sum(1), batch3.ts),
                         np.trapezoid(np.abs(Y[:, 4:]).sum(1), batch3.ts)])
    np.testing.assert_allclose(reference3[k], expected, rtol=1e-11)
    assert np.all(reference3 > 1.0)  # nontrivial metrics


@pytest.mark.parametrize("fn", [peers.expm_batch_first, peers.expm_batch_last])
def test_vectorised_expm_peers(batch3, reference3, fn):
    np.testing.assert_allclose(fn(batch3), reference3, rtol=1e-12)


@pytest.mark.parametrize("fn", [peers.rk4_batch_first, peers.rk4_batch_last])
def test_rk4_peer_agrees_with_exact(batch3, reference3, fn):
    m = fn(batch3)
    rel = np.max(np.abs(m - reference3) / reference3)
    # RK4, dt = 1e-3, fastest pole -39.8: local error ~ (39.8e-3)^5/120 per step -> ~1e-10.
    assert rel < 1e-8
    assert rel > 1e-14  # it is a different method; identical output would mean a wiring error


def test_loop_peers_agree_with_exact(batch3, reference3):
    pytest.importorskip("control")
    np.testing.assert_allclose(peers.control_loop(batch3), reference3, rtol=1e-10)
    one = wl.make_workload(1, seed=7)
    rel = np.max(np.abs(peers.solve_ivp_loop(one) - reference3[:1]) / reference3[:1])
    assert rel < 1e-4  # RK45 at rtol 1e-6


def test_fojax_matches_exact_peer(batch3, reference3):
    import fojax

    if not hasattr(fojax, "simulate"):
        pytest.skip("fojax.simulate is not available yet")
    import reference_workload

    m = reference_workload.run_fojax(batch3)
    assert m.shape == (3, 2)
    np.testing.assert_allclose(m, reference3, rtol=1e-8)


# ------------------------------------------------------------ study 2: time-varying δ(t), fault


@pytest.fixture(scope="module")
def tv3():
    return wl.make_tv_workload(3, seed=7)


@pytest.fixture(scope="module")
def tv_reference3(tv3):
    return peers_tv.tight_reference(tv3)


def test_tv_samples_and_reduction():
    tv = wl.make_tv_workload(50, seed=7)
    # sample ranges, and sample k does not depend on B
    assert np.all((tv.amplitude >= 0) & (tv.amplitude <= wl.TV_AMPLITUDE_MAX))
    assert np.all((tv.omega >= 0.5) & (tv.omega <= 5.0))
    assert np.all((tv.phase >= 0) & (tv.phase < 2 * np.pi))
    assert np.all(np.abs(tv.fault) <= wl.FAULT_MAX) and tv.fault.shape == (50, 2)
    small = wl.make_tv_workload(3, seed=7)
    np.testing.assert_array_equal(small.omega, tv.omega[:3])
    np.testing.assert_array_equal(small.fault, tv.fault[:3])
    # the initial states are study 1's (same stream)
    np.testing.assert_array_equal(tv.x0_cl, wl.make_workload(50, seed=7).x0_cl)
    # delta(t) is the documented sinusoid
    t = 1.234
    np.testing.assert_allclose(tv.delta(t), tv.amplitude * np.sin(tv.omega * t + tv.phase))
    # affine in delta: the hand reduction of A(delta) equals A_red0 + delta dA_red, and dA_red
    # is Delta A on the differential indices (entries (1,3) and (2,2) only)
    for d in (-0.3, 0.11, 0.3):
        A_red, T = wl.reduce_index1(wl.closed_loop_A(wl.A + d * wl.DELTA_A))
        np.testing.assert_allclose(A_red, tv.A_red0 + d * tv.dA_red, atol=1e-12)
        np.testing.assert_array_equal(T, tv.T)
    expected = np.zeros((7, 7))
    expected[0, 2] = expected[1, 1] = 1.0
    np.testing.assert_allclose(tv.dA_red, expected, atol=1e-14)
    # the reduced ODE solves the descriptor equation with the fault:
    # E_cl d/dt (T x_d) = A_cl(delta) T x_d + B_f f for any x_d, f
    rng = np.random.default_rng(0)
    xd, f, d = rng.normal(size=7), rng.normal(size=2), 0.23
    xdot = (tv.A_red0 + d * tv.dA_red) @ xd + tv.b_fault @ f
    A_cl = wl.closed_loop_A(wl.A + d * wl.DELTA_A)
    np.testing.assert_allclose(wl.E_CL @ tv.T @ xdot, A_cl @ tv.T @ xd + wl.B_FAULT_CL @ f, atol=1e-12)
    np.testing.assert_allclose(wl.full_output_rows() @ tv.T, tv.C_out, atol=1e-15)


def test_tv_every_delta_profile_is_stable():
    # a common quadratic Lyapunov function at both vertices of |delta| <= 0.3, decay rate 0.5
    P, worst = wl.quadratic_stability_certificate(alpha=0.5)
    assert worst < 0 and np.linalg.eigvalsh(P).min() > 0


def test_tv_peers_agree_with_tight_reference(tv3, tv_reference3):
    assert np.all(tv_reference3 > 1.0)
    # the reference itself: 10x tighter tolerances change it by < 1e-10
    one = wl.make_tv_workload(1, seed=7)
    rel = np.max(np.abs(peers_tv.tight_reference(one, rtol=1e-13, atol=1e-15) - tv_reference3[:1]))
    assert rel / np.min(tv_reference3[:1]) < 1e-10
    for fn in (peers_tv.rk4_batch_first, peers_tv.rk4_batch_last):
        rel = np.max(np.abs(fn(tv3) - tv_reference3) / tv_reference3)
        assert 1e-14 < rel < 1e-8  # RK4 dt = 1e-3: ~1e-10; identical output would be a wiring error
    rel = np.max(np.abs(peers_tv.solve_ivp_loop(one) - tv_reference3[:1]) / tv_reference3[:1])
    assert rel < 1e-4  # RK45 at rtol 1e-6


def test_fojax_tv_matches_tight_reference(tv3, tv_reference3):
    import time_varying

    m = np.asarray(time_varying.run_fojax(tv3, substeps=3))
    assert m.shape == (3, 2)
    np.testing.assert_allclose(m, tv_reference3, rtol=1e-9)
    # and the fault and the time variation matter at that level
    frozen = wl.make_tv_workload(3, seed=7)
    object.__setattr__(frozen, "amplitude", np.zeros(3))
    assert np.max(np.abs(np.asarray(time_varying.run_fojax(frozen, substeps=3)) - m) / m) > 1e-3


def test_served_as_worker_runs_the_worker_and_prints_its_result(capsys):
    # The child side of `_common.run_worker` (oracle: the marker line `run_worker` parses).
    import argparse

    import _common

    calls = []

    def worker(spec):
        calls.append(spec)
        return {"status": "complete", "n": spec["n"] + 1}

    assert not _common.served_as_worker(argparse.Namespace(worker=None), worker) and not calls
    assert _common.served_as_worker(argparse.Namespace(worker=json.dumps({"n": 41})), worker)
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith(_common.WORKER_MARK)
    assert json.loads(last[len(_common.WORKER_MARK):]) == {"status": "complete", "n": 42} and calls == [{"n": 41}]
