r"""The exact path of `run_study`: LTI samples on the batch-last kernel of `fojax.simulation._batch`.

A study qualifies when every sample is a linear time-invariant loop driven by *known*
signals: the plant is a `fojax.DescriptorSystem` or an `fojax.UncertainDescriptorSystem`
with a constant $\delta$ (per sample), possibly wrapped in a `FaultyPlant`; the
observers are LTI; the grid is uniform; the input and the fault are signals that a
linear exosystem generates exactly (`exosystem`): zero, constant, step, ramp
(saturating or not), sine, piecewise constant, `FaultProfile` (step or ramp-then-hold
faults, any onset). The signals become extra states $v$ of the joint loop
($\dot v = S v$), and their jumps (a step's onset, a ramp's start and end, a fault's
onset) enter exactly even between grid points: with $t_{k-1} < t_j \le t_k$,

$$w_k = e^{\mathcal A h} w_{k-1} + e^{\mathcal A (t_k - t_j)}\,\Delta w_j .$$

Each sample is then $w_k = \Phi w_{k-1}$ (+ its jumps) on the grid, stepped by
`fojax.simulation._batch` with the batch as the last axis, and the metrics of
`run_study` (IAE, ISE, ITAE, peak, settling time, and the error trajectories for the
quantile bands when asked) are accumulated inside the time loop with the same
definitions as `error_metrics` (trapezoidal rule on the grid).
"""

from __future__ import annotations

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Literal
from jaxtyping import Array

from ..plant import (
    Constant,
    FaultProfile,
    FaultyPlant,
    PiecewiseConstant,
    Ramp,
    Sine,
    Stack,
    Step,
    SumSignal,
    Zero,
)
from ..simulation._batch import (
    _block_kernel,
    _output_basis,
    repeat_groups,
)
from ..simulation._expm import DIFF_MAX_SQUARINGS, expm_last
from ..simulation._joint import Exogenous, joint_matrices
from ..simulation._problem import AbstractBatchProblem, eval_shape_cached
from ..simulation._reduction import (
    check_index1_host,
    is_concrete,
    lti_feedthrough,
    lti_matrices,
    svd_split,
    SVDSplit,
)
from ..simulation._save import METRIC_NAMES
from ..simulation._steppers import Exact, grid_deviation, UNIFORM_GRID_RTOL
from ._adjoint import pass_length, pass_recurrence_reduce, split_recurrence_reduce
from ._sharding import per_sample


#: Signal types `exosystem` generates exactly (and sums / stacks of them).
EXACT_SIGNALS = (Zero, Constant, Step, Ramp, Sine, PiecewiseConstant, FaultProfile)


def exactly_generated(sig) -> bool:
    """Whether `exosystem` generates `sig` exactly."""
    if isinstance(sig, SumSignal):
        return all(exactly_generated(t) for t in sig.terms)
    if isinstance(sig, Stack):
        return all(exactly_generated(t) for t in sig.parts)
    return isinstance(sig, EXACT_SIGNALS)


