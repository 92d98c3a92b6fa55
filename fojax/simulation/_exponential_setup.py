r"""The host side of the exponential integrator (`fojax.simulation._exponential`): what each
sample's loop is made of, and the check that it is what the integrator assumes.

- **Decomposition.** The reduced joint vector field of one sample is affine in the state
  and in the values of the plant's signals (uncertainty δ(t), faults, noise, input):
  $\dot w = A_0 w + \sum_j s_j(t)\,(\ldots)$. `decompose` reads its terms by probing: the
  signals are replaced by `_Probe` leaves whose values are inputs, and the vector field is
  differentiated with respect to them (`_probe_matrices`).
- **Plan.** Terms equal for every sample of a chunk are *shared* (multiplied into the
  φ-matrices once), terms that vanish are skipped, the rest are per-sample (`_host_plan`,
  from the set-up statistics of `setup_all`; `kernel_inputs` hands the kernel only what
  it reads).
- **Host check.** `check_affine` compares the decomposition with the plant's own vector
  field and outputs at random signal values and times, and refuses a plant for which the
  integrator would be wrong (a signal in the algebraic equations, a product of signals, a
  plant using ``t`` directly), naming the cause.
"""

from __future__ import annotations

import collections
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError, ShapeError
from .._small_linalg import solve_small
from ..plant import AbstractSignal, Constant
from ._reduction import slow_rate, solve_fast, svd_split


#: Number of traces of the compiled set-up passes and kernels (tests prove no retrace with them).
TRACE_COUNTS: collections.Counter = collections.Counter()


#: Relative size below which a term of the decomposition counts as zero, or as equal
#: across the samples of a chunk (round-off of the per-sample reductions).
PLAN_RTOL = 1e-13


#: Largest relative mismatch between the decomposition and the plant's own vector
#: field accepted by the host check.
AFFINE_CHECK_RTOL = 1e-8


#: XLA options of the host-side passes that run once per call on small data (the set-up
#: statistics, the affine check): without the backend's optimisation passes they compile
#: in about half the time, and their run time is negligible either way. The stepping
#: kernel keeps the default (it runs ~40 % slower at level 0).
HOST_PASS_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


def _check_structure(plant, observers):
    if not plant.linear_in_state:
        raise InputError(
            "the exponential stepper (fojax.Exponential) needs a plant that is linear in the state "
            f"(plant.linear_in_state); {type(plant).__name__} is not. Use stepper=fojax.Diffrax(...) "
            "for nonlinear plants."
        )
    bad = [type(o).__name__ for o in observers if o.linear_matrices() is None]
    if bad:
        raise InputError(
            f"the exponential stepper (fojax.Exponential) needs LTI observers (linear_matrices() not None); "
            f"{bad} are not."
        )
    for i, o in enumerate(observers):
        L = o.linear_matrices()
        for name, M, cols, what in (("Bu", L.Bu, plant.m, "input"), ("By", L.By, plant.p, "output")):
            if tuple(M.shape) != (o.state_size, cols):
                raise ShapeError(
                    f"observers[{i}].linear_matrices().{name}",
                    (o.state_size, cols),
                    tuple(M.shape),
                    f"It needs one column per plant {what} ({type(plant).__name__} has "
                    f"{'m' if what == 'input' else 'p'} = {cols}).",
                )


def _is_signal(x) -> bool:
    return isinstance(x, AbstractSignal)


def _plant_signals(plant) -> tuple:
    """The signals inside ``plant`` (outermost ones, in pytree order)."""
    return tuple(leaf for leaf in jax.tree.leaves(plant, is_leaf=_is_signal) if _is_signal(leaf))


class _Probe(AbstractSignal):
    """A constant stand-in for a signal (its value is the probe)."""

    value: jax.Array

    def __call__(self, t):
        return self.value

    @property
    def size(self):
        return self.value.shape[-1]


