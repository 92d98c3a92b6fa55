r"""The exponential path of `run_study`: time-varying affine samples on the batch kernel.

A study whose samples vary in time only through signals that enter the index-1 plant's
*differential* equations affinely — an `UncertainDescriptorSystem` with a time-varying
$\delta(t)$ (`sinusoidal_delta`, `piecewise_constant_delta`), faults of a `FaultyPlant`,
any known input — is reduced per sample to $\dot w = A_0 w + g_k(t, w)$ with $A_0$ the
joint slow matrix of the nominal loop (sample 0 with every signal at zero) and $g_k$
affine in $w$ and in the signal values (`fojax.simulation._exponential`). It is stepped by
Krogstad's fourth-order exponential Runge–Kutta method (ETDRK4) on the batch kernel
(`run_batched`: chunks, padding, blocks and devices exist once), and the metrics of
`run_study` (IAE, ISE, ITAE, peak, settling time; trapezoid rule on the grid; the error
trajectories for the quantile bands when asked) are accumulated in the time loop by the
same reducer as the exact path (`StudyProblem`), i.e. with the definitions of
`error_metrics`.

**Accuracy and the step.** ETDRK4 has classical order 4 (observed in
``tests/test_study_exponential.py``); $A_0$ is integrated exactly, so the step only resolves
$g$: the signals and the perturbation $\delta(t)\,\Delta A$ acting on the slow state. The
step is the study grid's ``h`` divided by the smallest number of substeps $s$ with
$(h/s)\,\rho \le$ `STEP_RATE` (0.5), $\rho$ the larger of $|\lambda|_{\max}(A_0)$ and
the largest angular frequency of a `fojax.Sine` signal of any sample; over an initial
layer of $\lceil 5/(|\lambda|_{\max} h)\rceil$ grid intervals, where the initial state
excites the fast modes that $g$ couples into, it is `STARTUP_FACTOR` (2) times smaller.
Fixed steps, no error control: the accuracy is a *measured* statement, not a bound.
On the default §3.3.7 study with $\delta(t) = a\sin(\omega t + \varphi)$,
$|a| \le 0.3$, $\omega \le 5$ rad/s, on the 0.01 s grid (one step per interval, two in
the first 140) the largest relative error of IAE, ISE, ITAE and peak over 10 samples is
5.1e-10 against DOP853 at rtol 1e-12, where a `solve_ivp` loop (RK45, rtol 1e-6) is off
by 2.5e-6 (``benchmarks/study_time_varying.py``); with a piecewise-constant δ switching
on the grid, 1.3e-9 against diffrax's Dopri8 at rtol 1e-11; on the §4.1.3 loop of
``tests/test_study_exponential.py`` (grid 0.04 s, four steps per interval) 8.6e-10.

**Jumps.** Signal jumps and kinks (fault onsets, ramp ends, switching times of a
piecewise-constant $\delta$, steps of the input) must lie on the step grid (to within
`BREAKPOINT_RTOL` of a step): the method is fourth order only between them, and a jump
on a step boundary is taken exactly (the last stage reads the left limits, the next
step starts from the right limits). `exponential_problem` checks this for every sample;
otherwise ``"auto"`` keeps the adaptive diffrax path, which places steps at the
breakpoints. Fault onsets drawn at random times (`fault_scenarios` with an `onset`
range) are therefore not on this path.

**Reverse mode.** `study_loss` runs the same engine through `exponential_metrics_traced`:
the same host decisions, the computation traced with respect to the observer, the time
loop in `jax.checkpoint`-ed segments (memory of the backward pass ~√S for S steps). Its
gradient is checked against central finite differences (``tests/test_study_loss.py``).
A traced study (inside `fojax.tune`'s jitted step, where the study is an argument) cannot
be checked there: `fojax.tune` decides on the host, before its first step, with the
starting observer (`exponential_schedule` through `fojax.studies.resolve_engine`) and hands
the step the schedule (static integers), so the study stays data.

**Compile time.** The set-up of the decomposition is compiled once, for the host pre-pass
(`fojax.simulation._exponential_setup.prepare`), which hands the kernel only what it reads; the
kernel holds one ETDRK4 step body; the host passes are compiled without the backend's
optimisation passes (`HOST_PASS_COMPILER_OPTIONS`); the φ-functions of a concrete $A_0$
are SciPy's `expm` on the host (nothing compiled). The first call's CPU goes about
equally to the host passes (set-up of the decomposition, the affine check, breakpoints,
initial checks: tracing and compiling at level 0) and to the kernel (no unrolled time
loop; at optimisation level 0 it would compile sooner but run markedly slower, so it
keeps the default).

**Tuning.** `fojax.tune` runs its step with the study as a traced argument: the host
decisions are taken once before the first step (`exponential_schedule` through
`fojax.studies.resolve_engine`, with the starting observer) and the step receives the
schedule, so the loss and its gradient run on this engine and new study numbers do not
recompile. A pole of the tuned observer faster than the starting loop's is not seen by
that schedule (the parameterization keeps the poles in the design's region).
"""