def exosystem(sig, t0):
    r"""``(S, H, v0, jt, jdv)`` of a linear exosystem generating `sig` exactly from ``t0``:
    $\dot v = S v$, ``sig(t) = H v(t)``, ``v(t0) = v0``, jumps ``jdv[j]`` at ``jt[j]``
    (applied at ``t ≥ jt[j]``, like the signals' own ``t >= onset`` tests; jumps at or
    before ``t0`` are already in ``v0``). ``None`` for other signals. Traceable (values
    may be batched); the structure depends only on the signal's type and shapes."""
    dt = jnp.asarray(t0).dtype
    if isinstance(sig, SumSignal | Stack):
        parts = [exosystem(t, t0) for t in (sig.terms if isinstance(sig, SumSignal) else sig.parts)]
        if any(p is None for p in parts):
            return None
        H = (jnp.concatenate if isinstance(sig, SumSignal) else lambda hs, axis: _blkdiag(*hs))(
            [p[1] for p in parts], axis=1
        )
        return (_blkdiag(*[p[0] for p in parts]), H, jnp.concatenate([p[2] for p in parts]),
                jnp.concatenate([p[3] for p in parts]), _blkdiag(*[p[4] for p in parts]))
    if isinstance(sig, Zero):
        n = sig.size
        return (jnp.zeros((0, 0), dt), jnp.zeros((n, 0), dt), jnp.zeros((0,), dt), jnp.zeros((0,), dt),
                jnp.zeros((0, 0), dt))
    if isinstance(sig, Constant | Step | PiecewiseConstant):
        m = sig.size
        S, H = jnp.zeros((m, m), dt), jnp.eye(m, dtype=dt)
        if isinstance(sig, Constant):
            return S, H, sig.value, jnp.zeros((0,), dt), jnp.zeros((0, m), dt)
        if isinstance(sig, Step):
            return S, H, sig(t0), sig.t0[None], sig.amplitude[None]
        return S, H, sig(t0), sig.times, jnp.diff(sig.values, axis=0)
    if isinstance(sig, Sine):
        m = sig.size
        I, Z = jnp.eye(m, dtype=dt), jnp.zeros((m, m), dt)
        W = jnp.diag(sig.omega)
        S = jnp.block([[Z, Z, Z], [Z, Z, W], [Z, -W, Z]])  # [offset; sin; cos]
        H = jnp.concatenate([I, jnp.diag(sig.amplitude), Z], axis=1)
        arg = sig.omega * t0 + sig.phase
        v0 = jnp.concatenate([sig.offset, jnp.sin(arg), jnp.cos(arg)])
        return S, H, v0, jnp.zeros((0,), dt), jnp.zeros((0, 3 * m), dt)
    if isinstance(sig, Ramp | FaultProfile):
        m = sig.size
        I, Z = jnp.eye(m, dtype=dt), jnp.zeros((m, m), dt)
        S = jnp.block([[Z, I], [Z, Z]])  # [value; rate]
        H = jnp.concatenate([I, Z], axis=1)
        if isinstance(sig, Ramp):
            start, end, rate = sig.t0, sig.t1, sig.slope
            step = jnp.zeros((m,), dt)
        else:
            ramped = sig.rise > 0
            start, end = sig.onset, sig.onset + sig.rise
            rate = jnp.where(ramped, sig.amplitude / jnp.where(ramped, sig.rise, 1.0), 0.0)
            step = jnp.where(ramped, 0.0, sig.amplitude)
        active = (t0 >= start) & (t0 < end)
        v0 = jnp.concatenate([sig(t0), jnp.where(active, rate, 0.0)])
        jt = jnp.stack([start, end])
        jdv = jnp.stack([jnp.concatenate([step, rate]), jnp.concatenate([jnp.zeros_like(step), -rate])])
        return S, H, v0, jt, jdv
    return None


def _unwrap(plant):
    """``(base, Fa, Fs, fault)`` (``fault`` ``None`` without a `FaultyPlant`)."""
    if isinstance(plant, FaultyPlant):
        return plant.base, plant.Fa, plant.Fs, plant.fault
    return plant, None, None, None


def _blkdiag(*ms):
    rows = sum(m.shape[0] for m in ms)
    cols = sum(m.shape[1] for m in ms)
    out = jnp.zeros((rows, cols), ms[0].dtype)
    r = c = 0
    for m in ms:
        out = out.at[r : r + m.shape[0], c : c + m.shape[1]].set(m)
        r, c = r + m.shape[0], c + m.shape[1]
    return out