def _with_probes(plant, s):
    """``plant`` with its signals replaced by constants taken from ``s`` (in order)."""
    leaves, treedef = jax.tree.flatten(plant, is_leaf=_is_signal)
    out, off = [], 0
    for leaf in leaves:
        if _is_signal(leaf):
            out.append(_Probe(s[off : off + leaf.size]))
            off += leaf.size
        else:
            out.append(leaf)
    return jax.tree.unflatten(treedef, out)


def _signal_values(sigs, t):
    if not sigs:
        return jnp.zeros((0,))
    return jnp.concatenate([jnp.asarray(sg(t), dtype=float).reshape(-1) for sg in sigs])


def _probe_matrices(plant, observers):
    r"""The joint slow system at the probes ``s = 0`` and ``s = e_i`` (leading axis ``P = 1 + n_s``).

    Each probed plant (signals := ``s``) is time-invariant and affine in ``(x, u)``; with
    $v = [u; 1]$ its data are $f = A x + B_v v$, $y = C x + D_v v$ (Jacobians at 0). All probes
    are reduced with the algebraic block $\tilde A_{22}$ of the ``s = 0`` probe (one
    elimination for every probe): the decomposition is affine only when the signals leave
    the algebraic equations' state dependence alone, and the host check (which uses the
    plant's own, per-point solve) refuses plants where they do not.

    Returns ``(Aj (P, N, N), Bj (P, N, m+1), OM (P, n+Σ, N), OF (P, n+Σ, m+1), split,
    (Yw (P, p, N), Yv (P, p, m+1)))``: $\dot w = A_j w + B_j v$, $[x; \xi] = OM\,w + OF\,v$
    and the plant output $y = Y_w w + Y_v v$.
    """
    ns = sum(sg.size for sg in _plant_signals(plant))
    probes = jnp.concatenate([jnp.zeros((1, ns)), jnp.eye(ns)], axis=0)
    n, m = plant.n, plant.m
    t0 = jnp.zeros(())
    zx, zu = jnp.zeros((n,)), jnp.zeros((m,))

    def linear_data(s):
        p = _with_probes(plant, s)
        rhs = lambda x, u: p.rhs(t0, x, u)
        out = lambda x, u: p.output(t0, x, u)
        A, Bu = jax.jacfwd(rhs, argnums=(0, 1))(zx, zu)
        C, Du = jax.jacfwd(out, argnums=(0, 1))(zx, zu)
        Bv = jnp.concatenate([Bu, rhs(zx, zu)[:, None]], axis=1)
        Dv = jnp.concatenate([Du, out(zx, zu)[:, None]], axis=1)
        return A, Bv, C, Dv

    A, Bv, C, Dv = jax.vmap(linear_data)(probes)  # (P, n, n), (P, n, m+1), (P, p, n), (P, p, m+1)
    P = A.shape[0]
    split = svd_split(plant.E)
    ms, mf = split.slow, split.fast
    At = jnp.einsum("ji,pjk,kl->pil", split.U, A, split.V)
    Bt = jnp.einsum("ji,pjk->pik", split.U, Bv)
    M = split.newton_matrix(At[0])
    rhs_cols = jnp.concatenate(
        [mf[None, :, None] * At * ms[None, None, :], mf[None, :, None] * Bt], axis=2
    )  # (P, n, n + m + 1)
    KK = -solve_small(M, jnp.moveaxis(rhs_cols, 0, 1).reshape(n, -1))
    KK = jnp.moveaxis(KK.reshape(n, P, -1), 1, 0)
    K, Ku = KK[:, :, :n], KK[:, :, n:]
    Pz = jnp.diag(ms)[None] + K  # z = Pz z_slow + Ku v
    rows = (ms / split.sigma)[None, :, None]
    As = rows * (At @ Pz)
    Bs = rows * (Bt + At @ Ku)
    Tx = split.V[None] @ Pz
    Tu = split.V[None] @ Ku
    Cs = C @ Tx
    Ds = C @ Tu + Dv
    sel_u = jnp.concatenate([jnp.eye(m), jnp.zeros((m, 1))], axis=1)
    zeros = lambda r, c: jnp.zeros((P, r, c))  # noqa: E731
    rows_A = [[As] + [zeros(n, o.state_size) for o in observers]]
    rows_B = [Bs]
    for i, o in enumerate(observers):
        L = o.linear_matrices()
        row = [L.By[None] @ Cs]
        for j, o2 in enumerate(observers):
            row.append(jnp.broadcast_to(L.A, (P,) + L.A.shape) if i == j else zeros(o.state_size, o2.state_size))
        rows_A.append(row)
        rows_B.append((L.Bu @ sel_u)[None] + L.By[None] @ Ds)
    Aj = jnp.concatenate([jnp.concatenate(r, axis=2) for r in rows_A], axis=1)
    Bj = jnp.concatenate(rows_B, axis=1)
    no = Aj.shape[-1] - n
    OM = jnp.concatenate(
        [jnp.concatenate([Tx, zeros(n, no)], axis=2), jnp.broadcast_to(jnp.eye(no, n + no, n), (P, no, n + no))],
        axis=1,
    )
    OF = jnp.concatenate([Tu, zeros(no, m + 1)], axis=1)
    Yw = jnp.concatenate([Cs, zeros(Cs.shape[1], no)], axis=2)
    return Aj, Bj, OM, OF, split, (Yw, Ds)


