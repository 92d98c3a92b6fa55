"""Helpers shared by the test modules (import with ``from helpers import ...``).

Eigenvalues, poles and roots are multisets: LAPACK returns them in an order that depends
on the BLAS kernel (a complex pair whose real parts differ by one ulp sorts either way),
so tests compare them with `assert_eigenvalues_match`, an optimal one-to-one matching
(`scipy.optimize.linear_sum_assignment`), never by sorting.
"""

from __future__ import annotations

import dataclasses
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import linear_sum_assignment


#: XLA's flag for the number of CPU host devices (XLA's name, as in tests/conftest.py).
HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"


def child_xla_flags(devices: int | None = None) -> str:
    """``XLA_FLAGS`` for a child process: this process's (e.g. the suite's compile flag,
    tests/conftest.py) without its host-device count, and with `devices` host devices if given."""
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split() if HOST_DEVICES_FLAG not in f]
    return " ".join(kept + ([] if devices is None else [f"{HOST_DEVICES_FLAG}={devices}"]))


def _fmt(z: np.ndarray) -> str:
    # display only: sorted by rounded real part, then imaginary part
    z = np.asarray(z, dtype=complex)
    z = z[np.lexsort((z.imag, np.round(z.real, 8)))]
    return "[" + ", ".join(f"{v.real:.12g}{v.imag:+.12g}j" for v in z) + "]"