class StudyProblem(AbstractBatchProblem):
    """The samples of a study as a problem of the batch kernel (see module docstring):
    per index pair ``(i, j)`` the joint loop of plant, observers and exosystem, and the
    metrics of `run_study` accumulated along the grid (a final `AbstractBatchProblem`)."""

    study: object
    observers: tuple
    split: SVDSplit
    E0: Array
    settle_tol: Array
    r: int | None = eqx.field(static=True)
    # 0: metrics only; k >= 1: also the error trajectories on every k-th grid point
    # (``ts[::k]``, the quantile bands' grid of `fojax.studies._runner.band_stride`)
    keep: int = eqx.field(static=True, default=0)
    # the metrics asked for (`fojax.Metrics.kinds`); only these (and "peak" when no integral
    # is asked for) are accumulated
    kinds: tuple[str, ...] = eqx.field(static=True, default=METRIC_NAMES)

    @property
    def computed(self) -> tuple[str, ...]:
        """The metrics accumulated along the grid, in `METRIC_NAMES` order: the requested
        `kinds`, and ``"peak"`` (one maximum per step) when none of the integrals
        ``"iae"``, ``"ise"``, ``"itae"`` is asked for. The finiteness of the computed
        metrics other than the settling time is the sample's success test (`final`); an
        integral is non-finite exactly when some error value is (``|±inf|``, ``nan`` and
        ``inf − inf`` in the trapezoid's end correction propagate; an overflow of the sum
        itself made the peak's run fail as well, since every computed metric is tested),
        so the peak is needed only when the settling time alone is asked for. Dropping
        it saves one maximum per output and step."""
        integral = any(k in self.kinds for k in ("iae", "ise", "itae"))
        return tuple(k for k in METRIC_NAMES if k in self.kinds or (k == "peak" and not integral))

    def joint(self, p):
        # p = (i, j) or (i, j, observers): one copy of the observers per sample (`study_loss`
        # on several devices: fojax.studies._sharding)
        TRACE_COUNTS["StudyProblem.joint"] += 1  # Python traces (run_study's fixed cost: tests count them)
        i, j = p[0], p[1]
        observers = p[2] if len(p) > 2 else self.observers
        study = self.study
        plant, x0 = study.sample(i, j)
        base, Fa, Fs, fault = _unwrap(plant)
        A, B, C = lti_matrices(base)
        t0 = study.ts[0]
        Su, Hu, vu0, jtu, jdvu = exosystem(study.u, t0)
        nu_, m = Su.shape[0], Hu.shape[0]
        n, p_ = A.shape[0], C.shape[0]
        if fault is None:
            Sf, Hf, vf0, jtf, jdvf = exosystem(Zero(0), t0)
            Fa, Fs = jnp.zeros((n, 0)), jnp.zeros((p_, 0))
        else:
            Sf, Hf, vf0, jtf, jdvf = exosystem(fault, t0)
        nf_ = Sf.shape[0]
        exo = Exogenous(
            S=_blkdiag(Su, Sf),
            Hin=_blkdiag(Hu, Hf),
            Hu=jnp.concatenate([Hu, jnp.zeros((m, nf_))], axis=1),
            Dy=jnp.concatenate([lti_feedthrough(base) @ Hu, Fs @ Hf], axis=1),  # y = Cx + Du + Fs f
            v0=jnp.concatenate([vu0, vf0]),
            jt=jnp.concatenate([jtu, jtf]),
            jdv=_blkdiag(jdvu, jdvf),
        )
        Aj, w0, out_map, ok = joint_matrices(
            base.E, A, jnp.concatenate([B, Fa], axis=1), C, observers, x0, self.split, self.r, exo
        )
        ok = ok & jnp.all(base.E == self.E0)
        # errors ẑ_i − z as a linear map of [x; ξ_1; ...; v] (z itself without observers)
        sizes = [o.state_size for o in observers]
        L = study.L
        Hz = jnp.zeros((L.shape[0], nu_ + nf_))
        if study.fault_targets:
            L = jnp.concatenate([L, jnp.zeros((Hf.shape[0], n))], axis=0)
            Hz = jnp.concatenate([Hz, jnp.concatenate([jnp.zeros((Hf.shape[0], nu_)), Hf], axis=1)], axis=0)
        # a signal study (no observers): the rows of z = L x + H_z v itself
        rows = [] if observers else [jnp.concatenate([L, Hz], axis=1)]
        for k, o in enumerate(observers):
            lm = o.linear_matrices()
            blocks = [lm.Dy @ C - L]
            blocks += [lm.C if k == kk else jnp.zeros((lm.C.shape[0], s)) for kk, s in enumerate(sizes)]
            blocks.append(lm.Dy @ exo.Dy + lm.Du @ exo.Hu - Hz)
            rows.append(jnp.concatenate(blocks, axis=1))
        G = jnp.concatenate(rows, axis=0) @ out_map
        N = Aj.shape[0]
        dW = jnp.concatenate([jnp.zeros((exo.jt.shape[0], N - exo.S.shape[0])), exo.jdv], axis=1)
        jumps = (exo.jt, dW) if exo.jt.shape[0] else None
        return Aj, w0, G, ok, jumps

    def plant_first(self, N: int):
        """Static ``(perm, k)`` for `fojax.simulation._batch._multistep_block`: the joint
        state ``[z; ξ; v]`` reordered plant first, ``[z; v; ξ]``, whose first ``k`` rows do
        not involve the observers (`joint_matrices`: the plant's and the exosystem's rows
        have zero observer columns), so the joint matrix is block lower-triangular;
        ``None`` without a static ``r``."""
        nq = sum(o.state_size for o in self.observers)
        if self.r is None or nq == 0 or nq == N:
            return None
        r = self.r
        perm = np.concatenate([np.arange(r), np.arange(r + nq, N), np.arange(r, r + nq)])
        return perm, N - nq

    # metrics along the grid, as `error_metrics` defines them; one accumulator per computed
    # metric (`computed`), in that order
    def init(self, o0):
        a = jnp.abs(o0)
        z = jnp.zeros_like(a)
        first = dict(peak=a, settling_time=jnp.where(a > self.settle_tol, 0, -1))
        return tuple(first.get(k, z) for k in self.computed)

    def update(self, acc, o, k, ts):
        a = jnp.abs(o)
        step = dict(iae=lambda s: s + a, ise=lambda s: s + o * o, itae=lambda s: s + (ts[k] - ts[0]) * a,
                    peak=lambda s: jnp.maximum(s, a), settling_time=lambda s: jnp.where(a > self.settle_tol, k, s))
        return tuple(step[name](v) for name, v in zip(self.computed, acc))

    def update_block(self, acc, O, ks, ts):
        """`update` over ``m`` consecutive steps at once: ``O`` ``(b, K, m)``, ``ks`` ``(m,)``."""
        a = jnp.abs(O)

        def itae(s):
            tk = (ts[ks] - ts[0])[None, None, :]
            return s + jnp.sum(tk * a, axis=2).T

        def settle(s):
            return jnp.maximum(s, jnp.max(jnp.where(a > self.settle_tol, ks[None, None, :], -1), axis=2).T)

        step = dict(iae=lambda s: s + jnp.sum(a, axis=2).T, ise=lambda s: s + jnp.sum(O * O, axis=2).T, itae=itae,
                    peak=lambda s: jnp.maximum(s, jnp.max(a, axis=2).T), settling_time=settle)
        return tuple(step[name](v) for name, v in zip(self.computed, acc))

    def final(self, acc, o0, o_end, ts, h, ok):
        """``(metrics (len(computed), K, b), success (b,))``: NaN metrics where a computed
        metric other than the settling time is not finite (or ``ok`` is false)."""
        T = ts.shape[0]
        a0, a1 = jnp.abs(o0), jnp.abs(o_end)
        tr = ts - ts[0]

        def settle(last):
            return jnp.where(last < 0, 0.0, jnp.where(last == T - 1, jnp.inf, tr[jnp.minimum(last + 1, T - 1)]))

        end = dict(iae=lambda s1: h * (s1 + 0.5 * a0 - 0.5 * a1),
                   ise=lambda s2: h * (s2 + 0.5 * o0 * o0 - 0.5 * o_end * o_end),
                   itae=lambda s3: h * (s3 - 0.5 * tr[-1] * a1), peak=lambda p: p, settling_time=settle)
        mets = jnp.stack([end[name](v) for name, v in zip(self.computed, acc)])  # (len(computed), K, b)
        finite = [i for i, name in enumerate(self.computed) if name != "settling_time"]
        good = ok & jnp.all(jnp.isfinite(mets[np.array(finite)]), axis=(0, 1))
        return jnp.where(good[None, None], mets, jnp.nan), good