def _split_terms(M):
    """``[M(0), M(e_1) − M(0), …]``: the constant part and the coefficient of each ``s_i``."""
    return jnp.concatenate([M[:1], M[1:] - M[:1]], axis=0)


def decompose(plant, observers, x0k):
    """One sample's probe decomposition (`_probe_matrices`), its initial slow state and
    mask: ``(Aj, Bj, OM, OF, (Yw, Yv), w0, mask)`` (leading probe axis ``P``)."""
    Aj, Bj, OM, OF, split, Y = _probe_matrices(plant, observers)
    no = Aj.shape[-1] - plant.n
    w0 = jnp.concatenate([split.slow * (split.V.T @ x0k)] + [o.initial_state() for o in observers])
    mask = jnp.concatenate([split.slow, jnp.ones((no,))])
    return Aj, Bj, OM, OF, Y, w0, mask


def setup_data(Aj, Bj, G, H, w0, mask):
    """The kernel's per-sample data from per-probe matrices (outputs $o = G w + H v$ at
    each probe): constant parts and coefficients of the signal values (`_split_terms`)."""
    return dict(A=_split_terms(Aj), B=_split_terms(Bj), G=_split_terms(G), H=_split_terms(H), w0=w0, mask=mask)


def _stats(data, ref):
    """Small summaries (host, NumPy) of a chunk's data that `_host_plan` turns into a plan;
    deviations are measured from ``ref`` (sample 0's data, no batch axis), so that chunks
    merge (`_merge_stats`)."""
    A, B, G, H, mask = data["A"], data["B"], data["G"], data["H"], data["mask"]
    return dict(
        mask_min=np.min(mask, axis=0),
        mask_max=np.max(mask, axis=0),
        A_abs=np.max(np.abs(A), axis=0),
        A_dev=np.max(np.abs(A - ref["A"][None]), axis=(0, 2, 3)),
        B_abs=np.max(np.abs(B), axis=0),
        G_abs=np.max(np.abs(G), axis=(0, 2, 3)),
        G_dev=np.max(np.abs(G - ref["G"][None]), axis=(0, 2, 3)),
        H_abs=np.max(np.abs(H), axis=(0, 2, 3)),
    )


def _merge_stats(a, b):
    return {k: (np.minimum if k == "mask_min" else np.maximum)(a[k], b[k]) for k in a}


def setup_all(setup, p, reference):
    """The set-up of a chunk ``p`` (leaves with a leading batch axis) and of ``reference``
    (one sample, whose constant part, all signals at zero, is ``A0``), in one vmapped call.
    Returns ``(data, A0)``; the constant term of every sample is ``Ā_k − A0``. On the host
    it runs once per chunk (twice when there are several), compiled once, and it is the
    only place the set-up is compiled: the stepping kernel reads `kernel_inputs`.
    Traceable (under an outer `jax.jit` / `jax.grad` it is called directly)."""
    p = jax.tree.map(lambda a, r: jnp.concatenate([a, jnp.asarray(r)[None]], axis=0), p, reference)
    data, _ = jax.vmap(setup)(p)
    A0 = data["A"][-1, 0]
    data = jax.tree.map(lambda a: a[:-1], data)
    data["A"] = data["A"].at[:, 0].add(-A0[None])
    return data, A0