def match_eigenvalues(actual, desired, *, rtol=1e-7, atol=0.0):
    """Pair `actual` with `desired` one to one within ``atol + rtol·|desired|``.

    **Arguments:**

    - `actual`, `desired`: two collections of (complex) numbers, any shapes, flattened.
    - `rtol`, `atol`: the tolerance of the pair ``(a, b)`` is ``atol + rtol·|b|``, as in
      `numpy.testing.assert_allclose(actual, desired)`; either may be an array
      broadcastable to `desired` (one tolerance per desired value).

    **Returns:** ``(aligned, ok, report)``: `aligned` is `actual` reordered so that
    ``aligned[j]`` is paired with ``desired.ravel()[j]``; `ok` says whether every pair is
    within its tolerance; `report` describes the worst pairs when not.

    A matching within tolerance exists iff the bipartite graph of the pairs within
    tolerance has a perfect matching; `linear_sum_assignment` on the normalised distances
    (``|a - b| / tol``, pairs beyond tolerance charged ``size + 1``) finds one whenever
    one exists, because any such matching costs at most ``size``.
    """
    a = np.asarray(actual, dtype=complex).ravel()
    b = np.asarray(desired, dtype=complex).ravel()
    if a.size != b.size:
        return a, False, f"{a.size} actual values but {b.size} desired values"
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return a, False, "non-finite values"
    if a.size == 0:
        return a, True, ""
    tol = np.broadcast_to(np.asarray(atol, float), np.shape(desired)).ravel() + np.broadcast_to(
        np.asarray(rtol, float), np.shape(desired)
    ).ravel() * np.abs(b)
    dist = np.abs(a[:, None] - b[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(dist == 0.0, 0.0, dist / tol[None, :])
    within = ratio <= 1.0
    rows, cols = linear_sum_assignment(np.where(within, ratio, a.size + 1.0))
    aligned = np.empty_like(a)
    aligned[cols] = a[rows]
    ok = bool(np.all(within[rows, cols]))
    if ok:
        return aligned, True, ""
    # For the message: the matching that minimises the total distance, worst pairs first.
    rows, cols = linear_sum_assignment(dist)
    worst = np.argsort(-ratio[rows, cols])
    lines = [
        f"  actual {a[rows[k]]:.12g} ~ desired {b[cols[k]]:.12g}: |diff| {dist[rows[k], cols[k]]:.3e}"
        f" > tol {tol[cols[k]]:.3e}"
        for k in worst
        if not within[rows[k], cols[k]]
    ]
    return aligned, False, "no one-to-one matching within tolerance; closest pairing:\n" + "\n".join(lines)


def spectral_distance(a, b) -> float:
    """The smallest ``d`` such that `a` and `b` pair one to one with every ``|a_i - b_j| <= d``
    (the bottleneck matching distance of two multisets of equal size; ``inf`` otherwise)."""
    a = np.asarray(a, dtype=complex).ravel()
    b = np.asarray(b, dtype=complex).ravel()
    if a.size != b.size or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("inf")
    if a.size == 0:
        return 0.0
    dist = np.abs(a[:, None] - b[None, :])
    cand = np.unique(dist)
    lo, hi = 0, cand.size - 1  # the answer is one of the pair distances: bisect on them
    while lo < hi:
        mid = (lo + hi) // 2
        r, c = linear_sum_assignment(dist > cand[mid])
        if np.any(dist[r, c] > cand[mid]):
            lo = mid + 1
        else:
            hi = mid
    return float(cand[lo])


def assert_eigenvalues_match(actual, desired, *, rtol=1e-7, atol=0.0, err_msg: str = ""):
    """Assert that two eigenvalue multisets agree up to a one-to-one matching.

    Tolerances as in `match_eigenvalues` (``|a - b| <= atol + rtol·|b|`` for every pair).
    The failure message shows both sets (sorted for display only) and the pairs that are
    too far apart. Returns `actual` reordered to the order of `desired`.
    """
    aligned, ok, report = match_eigenvalues(actual, desired, rtol=rtol, atol=atol)
    if not ok:
        raise AssertionError(
            f"eigenvalue sets differ (rtol={np.max(rtol):g}, atol={np.max(atol):g}): {report}\n"
            f"  actual : {_fmt(np.ravel(actual))}\n  desired: {_fmt(np.ravel(desired))}"
            + (f"\n{err_msg}" if err_msg else "")
        )
    return aligned


def count_equations(fn, *args) -> int:
    """Number of primitive equations in the jaxpr of ``fn(*args)``, counting the bodies of
    ``jit``/``scan``/``while``/``cond`` once each (a proxy for the size of the compiled
    graph, independent of timing: a Python loop unrolled over a size shows up as a count
    that grows with that size)."""
    import jax

    def count(jaxpr) -> int:
        total = 0
        for eqn in jaxpr.eqns:
            total += 1
            for p in eqn.params.values():
                for sub in p if isinstance(p, tuple | list) else (p,):
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        total += count(inner)
        return total

    return count(jax.make_jaxpr(fn)(*args).jaxpr)


def design_leaves(obj, prefix=""):
    """Every array and number of a design object keyed by its path (`solver` dicts left out)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            if f.name != "solver":
                yield from design_leaves(getattr(obj, f.name), f"{prefix}.{f.name}")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from design_leaves(v, f"{prefix}[{k}]")
    elif isinstance(obj, tuple | list):
        for i, v in enumerate(obj):
            yield from design_leaves(v, f"{prefix}[{i}]")
    else:
        yield prefix, obj


def assert_designs_identical(a, b) -> int:
    """Every array of two design objects bit-identical (same type, dtype, shape), every other
    number and string equal; returns the number of arrays compared."""
    import jax

    la, lb = dict(design_leaves(a)), dict(design_leaves(b))
    assert la.keys() == lb.keys()
    n = 0
    for k, x in la.items():
        y = lb[k]
        if isinstance(x, np.ndarray | jax.Array | np.generic):
            assert type(x) is type(y) or (isinstance(x, jax.Array) and isinstance(y, jax.Array)), k
            x, y = np.asarray(x), np.asarray(y)
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), k
            n += 1
        else:
            assert type(x) is type(y) and (x == y or (x != x and y != y)), (k, x, y)
    return n


def joint_error_system(sys_, L, obs, Bw, Dv):
    r"""``(Ej, Aj, Bj, Cj, Dj)``: plant and functional observer as one descriptor system with
    states $[x; \zeta; v]$, input $d = [w; \nu]$ ($E\dot x = Ax + B_w w$, $y = Cx + D_v\nu$,
    $u = 0$) and output $\hat z - z$, written from the observer's own matrices (not from
    fojax's error coordinates), so the plant modes cancel only if the design conditions hold."""
    E, A, C = (np.asarray(x) for x in (sys_.E, sys_.A, sys_.C))
    N, J, F, S, G, M, P, Q, Wy = (np.asarray(x) for x in (obs.N, obs.J, obs.F, obs.S, obs.G, obs.M,
                                                          obs.P, obs.Q, obs.Wy))
    n, q0, q1 = A.shape[0], N.shape[0], G.shape[0]
    mw, mv = Bw.shape[1], Dv.shape[1]
    Ej = np.eye(n + q0 + q1)
    Ej[:n, :n] = E
    Aj = np.block([[A, np.zeros((n, q0 + q1))], [F @ Wy @ C, N, J], [M @ Wy @ C, S, G]])
    Bj = np.block([[Bw, np.zeros((n, mv))], [np.zeros((q0, mw)), F @ Wy @ Dv],
                   [np.zeros((q1, mw)), M @ Wy @ Dv]])
    Cj = np.hstack([Q @ Wy @ C - np.asarray(L), P, np.zeros((P.shape[0], q1))])
    Dj = np.hstack([np.zeros((P.shape[0], mw)), Q @ Wy @ Dv])
    return Ej, Aj, Bj, Cj, Dj


def plain_skeleton(v):
    """A design file's JSON skeleton (`fojax._serialize`) with its encoded dicts
    (``{"$": "dict", "items": [[key, value], ...]}``) as plain dicts, so keys have paths."""
    if isinstance(v, dict) and v.get("$") == "dict" and isinstance(v.get("items"), list):
        return {str(k): plain_skeleton(x) for k, x in v["items"]}
    if isinstance(v, dict):
        return {k: plain_skeleton(x) for k, x in v.items()}
    if isinstance(v, list):
        return [plain_skeleton(x) for x in v]
    return v


def json_differences(x, y, path=""):
    """The paths at which two JSON values differ, but for the solver's wall-clock time."""
    x, y = plain_skeleton(x), plain_skeleton(y)
    if isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
        return [d for i, (a, b) in enumerate(zip(x, y, strict=True)) for d in json_differences(a, b, f"{path}/{i}")]
    if isinstance(x, dict) and isinstance(y, dict):
        return [d for k in sorted(set(x) | set(y)) for d in json_differences(x.get(k), y.get(k), f"{path}/{k}")]
    if path.endswith("/solve_time") or "/solve_time/" in path:  # the solver's wall clock (a float node)
        return []
    return [] if x == y else [(path, x, y)]


def uncertain_plant_3_3_7(ex, delta=None):
    """The fault-augmented §3.3.7 plant (9 states, ``ex.augmented``) with the uncertainty
    ``δ ΔA`` on its 6 physical states (``ex.dA`` padded with zeros for the 3 fault states)
    and the δ profile `delta` (default: a constant 0 that the studies' samplers replace).
    Imports fojax/JAX lazily."""
    import jax.numpy as jnp

    import fojax

    dA = np.zeros((1, 9, 9))
    dA[0, :6, :6] = ex.dA
    delta = fojax.Constant(jnp.zeros(1)) if delta is None else delta
    return fojax.UncertainDescriptorSystem(ex.augmented, dA=dA, delta=delta)


def small_step_input_study(seed: int, n_delta: int, n_faults: int):
    """``(study, design)``: the short §3.3.7 study of the study-loss tests (fault-augmented
    plant, constant δ in [-0.3, 0.3] × constant faults, 21 points on [0, 1], a step input
    at t = 0.33 between grid points: a jump of the exosystem state) and the generalized
    LMI design in ``Disk(-2, 1)``; ``n_delta × n_faults`` samples from ``PRNGKey(seed)``.
    Imports fojax/JAX lazily (the other helpers are NumPy only)."""
    import jax
    import jax.numpy as jnp

    import fojax
    from fojax import studies as S
    from fojax.design import design_functional_observer, Disk

    ex = fojax.models.example_3_3_7()
    d = design_functional_observer(ex.augmented, ex.L_aug, kind="generalized", region=Disk(-2.0, 1.0))
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:6].set(0.5)
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    study = S.Study(plant, x0, jnp.linspace(0.0, 1.0, 21), ex.L_aug, fojax.Step(jnp.array([0.4, -0.3]), 0.33),
                    uncertainty=(S.constant_delta(k1, n_delta, 1, bounds=(-0.3, 0.3)),),
                    scenarios=(S.constant_faults(k2, n_faults, x0, 3),))
    return study, d


def h2_by_integral(sys_, L, obs, Bw, Dv) -> float:
    r"""$\|T - D_j\|_2$ of `joint_error_system` (its strictly proper part) by the frequency-domain
    definition $\frac1\pi\int_0^\infty \|\mathcal C(j\omega\mathcal E - \mathcal A)^{-1}\mathcal B\|_F^2
    d\omega$ (`scipy.integrate.quad`, $\omega = \tan\theta$): the H2 oracle of test_h2 and
    test_tuning_robustness."""
    import scipy.integrate as si

    Ej, Aj, Bj, Cj, _ = joint_error_system(sys_, L, obs, Bw, Dv)

    def f(theta):
        w = np.tan(theta)
        G = Cj @ np.linalg.solve(1j * w * Ej - Aj, Bj)
        return float(np.sum(np.abs(G) ** 2)) * (1.0 + w * w)  # dω = (1 + ω²) dθ

    val, _ = si.quad(f, 0.0, np.pi / 2, limit=400, epsabs=0.0, epsrel=1e-10)
    return float(np.sqrt(val / np.pi))


# ------------------------------------------------- plants of the H∞/H2 tests (test_hinf, test_h2,
# test_tuning_robustness)

def scalar_plant(a):
    r"""$\dot x = ax + u$, $y = x$: with $B_w = D_v = 1$, $z = x$ the scalar Kalman / H∞ closed forms."""
    import fojax

    return fojax.DescriptorSystem(np.eye(1), a * np.eye(1), np.ones((1, 1)), np.eye(1))


def random_descriptor(seed, *, disturb_algebraic_row: bool = True):
    """``(system, L, Bw, Dv)``: n = 5, rank E = 4 (index 1: A22 kept away from 0), p = 3, q = 2,
    Dv = 0.3 I. With the default q0 = 2, Σ has q0 + r1 + p = 6 > n rows, so the gains 𝕐, Y3 are
    free and the H∞ LMI has room. ``disturb_algebraic_row=False`` zeroes the disturbance on the
    algebraic row (there it reaches ẑ − z directly: an H2 design needs that, and q0 = 4 against
    the noise's feedthrough). Same random draws either way."""
    import fojax

    rng = np.random.default_rng(seed)
    n = 5
    E = np.diag([1.0, 1, 1, 1, 0])
    A = rng.standard_normal((n, n))
    A[4, 4] += 3.0 * np.sign(A[4, 4])
    B = rng.standard_normal((n, 1))
    C = rng.standard_normal((3, n))
    L = rng.standard_normal((2, n))
    Bw = rng.standard_normal((n, 2))
    if not disturb_algebraic_row:
        Bw[4] = 0.0
    return fojax.DescriptorSystem(E, A, B, C), L, Bw, 0.3 * np.eye(3)


def channels_3_3_7(delta_max: float = 0.3, sigma: float = 0.05):
    """``(example, Bw, Dv)`` of §3.3.7: the uncertainty δΔA, |δ| ≤ `delta_max`, as the disturbance
    channel (`fojax.design.hinf_uncertainty_channel`; on the differential rows only) and output
    noise ``Dv = sigma I3``."""
    import fojax
    from fojax.design import hinf_uncertainty_channel

    ex = fojax.models.example_3_3_7()
    Bw, _ = hinf_uncertainty_channel(np.asarray(ex.dA), delta_max)
    return ex, Bw, sigma * np.eye(3)


class WeightedPenalty(eqx.Module):
    """A user term for `fojax.tune`'s ``extra_loss``: ``weight · of(obs, p)``. The weight is an
    array, a leaf of the jitted tuning step rather than part of its structure (``of``, a
    module-level function, is), so tunings with different weights run one compiled step: a
    test module tunes with weight 0 wherever it needs the plain objective (+ 0 to the loss
    and to its gradient: the objective exactly) and its extra-loss test with another weight,
    and its tuning step, the module's largest program, compiles once. The
    ``extra_loss=None`` branch is exercised by the other tuning modules (e.g.
    tests/test_tuning.py, tests/test_parameterization.py) and the CLI studies."""

    weight: jax.Array
    of: object = eqx.field(static=True)

    def __init__(self, weight, of):
        self.weight = jnp.asarray(weight, dtype=jnp.float64)
        self.of = of

    def __call__(self, obs, p):
        return self.weight * self.of(obs, p)


NOTEBOOKS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "notebooks")