@eqx.filter_jit
def _first_joint(problem, p):
    Aj, w0, G, ok, _ = problem.joint(p)
    return G, ok


@eqx.filter_jit
def _sample_data(study, iu, jf):
    """``E`` and ``A`` of sample 0, whether every sample's ``E`` equals it, and its SVD
    split: one compiled call (done eagerly, these few dozen small operations cost one
    XLA compile each, ~2 s on the first call of a process)."""
    base0 = _unwrap(study.sample(0, 0)[0])[0]
    E0 = base0.E
    # in vmapped batches of SAME_E_BATCH samples: the samples' E are never all alive at
    # once (B n² floats: 0.5 GB at n = 256, B = 1,000)
    same = lax.map(lambda ij: jnp.all(_unwrap(study.sample(ij[0], ij[1])[0])[0].E == E0), (iu, jf),
                   batch_size=SAME_E_BATCH)
    return E0, lti_matrices(base0)[0], jnp.all(same), svd_split(E0)


#: Samples whose ``E`` `_sample_data` compares with sample 0's at once.
SAME_E_BATCH = 256


def _structure(fn, *args):
    """The output structure of ``fn(*args)`` without computing it (``None`` stays ``None``,
    module types are kept, arrays become shapes); cached by structure
    (`fojax.simulation._problem.eval_shape_cached`: `fn` is one of the module-level
    functions below)."""
    return eval_shape_cached(fn, *args)


def _observer_lti(o):
    return o.linear_matrices()


def _first_plant(study):
    return study.sample(0, 0)[0]


def _first_lti(study):
    return lti_matrices(_unwrap(study.sample(0, 0)[0])[0])