from __future__ import annotations

import collections
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import FojaxError, InputError
from ..plant import Sine
from ..simulation._driver import _step_size
from ..simulation._exponential import ExponentialProblem, phi_functions
from ..simulation._exponential_setup import (
    _check_structure,
    _full_plan,
    _plant_signals,
    _with_probes,
    check_affine,
    decompose,
    HOST_PASS_COMPILER_OPTIONS,
    kernel_inputs,
    prepare,
    setup_all,
    setup_data,
)
from ..simulation._reduction import host_initial_checks, is_concrete
from ..simulation._save import METRIC_NAMES
from ..simulation._steppers import Exponential, grid_deviation, UNIFORM_GRID_RTOL
from ._exact import blocked, LossProblem, StudyProblem


#: Defaults of `fojax.Exponential` (`step_rate`, `startup_factor`), which sets the schedule.
#: Largest step × rate: the step resolves the fastest mode of the nominal loop
#: (``|λ|max(A0)``) and the fastest `fojax.Sine` signal (``ω``), ``h_step · rate ≤ STEP_RATE``.
STEP_RATE = Exponential().step_rate
#: Over the initial layer the step is this many times smaller.
STARTUP_FACTOR = Exponential().startup_factor
#: A signal breakpoint counts as on the step grid within this fraction of a step (below
#: `fojax.simulation._exponential.SIDE_OFFSET`, the offset of the one-sided signal values).
BREAKPOINT_RTOL = 1e-10
#: Samples per call of the host pre-pass (set-up and plan statistics).
PREPARE_CHUNK = 2048
#: Samples stepped together by the differentiable path (`exponential_metrics_traced`): the
#: blocks run one after another (`fojax.studies._exact.blocked`), so the per-sample data and
#: the backward pass's per-sample cotangents stay in cache (with all samples in one block the
#: cost of a tune step grows much faster than the number of samples).
DIFF_BLOCK = 64
#: Traces of the differentiable exponential study metrics (tests prove `study_loss` takes
#: this path and does not retrace for new observer numbers).
TRACE_COUNTS: collections.Counter = collections.Counter()


class StudyModel(eqx.Module):
    """``(i, j) -> (plant, observers, u)`` of a study (the form the affine check reads)."""

    study: object
    observers: tuple

    def __call__(self, p):
        plant, _ = self.study.sample(p[0], p[1])
        return plant, self.observers, self.study.u


class StudyErrors(eqx.Module):
    """The errors ``ẑ_k − z`` of every observer, from the plant's own output (the
    affine check compares the decomposition's error maps with it)."""

    L: jax.Array
    fault_targets: bool = eqx.field(static=True)

    def __call__(self, plant, observers, t, x, xi, u_t, y):
        z = self.L @ x
        if self.fault_targets:
            z = jnp.concatenate([z, plant.fault(t)])
        if not observers:  # a signal study: z itself
            return z
        parts, off = [], 0
        for o in observers:
            parts.append(o.output(t, xi[off : off + o.state_size], u_t, y) - z)
            off += o.state_size
        return jnp.concatenate(parts)