@dataclasses.dataclass
class ExecutedNotebook:
    """A notebook after `execute_notebook`: the node, the text it printed (streams and
    ``text/plain`` results of the code cells, in order) and how many PNG figures it drew."""

    nb: object
    text: str
    figures: int

    @property
    def errors(self) -> list:
        return [o for c in self.nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
                if o.get("output_type") == "error"]


def execute_notebook(name: str, *, timeout: int = 600) -> ExecutedNotebook:
    """Execute ``notebooks/<name>`` top to bottom in a fresh ``python3`` kernel (nbclient),
    in the notebooks' folder, and return what it printed and drew."""
    import nbclient
    import nbformat

    path = os.path.join(NOTEBOOKS, name)
    nb = nbformat.read(path, as_version=4)
    nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": NOTEBOOKS}}).execute()
    cells = [c.get("outputs", []) for c in nb.cells if c.cell_type == "code"]
    text = "\n".join(
        "".join(o["text"] if o.get("output_type") == "stream" else o.get("data", {}).get("text/plain", "")
                for o in outputs)
        for outputs in cells)
    return ExecutedNotebook(nb, text, sum("image/png" in o.get("data", {}) for outputs in cells for o in outputs))


def index1_system(n, p, q, n_alg, seed):
    """A random stable index-1 plant of a shape the benchmarks do not use (m = 3 inputs) and a
    random functional with `q` rows."""
    from scipy.stats import ortho_group

    import fojax

    rng = np.random.default_rng([seed, n, p, q])
    r = n - n_alg
    A0 = rng.standard_normal((n, n)) / np.sqrt(n)
    A0[:r, :r] -= 2.0 * np.eye(r)
    A0[r:, r:] -= 2.0 * np.eye(n_alg)
    U, V = ortho_group.rvs(n, random_state=rng), ortho_group.rvs(n, random_state=rng)
    E = U @ np.diag([1.0] * r + [0.0] * n_alg) @ V
    return (fojax.DescriptorSystem(E, U @ A0 @ V, rng.standard_normal((n, 3)), rng.standard_normal((p, n))),
            rng.standard_normal((q, n)))