def exact_problem(study, observers, settle_tol: float, keep: int, kinds: tuple[str, ...] = METRIC_NAMES):
    """Host: the `StudyProblem` of `study`, or ``(None, reason)`` when it does not qualify.
    ``keep``: 0, or the stride of the kept error trajectories (`StudyProblem.keep`);
    ``kinds``: the metrics to accumulate (`StudyProblem.kinds`)."""
    if not is_concrete(study):
        return None, "the study's arrays are traced"
    reason = exact_refusal(study, observers)
    if reason is not None:
        return None, reason
    # every sample must share E (one SVD split for all): checked on the host
    iu = np.arange(study.num_samples) // study.num_scenarios
    jf = np.arange(study.num_samples) % study.num_scenarios
    E0, A0, same_E, split = _sample_data(study, iu, jf)
    if not bool(same_E):
        return None, "E differs between samples"
    E0 = np.asarray(E0)
    check_index1_host(E0, np.asarray(A0), jacobian_name="A")
    r = int(np.sum(np.asarray(split.slow)))
    problem = StudyProblem(study, tuple(observers), split, E0, np.asarray(float(settle_tol)), r, int(keep),
                           tuple(kinds))
    G0, _ = _first_joint(problem, (np.asarray(0), np.asarray(0)))
    basis = _output_basis(np.asarray(G0))
    return (problem, basis, (iu, jf)), None


class LossProblem(AbstractBatchProblem):
    """The `StudyProblem` of `study_loss`: the same samples, but only the one metric the
    loss reads (``"iae"`` or ``"ise"``) is accumulated along the grid (a final
    `AbstractBatchProblem`).

    `StudyProblem` carries five accumulators (IAE, ISE, ITAE, peak, last index above the
    settling threshold); the loss reads one, yet the adjoint recurrence differentiates the
    update of all five at every step. The sums and the trapezoid end corrections are
    written exactly as in `StudyProblem`, so the value is the same number (tested against
    `run_study`). A sample is flagged (NaN) when its own metric is not finite.
    Its adjoint is correspondingly cheaper than that of `StudyProblem` (one accumulator
    instead of five per step).
    """

    study: StudyProblem
    metric: str = eqx.field(static=True)
    keep: int = eqx.field(static=True, default=0)
    # `update` adds a function of the step's outputs to the accumulator: the adjoint of
    # `fojax.studies._adjoint.split_recurrence_reduce` takes the outputs' cotangents of a
    # whole checkpoint segment at once
    additive = True

    @property
    def computed(self) -> tuple[str, ...]:
        return (self.metric,)

    def joint(self, p):
        return self.study.joint(p)

    def _integrand(self, o):
        return jnp.abs(o) if self.metric == "iae" else o * o

    def init(self, o0):
        return jnp.zeros_like(o0)

    def update(self, acc, o, k, ts):
        return acc + self._integrand(o)

    def final(self, acc, o0, o_end, ts, h, ok):
        m = h * (acc + 0.5 * self._integrand(o0) - 0.5 * self._integrand(o_end))  # (K, b)
        good = ok & jnp.all(jnp.isfinite(m), axis=0)
        return jnp.where(good[None], m, jnp.nan), good


#: Samples stepped together by the differentiable kernel (`sample_metrics_traced`): every
#: block of this fixed width runs the whole time loop (and its adjoint) before the next,
#: so its per-sample matrices (``Φ``, ``G``: ``8 (N² + K N) · 32`` bytes, 92 KB at
#: ``N = 19``) stay in the L2 cache instead of being streamed from memory at every step.
#: Wider blocks spill out of the cache and cost several times more per sample and step;
#: narrower ones gain nothing. The width is fixed (not derived from ``B`` or the number of devices), so each
#: sample's arithmetic, and the loss's bits, do not depend on how samples are split.
DIFF_BLOCK = 32


def blocked(fn, p, width: int):
    """``fn`` over blocks of ``width`` samples (leading axis of every leaf of ``p``) in a
    `jax.lax.map`; the sample axis is padded with copies of sample 0 (their outputs are
    dropped, so their cotangents are zero) and the outputs are concatenated, samples
    first. Traceable."""
    b = int(jax.tree.leaves(p)[0].shape[0])
    nb = -(-b // width)
    pad = nb * width - b
    if pad:
        p = jax.tree.map(lambda a: jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])]), p)
    if nb == 1:
        out = fn(p)
    else:
        out = jax.lax.map(fn, jax.tree.map(lambda a: a.reshape((nb, width) + a.shape[1:]), p))
        out = jax.tree.map(lambda a: a.reshape((nb * width,) + a.shape[2:]), out)
    return jax.tree.map(lambda a: a[:b], out)