class StudySetup(eqx.Module):
    r"""Per-sample set-up for `ExponentialProblem`: ``p = (i, j)`` → the decomposition of
    sample ``(i, j)`` with the error maps $e = G w + H v$ per probe as outputs."""

    study: object
    observers: tuple

    def __call__(self, p):
        study, observers = self.study, self.observers
        plant, x0 = study.sample(p[0], p[1])
        Aj, Bj, OM, OF, (Yw, Yv), w0, mask = decompose(plant, observers, x0)
        n, m = plant.n, plant.m
        P = Aj.shape[0]
        X, XV = OM[:, :n], OF[:, :n]  # x = X w + XV v per probe
        L = study.L
        if study.fault_targets:
            # the fault's value at each probe (s = 0, e_1, ...): its coefficients in s
            sigs = _plant_signals(plant)
            ns = sum(sg.size for sg in sigs)
            probes = jnp.concatenate([jnp.zeros((1, ns)), jnp.eye(ns)], axis=0)
            zf = jax.vmap(lambda s: _with_probes(plant, s).fault(study.ts[0]))(probes)  # (P, nf)
            L = jnp.concatenate([L, jnp.zeros((zf.shape[1], n))], axis=0)
        sel_u = jnp.concatenate([jnp.eye(m), jnp.zeros((m, 1))], axis=1)
        Gs, Hs, off = [], [], n
        for o in observers:
            lm = o.linear_matrices()
            s = o.state_size
            Gk = (lm.Dy @ Yw - L @ X).at[:, :, off : off + s].add(lm.C)
            Hk = lm.Dy @ Yv + (lm.Du @ sel_u)[None] - L @ XV
            if study.fault_targets:
                Hk = Hk.at[:, study.L.shape[0] :, m].add(-zf)
            Gs.append(Gk)
            Hs.append(jnp.broadcast_to(Hk, (P,) + Hk.shape[1:]))
            off += s
        if not observers:  # a signal study: z = L x (+ the fault) itself
            Hz = jnp.broadcast_to(L @ XV, (P,) + L.shape[:1] + XV.shape[2:])
            if study.fault_targets:
                Hz = Hz.at[:, study.L.shape[0] :, m].add(zf)
            Gs, Hs = [L @ X], [Hz]
        data = setup_data(Aj, Bj, jnp.concatenate(Gs, axis=1), jnp.concatenate(Hs, axis=1), w0, mask)
        return data, (_plant_signals(plant), study.u)

    def signals(self, p):
        plant, _ = self.study.sample(p[0], p[1])
        return _plant_signals(plant), self.study.u


@eqx.filter_jit(compiler_options=HOST_PASS_COMPILER_OPTIONS)
def _breakpoints(study, iu, jf):
    """Every sample's signal breakpoints (plant signals and input) ``(B, k)`` and the
    angular frequencies of its `fojax.Sine` signals ``(B, k')``."""

    def one(i, j):
        plant, _ = study.sample(i, j)
        sigs = _plant_signals(plant) + (study.u,)
        sines = [leaf for leaf in jax.tree.leaves(sigs, is_leaf=lambda x: isinstance(x, Sine))
                 if isinstance(leaf, Sine)]
        return (jnp.concatenate([sg.breakpoints().reshape(-1) for sg in sigs]),
                jnp.concatenate([jnp.zeros((0,))] + [sn.omega.reshape(-1) for sn in sines]))

    return jax.vmap(one)(iu, jf)


def _off_step_grid(bps: np.ndarray, t0: float, t1: float, h_step: float) -> np.ndarray:
    b = bps[np.isfinite(bps) & (bps > t0) & (bps < t1)]
    k = (b - t0) / h_step
    return b[np.abs(k - np.round(k)) > BREAKPOINT_RTOL]