def assert_design_conditions(d, sysm, L):
    """Conditions a.–d. of a functional-observer design recomputed with NumPy from its observer
    matrices (``N TE + F Ψ = T A``, ``H = T B``, ``S TE + M Ψ = 0``, ``P TE + Q Ψ = L``, relative
    to the data's scale); returns the observer's blocks and its error matrix ``[[N, J], [S, G]]``."""
    b = {k: np.asarray(getattr(d.observer, k)) for k in "N J F H S G M P Q".split()}
    E, A, B, C = (np.asarray(x) for x in (sysm.E, sysm.A, sysm.B, sysm.C))
    Psi = np.vstack([np.asarray(d.structure.Eperp) @ A, C])
    T = np.asarray(d.T)
    TE = T @ E
    scale = max(1.0, np.abs(A).max(), np.abs(T).max()) * max(1.0, np.abs(b["N"]).max(), np.abs(b["F"]).max())
    assert np.abs(b["N"] @ TE + b["F"] @ Psi - T @ A).max() <= 1e-9 * scale
    assert np.abs(b["H"] - T @ B).max() <= 1e-9 * scale
    if b["S"].size:
        assert np.abs(b["S"] @ TE + b["M"] @ Psi).max() <= 1e-9 * scale
    assert np.abs(b["P"] @ TE + b["Q"] @ Psi - np.asarray(L)).max() <= 1e-9 * max(scale, np.abs(L).max())
    return b, np.block([[b["N"], b["J"]], [b["S"], b["G"]]])