#: Traces of the differentiable exact study loss (tests prove `study_loss` takes it) and of
#: `StudyProblem.joint` (a repeated `run_study` of the same structure traces nothing).
TRACE_COUNTS: collections.Counter = collections.Counter()


def exact_refusal(study, observers, stepper=None) -> str | None:
    """Why the exact batch kernel cannot run `study` (``None``: it can): the one test of
    `exact_problem` (`run_study`), `study_loss`, `resolve_engine` and `tune`'s device
    check. Decided from the types and shapes of sample 0 (no arrays are computed, so it
    also works on a traced study) and from the grid when it is concrete (`grid_deviation`,
    the one uniform-grid test; a traced grid is assumed uniform, as `fojax.Auto` does).
    With a `stepper` (`fojax.Auto`, `fojax.Exact`, ...), also refused when none of its
    ``batch_candidates`` is an `fojax.Exact`."""
    if stepper is not None and not any(isinstance(c, Exact) for c in stepper.batch_candidates):
        return f"the stepper {type(stepper).__name__} excludes the exact engine"
    if not all(_structure(_observer_lti, o) is not None for o in observers):
        return "an observer is not LTI"
    if is_concrete(study.ts) and not grid_deviation(study.ts)[0] <= UNIFORM_GRID_RTOL:
        return "the grid is not uniform"
    base, _, _, fault = _unwrap(_structure(_first_plant, study))
    if _structure(_first_lti, study) is None:
        return f"the plant ({type(base).__name__}) is not LTI"
    if not exactly_generated(study.u) or (fault is not None and not exactly_generated(fault)):
        return "a signal has no exact exosystem"
    return None


def _split_loop(problem, q, h, Phi, w0, G, jv, kon, ts, reps=1, q_rep=None):
    r"""The time loop of one block of `sample_metrics_traced`: the joint state
    ``w = [x (n); ξ (q); v]`` split into the plant part ``p = [x; v]`` and the observers'
    ``ξ`` (`fojax.studies._adjoint.split_recurrence_reduce`).

    The plant part (``Φ_pp``, ``p_0``, its jumps) is rebuilt from the joint of the same
    samples with the observers under `jax.lax.stop_gradient` (the plant rows of the joint
    do not involve the observers) and discretised by its own `expm_last`: nothing the
    observers' parameters reach is treated as constant, and differentiating with respect
    to the study's arrays raises `fojax.errors.InputError` (the adjoint has no plant part). ``Φ_pp = e^{A_p h}`` is the plant block of ``e^{\mathcal A h}`` (block
    lower-triangular ``\mathcal A``), equal up to rounding.

    The loss (`LossProblem`) without jumps runs in passes of ``S`` grid steps
    (`fojax.studies._adjoint.pass_recurrence_reduce`, ``S = pass_length(T − 1)``, static);
    with jumps, other reductions, or ``S = 1``, step by step.

    With ``reps > 1`` (`scenario_free` studies, `_block_kernel`'s ``groups``): ``Phi`` and
    ``G`` are given once per group of ``reps`` consecutive samples (representatives
    ``q_rep``), and so are the plant's exponential and the pass matrices; they are
    repeated to the samples only for the time loop."""
    sp = problem.study if isinstance(problem, LossProblem) else problem
    n = sp.E0.shape[0]
    nq = sum(o.state_size for o in sp.observers)
    N = Phi.shape[0]

    def rows(X, axis):  # the plant entries [0, n) ∪ [n + nq, N) along `axis`
        return jnp.concatenate([lax.slice_in_dim(X, 0, n, axis=axis), lax.slice_in_dim(X, n + nq, N, axis=axis)],
                               axis=axis)

    def obs(X, axis):
        return lax.slice_in_dim(X, n, n + nq, axis=axis)

    sg = lambda t: jax.tree.map(lambda x: lax.stop_gradient(x) if eqx.is_array(x) else x, t)  # noqa: E731
    free = eqx.tree_at(lambda pr: pr.observers, sp, sg(sp.observers))

    def plant_of(pk):
        pk = tuple(pk[:2]) + tuple(sg(x) for x in pk[2:])
        Aj, w0p, _, _, jumps = free.joint(pk)
        return rows(rows(Aj, 0), 1), rows(w0p, 0), jumps

    Ap, p0, jumps = jax.vmap(plant_of)(q)  # (b, m, m), (b, m)
    if q_rep is not None:  # the representatives' (the samples' Ap is then dead code)
        Ap = jax.vmap(plant_of)(q_rep)[0]  # (b / reps, m, m)
    expm = lambda M: expm_last(M, max_squarings=DIFF_MAX_SQUARINGS)  # noqa: E731
    Ppp = expm(jnp.moveaxis(h * Ap, 0, -1))
    jvp = None
    if jv is not None:
        # the plant part of e^{A (t_k - t_j)} Δw_j, as `_block_kernel` forms the joint one
        jt, dW = jumps  # (b, J), (b, J, N)
        b_, J = jt.shape
        valid = (kon.T >= 1) & jnp.isfinite(jt)  # kon: -1 where the jump is off the grid's steps
        tau = jnp.where(valid, ts[jnp.clip(kon.T, 0, ts.shape[0] - 1)] - jnp.where(valid, jt, 0.0), 0.0)
        Aps = repeat_groups(Ap, reps, 0)  # each sample's copy
        Mj = (tau[:, :, None, None] * Aps[:, None]).reshape((b_ * J,) + Ap.shape[1:])
        Psi = expm(jnp.moveaxis(Mj, 0, -1))  # (m, m, b J)
        dWp = jnp.moveaxis(rows(dW, 2).reshape(b_ * J, -1), 0, -1)  # (m, b J)
        jvp = jnp.einsum("ijb,jb->ib", Psi, dWp)
        jvp = jnp.moveaxis(jvp.reshape(jvp.shape[0], b_, J), 2, 0)  # (J, m, b)
        jvp = jnp.where(valid.T[:, None, :], jvp, 0.0)
    diff = (obs(obs(Phi, 0), 1), rows(obs(Phi, 0), 1), obs(G, 1), rows(G, 1), obs(w0, 0),
            None if jv is None else obs(jv, 1), ts)
    S = pass_length(ts.shape[0] - 1) if isinstance(problem, LossProblem) and jv is None else 1
    if S > 1:  # the loss without jumps: S steps per pass (static choice, one compiled path)
        acc, p_end, xi_end = pass_recurrence_reduce(diff, (Ppp, p0.T, None), problem, S, reps=reps)
    else:
        Poo, Pop, Go, Gp = (repeat_groups(X, reps, -1) for X in diff[:4])
        acc, p_end, xi_end = split_recurrence_reduce((Poo, Pop, Go, Gp) + diff[4:],
                                                     (repeat_groups(Ppp, reps, -1), p0.T, jvp), problem, kon)
    w_end = jnp.concatenate([p_end[:n], xi_end, p_end[n:]], axis=0)
    return acc, w_end