def exponential_problem(study, observers, settle_tol: float, keep: bool, strict: bool,
                        options: Exponential = Exponential(), kinds: tuple[str, ...] = METRIC_NAMES):
    """Host: ``((problem, None, (iu, jf)), None)`` for `run_batched`, or ``(None,
    reason)`` when the study does not qualify (with `strict`: raise `fojax.errors.InputError`).
    `options`: the `fojax.Exponential` stepper (its step schedule); `kinds`: the metrics
    to accumulate (`fojax.studies._exact.StudyProblem.kinds`)."""

    def refuse(reason):
        if strict:
            raise InputError(
                f"stepper {options!r} cannot run this study: {reason}. Use "
                "stepper=Auto() (which then takes the adaptive diffrax path) or Diffrax()."
            )
        return None, reason

    if not all(o.linear_matrices() is not None for o in observers):
        return refuse("an observer is not LTI")
    if not is_concrete(study):
        return refuse("the study's arrays are traced")
    t = np.asarray(study.ts)
    T = t.shape[0]
    if not (T >= 2 and grid_deviation(t)[0] <= UNIFORM_GRID_RTOL):
        return refuse("the grid is not uniform")
    h = (t[-1] - t[0]) / (T - 1)
    plant0, x00 = study.sample(0, 0)
    try:
        _check_structure(plant0, tuple(observers))
    except InputError as err:
        return refuse(str(err))
    iu = np.arange(study.num_samples) // study.num_scenarios
    jf = np.arange(study.num_samples) % study.num_scenarios
    idx = (jnp.asarray(iu), jnp.asarray(jf))
    bps, omega = (np.asarray(a) for a in _breakpoints(study, *idx))
    try:
        host_initial_checks(plant0, x00, study.ts[0], study.u, strict=False, tol=0.0)
        setup = StudySetup(study, tuple(observers))
        first = (iu[0], jf[0])  # NumPy scalars: no eager device op
        A0, plan, per, shared, data0 = prepare(setup, idx, first, PREPARE_CHUNK)
        ns = sum(sg.size for sg in _plant_signals(plant0))
        check_affine(StudyModel(study, tuple(observers)), first, data0, A0,
                     StudyErrors(study.L, study.fault_targets), float(t[0]), float(t[-1]), ns, plant0.m,
                     who="run_study(stepper=Exponential())")
    except FojaxError as err:  # refused by a check: "auto" keeps the adaptive path
        if strict:
            raise
        return None, f"{type(err).__name__}: {err}"
    kept = np.asarray(plan.keep, dtype=int)
    A0k = A0[kept][:, kept]
    lam = float(np.max(np.abs(np.linalg.eigvals(np.asarray(A0k))), initial=0.0)) if kept.size else 0.0
    rate = max(lam, float(np.max(np.abs(omega), initial=0.0)))
    substeps, sub_start = options.schedule(rate, h)  # default: STEP_RATE, STARTUP_FACTOR
    n_start = min(T - 1, math.ceil(5.0 / (lam * h))) if lam > 0 else 0
    off = _off_step_grid(bps, float(t[0]), float(t[-1]), h / substeps)
    if off.size:
        return refuse(
            f"{off.size} signal breakpoint(s) (jumps or kinks, e.g. at t = {float(off[0]):.6g}) are not on the "
            f"step grid (h / {substeps} = {h / substeps:g}); put fault onsets and switching times on it"
        )
    hj = jnp.asarray(h)
    phis = (phi_functions(A0k, hj / substeps), phi_functions(A0k, hj / sub_start))
    reducer = StudyProblem(study, tuple(observers), None, None, jnp.asarray(float(settle_tol)), None, keep,
                           tuple(kinds))
    problem = ExponentialProblem(setup, reducer, shared, phis, plan, (n_start, sub_start, substeps))
    return (problem, None, (idx, per)), None


def _zero_stand_in(observer):
    """``observer`` with every array leaf replaced by concrete zeros of its shape."""
    return jax.tree.map(lambda a: np.zeros(jnp.shape(a), jnp.result_type(a)) if eqx.is_array(a) else a, observer)


def exponential_schedule(study, observers, settle_tol, options: Exponential = Exponential()):
    """Host: the step schedule ``(n_start, sub_start, substeps)`` (static integers) the
    exponential engine uses for the concrete `study`, or ``None`` when the study does not
    qualify (the rules and checks of `exponential_problem`, taken with the observers when
    they are concrete and otherwise with a zero stand-in of the same structure, see
    `exponential_metrics_traced`). `fojax.studies.resolve_engine` stores it in the
    `SimConfig` with which `fojax.tune` runs its jitted step, where the study is traced."""
    observers = tuple(observers)
    if not is_concrete(study):
        return None
    host_obs = observers if is_concrete(observers) else tuple(_zero_stand_in(o) for o in observers)
    with jax.ensure_compile_time_eval():  # host passes on concrete data, also inside an outer jit
        prepared, _ = exponential_problem(study, host_obs, settle_tol, False, strict=False, options=options)
    return None if prepared is None else tuple(int(k) for k in prepared[0].schedule)