@eqx.filter_jit(compiler_options=HOST_PASS_COMPILER_OPTIONS)
def _setup_chunk(setup, p, reference):
    """`setup_all` compiled for the host pre-pass (`prepare`)."""
    TRACE_COUNTS["setup"] += 1
    return setup_all(setup, p, reference)


def kernel_inputs(data, plan, xp=np):
    """What the stepping kernel reads, from the set-up's ``data`` (leading batch axis; the
    constant term already reduced by ``A0``) and the `_Plan`: per sample (leading batch
    axis) ``w0`` and the stacked per-sample terms ``Ms``, ``Bs``, ``Gs``, ``Hs``; shared
    by all (sample 0's) the shared perturbation and output matrices. ``xp``: `numpy` on
    the host, `jax.numpy` under a trace."""
    keep, rows, cols = (np.asarray(a, dtype=int) for a in plan[:3])
    Bn = data["w0"].shape[0]
    A = data["A"][:, :, keep][:, :, :, keep][:, :, rows][:, :, :, cols]  # (B, nt, nr, nc)
    G = data["G"][:, :, :, keep]  # (B, nt, R, Nk)
    Bf = data["B"][:, :, keep][:, :, rows]  # (B, nt, nr, m+1)
    H = data["H"]  # (B, nt, R, m+1)
    nr, nc, Nk, R, m1 = rows.size, cols.size, keep.size, G.shape[2], Bf.shape[-1]

    def stack(parts, shape, axis=1):
        return xp.stack(parts, axis=axis) if parts else xp.zeros(shape)

    per = dict(
        w0=data["w0"][:, keep],
        Ms=stack([A[:, i] for i, kind in plan.terms if kind == "sample"], (Bn, 0, nr, nc)),
        Bs=stack([Bf[:, i] for i in plan.fterms], (Bn, 0, nr, m1)),
        Gs=stack([G[:, i] for i, kind in plan.gterms if kind == "sample"], (Bn, 0, R, Nk)),
        Hs=stack([H[:, i] for i in plan.hterms], (Bn, 0, R, m1)),
    )
    shared = dict(
        A=stack([A[0, i] for i, kind in plan.terms if kind == "shared"], (0, nr, nc), axis=0),
        G=stack([G[0, i] for i, kind in plan.gterms if kind == "shared"], (0, R, Nk), axis=0),
    )
    return per, shared


def prepare(setup, p, reference, chunk_size: int):
    """Host: ``A0``, the `_Plan` of all samples of ``p`` (read in chunks of `chunk_size`),
    the kernel's inputs (`kernel_inputs`: per sample, NumPy, and shared) and sample 0's
    data. With one chunk the set-up runs once; with several, a second time per chunk
    once the plan is known (same compiled function), so that only the kernel's inputs of
    all samples are held, not the set-up's data."""
    Bn = jax.tree.leaves(p)[0].shape[0]
    bc = min(int(chunk_size), Bn)
    n_chunks = -(-Bn // bc)
    pad = n_chunks * bc - Bn
    if pad:  # copies of the last sample change no maximum; one shape, one compilation
        p = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)], axis=0), p)

    def chunk(i):
        data, A0 = _setup_chunk(setup, jax.tree.map(lambda a: a[i * bc : (i + 1) * bc], p), reference)
        return jax.tree.map(np.asarray, data), np.asarray(A0)

    stats = None
    for i in range(n_chunks):
        data, A0 = chunk(i)
        if i == 0:
            ref = jax.tree.map(lambda a: a[0], data)
        st = _stats(data, ref)
        stats = st if stats is None else _merge_stats(stats, st)
    plan = _host_plan(stats, A0)
    if n_chunks == 1:
        per, shared = kernel_inputs(data, plan)
    else:
        parts = [kernel_inputs(chunk(i)[0], plan) for i in range(n_chunks)]
        shared = parts[0][1]
        per = jax.tree.map(lambda *a: np.concatenate(a, axis=0)[:Bn], *[pt[0] for pt in parts])
    return A0, plan, per, shared, ref