def sample_metrics_traced(study, observers, settle_tol, mesh=None, metric: str | None = None):
    """Per-sample metrics ``(5, K, B)`` and success ``(B,)`` of every sample, exactly and
    reverse-differentiably with respect to the observers (the time loop split into the
    plant and the observers, `_split_loop`; blocks of `DIFF_BLOCK` samples, `expm_last` with a
    squaring budget and its hand-written reverse mode, the masked full-size slow coordinates so that nothing
    needs ``rank E`` on the host). With `metric` (``"iae"`` or ``"ise"``) only that metric
    is accumulated (`LossProblem`) and the result is ``(1, K, B)``.

    When the scenarios do not change the joint matrix (`scenario_free`: initial states,
    fault sizes and onsets) and there are 2 to `DIFF_BLOCK` of them, the ``Nf`` scenarios
    of an uncertainty sample are one group: their joint exponential, its reverse pass, the
    plant's exponential and the pass matrices are formed once per group, a block holds
    ``max(2, DIFF_BLOCK // Nf)`` whole groups, and samples are spread over devices by whole groups
    (so each group's sum of cotangents is the same on any split); this roughly halves the
    value-and-gradient of a study with many scenarios per uncertainty sample
    (``benchmarks/tuning_step.py``); values and gradients agree with the per-sample
    computation to rounding (tested). With a `mesh`
    (`fojax.studies._sharding.sample_mesh`) the samples are cut over its devices, possibly
    of several processes; the values and their gradient are bit-identical to one device
    (`fojax.studies._sharding`). Traceable."""
    TRACE_COUNTS["study_loss_exact"] += 1
    E0 = _unwrap(study.sample(0, 0)[0])[0].E
    split = svd_split(E0)
    problem = StudyProblem(study, tuple(observers), split, E0, jnp.asarray(settle_tol, dtype=jnp.float64), None)
    if metric is not None:
        problem = LossProblem(problem, metric)
    ts = study.ts
    h = (ts[-1] - ts[0]) / (ts.shape[0] - 1)
    Nu, Nf = study.num_uncertainty, study.num_scenarios
    reps = Nf if 2 <= Nf <= DIFF_BLOCK and scenario_free(problem, observers) else 1

    def block(shared, q):
        problem, ts, h = shared
        qs, groups = q, None
        if reps > 1:  # q: one row per uncertainty sample; its Nf scenarios are the block's samples
            g = q[0].shape[0]
            qs = (jnp.repeat(q[0], reps), jnp.tile(jnp.arange(reps, dtype=q[1].dtype), g),
                  jax.tree.map(lambda a: repeat_groups(a, reps, 0) if eqx.is_inexact_array(a) else jnp.repeat(a, reps, axis=0), q[2]))
            groups = (q, reps)
        mets, ok = _block_kernel(problem, qs, h, ts, None, differentiable=True, groups=groups,
                                 time_loop=lambda pr, Phi, w0, G, jv, kon, ts, r: _split_loop(
                                     pr, qs, h, Phi, w0, G, jv, kon, ts, r, None if groups is None else q))
        mets = mets[None] if mets.ndim == 2 else mets  # LossProblem: (K, b) -> (1, K, b)
        mets = jnp.moveaxis(mets, -1, 0)  # samples first
        if reps > 1:  # (g, Nf, ...): the block's rows are its uncertainty samples
            mets, ok = mets.reshape((-1, reps) + mets.shape[1:]), ok.reshape(-1, reps)
        return mets, ok

    def local(shared, p):
        # at least two groups per block: with one, XLA lowers the groups' batch-of-one
        # products as plain matrix products, whose bits then depend on the process
        # layout (the tuning gradient on 2 processes × 2 devices would differ from one
        # process in the last bits)
        return blocked(lambda q: block(shared, q), p, DIFF_BLOCK if reps == 1 else max(2, DIFF_BLOCK // reps))

    if reps == 1:
        k = jnp.arange(study.num_samples)
        iu, jf = k // Nf, k % Nf
    else:  # one row per uncertainty sample (its scenarios stay on one device, in one block)
        iu, jf = jnp.arange(Nu), jnp.zeros((Nu,), int)
    mets, ok = per_sample(local, (problem, ts, h), tuple(observers), iu, jf, mesh)
    if reps > 1:
        mets, ok = mets.reshape((Nu * Nf,) + mets.shape[2:]), ok.reshape(Nu * Nf)
    return jnp.moveaxis(mets, 0, -1), ok


def scenario_free(problem, observers) -> bool:
    r"""Whether a sample's joint matrix, output map and validity (`StudyProblem.joint`'s
    ``Aj``, ``G``, ``ok``) do not depend on its scenario index ``j``, only on its
    uncertainty index ``i``: then the ``Nf`` scenarios of one uncertainty sample share one
    joint exponential (`sample_metrics_traced` forms it once per uncertainty sample).

    Decided by a forward walk of the jaxpr of ``(i, j) ↦ (Aj, G, ok)``: a variable depends
    on ``j`` when an equation that produces it reads one that does (an equation with a
    sub-program counts as reading all its inputs for all its outputs), so the answer errs
    towards "depends" and never wrongly says "free". Typically free: scenarios that set the
    initial state (`fojax.studies.constant_faults`, `initial_conditions`) or a step/ramp
    fault's onset and size (those enter as the exosystem's state and its jumps); not free:
    e.g. a sine fault whose frequency differs by scenario. Traces ``joint`` once (no
    arrays are computed)."""
    obs = tuple(observers)
    saved = TRACE_COUNTS["StudyProblem.joint"]
    try:
        def matrices(i, j):  # (Aj, G, ok), from one trace of the joint
            Aj, _, G, ok, _ = problem.joint((i, j, obs))
            return Aj, G, ok

        jaxpr = jax.make_jaxpr(matrices)(jnp.zeros((), int), jnp.zeros((), int))
    finally:
        TRACE_COUNTS["StudyProblem.joint"] = saved
    dep = {jaxpr.jaxpr.invars[1]}
    for eqn in jaxpr.jaxpr.eqns:
        if any(not isinstance(v, Literal) and v in dep for v in eqn.invars):
            dep.update(eqn.outvars)
    return not any(not isinstance(v, Literal) and v in dep for v in jaxpr.jaxpr.outvars)