def exponential_metrics_traced(study, observers, settle_tol, options: Exponential = Exponential(),
                               schedule: tuple | None = None, metric: str | None = None):
    r"""Per-sample metrics ``(5, K, B)`` and success ``(B,)`` of a `study` on the
    exponential engine (with `metric`, ``"iae"`` or ``"ise"``, only that one is
    accumulated, `fojax.studies._exact.LossProblem`, and the metrics are ``(1, K, B)``), reverse-differentiable with respect to the `observers` (which may
    be traced, e.g. under `jax.grad`), or ``None`` when the study does not qualify (the
    rules of `exponential_problem`).

    **The host decisions** (qualification, breakpoints on the step grid, the affine check,
    the step schedule) are those of `exponential_problem` (`exponential_schedule`). With
    ``schedule=None`` they are taken now, which needs a concrete `study` (a traced one
    never qualifies), with the observers when they are concrete and otherwise with a
    concrete stand-in of the same structure whose arrays are zeros: the observers are LTI,
    so their part of the field is affine by construction and the check still tests the
    plant; the schedule then sees the plant's nominal slow poles and the signal
    frequencies but not the observer's poles (the observer's poles set the step only when
    they are faster than the plant's; the schedule of a concrete call, `run_study`'s,
    includes them). With a `schedule` (from `exponential_schedule`, taken earlier on the
    host on this study's concrete values, as `fojax.tune` does through
    `fojax.studies.resolve_engine`) nothing is decided here and the study may be traced:
    its numbers are data, so a new study of the same shapes and schedule does not
    recompile.

    **The computation** is traced: the set-up of every sample (`setup_all`), every term
    applied per sample (no plan, as under an outer `jax.jit`), the φ-functions of the
    traced $A_0$ (`phi_functions`: matrix products and fixed-length loops), and all
    samples stepped in blocks of `DIFF_BLOCK` (one after another) by `ExponentialProblem.block_kernel` with
    ``checkpoint=True``: the backward pass recomputes segments of about $\sqrt S$ steps
    (``S`` steps in all), so its memory grows like $\sqrt S$, not $S$. Reverse mode is the
    exact derivative of the discrete scheme (JAX differentiates the ETDRK4 recurrence
    itself). The values equal `run_study`'s exponential engine to round-off when the
    schedules agree.
    """
    TRACE_COUNTS["study_loss_exponential"] += 1
    observers = tuple(observers)
    if schedule is None:
        schedule = exponential_schedule(study, observers, settle_tol, options)
        if schedule is None:
            return None
    schedule = tuple(int(k) for k in schedule)
    n_start, sub_start, substeps = schedule
    iu = np.arange(study.num_samples) // study.num_scenarios
    jf = np.arange(study.num_samples) % study.num_scenarios
    idx = (jnp.asarray(iu), jnp.asarray(jf))
    setup = StudySetup(study, observers)
    data, A0 = setup_all(setup, idx, (iu[0], jf[0]))
    plan = _full_plan(A0.shape[0], data["A"].shape[1])
    per, shared = kernel_inputs(data, plan, jnp)
    _, h, ts = _step_size(study.ts)
    phis = (phi_functions(A0, h / substeps), phi_functions(A0, h / sub_start))
    reducer = StudyProblem(study, observers, None, None, jnp.asarray(float(settle_tol)), None, False)
    if metric is not None:
        reducer = LossProblem(reducer, metric)
    problem = ExponentialProblem(setup, reducer, shared, phis, plan, schedule)

    def block(q):  # one block of samples, batch last -> samples first
        mets, ok = problem.block_kernel(q, h, ts, checkpoint=True)
        return jnp.moveaxis(mets, -1, 0), ok

    mets, ok = blocked(block, (idx, per), DIFF_BLOCK)
    mets = jnp.moveaxis(mets, 0, -1)
    return (mets[None] if mets.ndim == 2 else mets), ok