class _Plan(NamedTuple):
    """Static description of which terms the kernel applies, and how."""

    keep: tuple  # kept components of w (slow ones and observer states)
    rows: tuple  # components g writes (indices into the kept ones)
    cols: tuple  # components g reads
    terms: tuple  # ((i, "shared" | "sample"), ...) state terms
    fterms: tuple  # (i, ...) input terms (per sample)
    gterms: tuple  # ((i, kind), ...) output-map terms
    hterms: tuple  # (i, ...) output feedthrough terms (per sample)


def _full_plan(N, n_terms) -> _Plan:
    idx = tuple(range(N))
    ii = tuple(range(n_terms))
    return _Plan(idx, idx, idx, tuple((i, "sample") for i in ii), ii, tuple((i, "sample") for i in ii), ii)


def _host_plan(stats, A0) -> _Plan:
    st = {k: np.asarray(v) for k, v in stats.items()}
    A0 = np.asarray(A0)
    N = A0.shape[0]
    if np.array_equal(st["mask_min"], st["mask_max"]):
        keep = np.flatnonzero(st["mask_max"] > 0)
    else:  # different ranks of E in one chunk: keep every component (masked)
        keep = np.arange(N)
    A_abs = st["A_abs"][:, keep][:, :, keep]
    B_abs = st["B_abs"][:, keep]
    tol_a = PLAN_RTOL * max(1.0, float(np.max(np.abs(A0[np.ix_(keep, keep)]), initial=0.0)), float(np.max(A_abs, initial=0.0)))
    tol_b = PLAN_RTOL * max(1.0, float(np.max(B_abs, initial=0.0)))
    terms, nz_a = [], np.zeros(A_abs.shape[1:], dtype=bool)
    for i in range(A_abs.shape[0]):
        nz = A_abs[i] > tol_a
        if nz.any():
            terms.append((i, "shared" if st["A_dev"][i] <= tol_a else "sample"))
            nz_a |= nz
    fterms, nz_b = [], np.zeros(B_abs.shape[1], dtype=bool)
    for i in range(B_abs.shape[0]):
        nz = B_abs[i] > tol_b
        if nz.any():
            fterms.append(i)
            nz_b |= nz.any(axis=1)
    rows = np.flatnonzero(nz_a.any(axis=1) | nz_b)
    cols = np.flatnonzero(nz_a.any(axis=0))
    tol_g = PLAN_RTOL * max(1.0, float(np.max(st["G_abs"], initial=0.0)), float(np.max(st["H_abs"], initial=0.0)))
    gterms = tuple(
        (i, "shared" if st["G_dev"][i] <= tol_g else "sample")
        for i in range(st["G_abs"].shape[0])
        if st["G_abs"][i] > tol_g
    )
    hterms = tuple(i for i in range(st["H_abs"].shape[0]) if st["H_abs"][i] > tol_g)
    as_t = lambda a: tuple(int(v) for v in a)
    return _Plan(as_t(keep), as_t(rows), as_t(cols), tuple(terms), tuple(fterms), gterms, hterms)


@eqx.filter_jit(compiler_options=HOST_PASS_COMPILER_OPTIONS)
def _affinity_mismatch(model, p, terms, outputs, t_rand, s_rand, u_rand, w_rand):
    """Relative mismatch of one sample's decomposition (``terms = (A, B, G, H)``, raw: the
    constant part not reduced by ``A0``) against the plant's own slow field and against
    ``outputs(plant, observers, t, x, ξ, u, y)`` computed from the plant's own output."""
    TRACE_COUNTS["check"] += 1
    plant, observers, u = model(p)  # (plant, observers, input signal) of one sample
    A, B, G, H = terms
    split = svd_split(plant.E)
    n = plant.n
    mask = jnp.concatenate([split.slow, jnp.ones((A.shape[-1] - n,))])
    w = mask * w_rand

    def generic(pl, usig, t):
        # the plant's own slow field (as on fojax.simulate's diffrax path: a fresh algebraic
        # solve at (t, w)), the observers' vector fields, and the metric outputs
        z = solve_fast(pl, split, t, w[:n], usig)
        u_t = usig(t)
        x = split.V @ z
        parts, off = [slow_rate(pl, split, t, z, u_t)], n
        y = pl.output(t, x, u_t)
        for o in observers:
            parts.append(o.vector_field(t, w[off : off + o.state_size], u_t, y))
            off += o.state_size
        return jnp.concatenate(parts), outputs(pl, observers, t, x, w[n:], u_t, y)

    def decomposed(s, v):
        c = jnp.concatenate([jnp.ones((1,)), s])
        F = jnp.einsum("i,ijk,k->j", c, A, w) + jnp.einsum("i,ijk,k->j", c, B, v)
        O = jnp.einsum("i,ijk,k->j", c, G, w) + jnp.einsum("i,ijk,k->j", c, H, v)
        return F, O

    def rel(a, b):
        return jnp.max(jnp.abs(a - b), initial=0.0) / jnp.maximum(jnp.max(jnp.abs(b), initial=0.0), 1e-300)

    # (i) random signal values and input at t = 0, where the decomposition was built
    # (affinity in them; the algebraic equations solved at the point)
    F1, O1 = generic(_with_probes(plant, s_rand), Constant(u_rand), jnp.zeros(()))
    D1, P1 = decomposed(s_rand, jnp.concatenate([u_rand, jnp.ones((1,))]))
    # (ii) the plant as given at a random time (time enters only through its signals)
    F2, O2 = generic(plant, u, t_rand)
    D2, P2 = decomposed(_signal_values(_plant_signals(plant), t_rand), jnp.concatenate([u(t_rand), jnp.ones((1,))]))
    return jnp.stack([rel(D1, F1), rel(P1, O1), rel(D2, F2), rel(P2, O2)])


def check_affine(model, first, data, A0, outputs, t0, t1, ns, m, who):
    """Host: refuse (`fojax.errors.InputError`) a decomposition of sample ``first`` (its `data`,
    no batch axis) that misses the plant's own vector field or outputs."""
    rng = np.random.default_rng(20261121)
    t_rand = jnp.asarray(t0 + 0.3719 * (t1 - t0))
    A = np.array(data["A"])
    A[0] += np.asarray(A0)
    terms = tuple(jnp.asarray(a) for a in (A, data["B"], data["G"], data["H"]))
    err = np.asarray(
        _affinity_mismatch(
            model,
            first,
            terms,
            outputs,
            t_rand,
            jnp.asarray(rng.standard_normal(ns)),
            jnp.asarray(rng.standard_normal(m)),
            jnp.asarray(rng.standard_normal(A0.shape[0])),
        )
    )
    what = (
        "the vector field at random signal values",
        "the metric outputs at random signal values",
        f"the vector field at t = {float(t_rand):g}",
        f"the metric outputs at t = {float(t_rand):g}",
    )
    for e, w in zip(err, what):
        if not e <= AFFINE_CHECK_RTOL:
            raise InputError(
                f"{who} needs a plant whose reduced vector field is affine in "
                "the state and in the values of its signals (uncertainty δ(t), faults, noise, "
                "input), with time entering only through those signals. On the first sample the "
                f"affine decomposition misses {w} by {e:.1e} (relative; tolerance "
                f"{AFFINE_CHECK_RTOL:.0e}). Typical causes: a time-varying uncertainty in the "
                "algebraic equations (it enters through Ã22⁻¹), a product of signals (δ(t)·dB·u(t) "
                "with a nonzero input), or a plant using t directly. Use jax.vmap(fojax.simulate) "
                "(adaptive diffrax) for such plants."
            )
