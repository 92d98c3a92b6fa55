r"""Gradient tuning of functional-observer gains under uncertainty (optax), certified at every iterate.

**One entry point** for LTI and Takagi–Sugeno designs: ``tune(design, study,
parameterization=...)``. The parameterization is an object of
`fojax.design.AbstractParameterization` (``SteinDisk`` for LTI designs and
``CommonCertificate`` for T-S designs by default, or ``FixedCertificateDisk``); the
strings ``"direct"`` (= ``SteinDisk``), ``"disk"`` (= ``FixedCertificateDisk``) and
``"common_certificate"`` are accepted. Every value of the parameters satisfies
conditions a.–d. by construction; a step whose candidate has margin ≤ `min_margin` is
*backtracked* (the update halved up to `max_backtracks` times, the candidates evaluated
in turn on the host by the parameterization's compiled margin; then the halvings of the update
without its outward component), and if no fraction is admissible the iterate is rejected.
Every accepted iterate is certified on the host in float64 (`certify`: residuals,
eigenvalues, region LMI at the certificate); an iterate that fails is rejected, never
returned. The returned design is certified again.

**Live parameters and the optimizer's coordinates** (``precondition=``). Before the first
step `AbstractParameterization.live` computes the Jacobian of the observer's response
$(u, y)\mapsto\hat z$ with respect to the free parameters at the starting design, $J =
U\Sigma V^\top$, and its rank $r$ (the number of *live* directions; the others cannot
reach $\hat z$). The optimizer moves $\xi$ with $\theta = \theta_0 + B\xi$:

- ``"live"`` (default): $B$ = the identity with the parameters that are dead *by
  themselves* (zero Jacobian column) frozen; Adam then acts as on the raw parameters.
- ``"project"``: $B = V_rV_r^\top$ (every dead direction projected out).
- ``"whiten"``: $B = V_r\,\mathrm{diag}(1/\max(\sigma_i, 0.1\,\sigma_1))$: one unit of each
  coordinate moves the response comparably, whatever the scaling of the plant's states
  and equations (``tests/test_parameterization.py``: the hand example with rows and states
  rescaled by 1e-3…1e3 tunes to the same held-out IAE as the original (within 5 %); with ``"none"``
  the rescaled twin barely moves). Its step size differs from the raw parameters', so it
  needs its own learning rate.
- ``"none"``: the raw parameters (the behaviour before this option).

Which default: whitening makes the *steps* unit-free, but a raw start is not (``default_R``
and the LMI solution depend on the units). **Unit-free start:** design with
``design_functional_observer(..., balance=True)``; its `structure` and parameters are
unit-free, so a model and its rescaled twin start from the same observer in the same
coordinates, and ``"live"`` then tunes both to the same held-out IAE (the LC-filter
benchmark ``benchmarks/tuning_circuit.py``, results in
``benchmarks/results/tuning_circuit_latest.json``, compares the modes on the model and its
twin). A tuned ``balance=True`` design keeps ``T`` in the model's units and is re-verified
in both frames. ``"live"`` is the default.

In every mode the count is reported (`TuneResult.live_parameters`, the design's
``solver["tuning"]``).

**Loss.** The batched mean (or `quantile`) of the IAE/ISE of $\hat z - z$ over the training
study (`fojax.studies.study_loss`), plus ``barrier · parameterization.barrier(params)``,
plus the user's `extra_loss`, plus the built-in `robustness` terms (`fojax.tuning.H2Term`,
`fojax.tuning.HinfTerm`: the H2 norm and a smooth H∞ surrogate of the iterate's error system from
the disturbance/noise channels, `fojax.tuning._robustness`). Loss, gradient and the optax update
form one `equinox.filter_jit` function, compiled once
(``TRACE_COUNTS["tune_step"]``; held-out evaluation ``"evaluate"``).

**Checkpoints.** ``checkpoint=path`` writes, every `checkpoint_every` steps, the
optimizer's coordinates, its state, the step, the PRNG key and the history (``path.npz`` +
``path.json``, each written atomically; a pair that disagrees is refused). ``resume=True``
continues from it; the result equals an uninterrupted run. With `devices` spanning
several processes only process 0 writes and reads it (the others receive its bytes).
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import os
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._background import in_background
from .._errors import InputError, removed_keywords
from ..design import (
    AbstractParameterization,
    CommonCertificate,
    error_norms,
    FixedCertificateDisk,
    LiveParameters,
    SteinDisk,
    TakagiSugenoObserverDesign,
    unflatten,
)
from ..simulation import resolve_stepper
from ..studies import (
    check_same_on_every_process,
    distributed_errors,
    exact_refusal,
    replicate,
    resolve_engine,
    SimConfig,
    spans_processes,
    Study,
    study_loss,
)
from ._loop import backtracked_update, check_extra_loss, run_loop
from ._optimizer import shared_optimizer, step_optimizer, transformation
from ._robustness import robustness_terms


#: Number of traces of the jitted tuning step and of the held-out evaluation.
TRACE_COUNTS: collections.Counter = collections.Counter()

_NAMES = {"direct": SteinDisk, "stein": SteinDisk, "disk": FixedCertificateDisk,
          "common_certificate": CommonCertificate, "takagi_sugeno": CommonCertificate}
_DEFAULT_BARRIER = {SteinDisk: 1e-3, FixedCertificateDisk: 0.0, CommonCertificate: 1e-4}


def make_parameterization(design, parameterization=None, region=None, *, tune_Z=None) -> AbstractParameterization:
    """The parameterization object `tune` uses for `design` (host).

    `parameterization`: ``None`` (``SteinDisk`` for LTI designs, ``CommonCertificate`` for
    T-S designs), a name (``"direct"``, ``"disk"``, ``"common_certificate"``), a class, or
    an `AbstractParameterization` instance (returned as is).
    """
    if isinstance(parameterization, AbstractParameterization):
        return parameterization
    if parameterization is None:
        cls = CommonCertificate if isinstance(design, TakagiSugenoObserverDesign) else SteinDisk
    elif isinstance(parameterization, str):
        if parameterization not in _NAMES:
            raise InputError(f"parameterization must be one of {sorted(_NAMES)} or a "
                             f"fojax.design.AbstractParameterization; got {parameterization!r}.")
        cls = _NAMES[parameterization]
    elif isinstance(parameterization, type) and issubclass(parameterization, AbstractParameterization):
        cls = parameterization
    else:
        raise InputError(f"parameterization must be a name or a fojax.design.AbstractParameterization; got "
                         f"{type(parameterization).__name__}.")
    return cls(design, region, **({} if tune_Z is None else {"tune_Z": bool(tune_Z)}))


def initial_parameters(design, region=None, *, tune_Z: bool | None = None, parameterization=None):
    """``(parameterization, params)`` reproducing `design`'s observer exactly (host)."""
    par = make_parameterization(design, parameterization, region, tune_Z=tune_Z)
    return par, par.init(design)


def observer_from_parameters(parameterization: AbstractParameterization, params):
    """``(observer, margin)`` for the parameters (traceable)."""
    return parameterization.observer(params), parameterization.margin(params)


class Coordinates(eqx.Module):
    r"""The optimizer's coordinates $\xi$: $\theta = \theta_0 + B\xi$ (``B`` = $V_r\Sigma_r^{-1}$,
    $V_r$ or $I$), flattened in `LiveParameters.names` order. Data are leaves."""

    theta0: jax.Array
    B: jax.Array
    names: tuple = eqx.field(static=True)

    def params(self, xi):
        return unflatten(self.names, self.theta0 + self.B @ xi["xi"])


#: whitening floor: a live direction with singular value s moves by 1/max(s, WHITEN_FLOOR s_max)
WHITEN_FLOOR = 0.1


def coordinates(params, live: LiveParameters, precondition: str) -> Coordinates:
    """The optimizer's coordinates for `precondition` (module docstring; host)."""
    if precondition not in ("live", "project", "whiten", "none"):
        raise InputError(f"precondition must be 'live', 'project', 'whiten' or 'none', got {precondition!r}.")
    theta0 = jnp.concatenate([jnp.ravel(params[k]) for k, _ in live.names])
    if precondition == "none":
        B = np.eye(live.total)
    elif precondition == "live":  # raw coordinates; every parameter that is dead by itself frozen
        B = np.diag(live.live_mask().astype(float))
    elif precondition == "project":  # raw coordinates, every dead direction projected out
        B = live.basis @ live.basis.T
    else:
        sv = live.singular_values[: live.live]
        B = live.basis / np.maximum(sv, WHITEN_FLOOR * sv[0])[None, :] if live.live else live.basis
    return Coordinates(theta0, jnp.asarray(B), live.names)


@dataclasses.dataclass
class TuneResult:
    """Result of `tune`.

    Attributes:
        design: the tuned, verified design (same structure and region as the LMI design;
            ``solver["tuning"]`` holds the run's options and the live-parameter count).
        params: the parameterization's parameters of the returned design (e.g. ``Z, Y1, ...``
            for ``SteinDisk``, ``Theta, Y3[, Z]`` for ``FixedCertificateDisk``).
        history: dict of lists per step: ``step, train_loss, heldout_loss`` (``nan`` when
            not evaluated), ``margin``, ``accepted``, ``backtracks``, ``max_real_eig``.
        initial_heldout, final_heldout: held-out loss of the LMI design and of the result.
        live_parameters: how many free parameters can reach $\\hat z$ (`LiveParameters`).
        parameterization: the `fojax.design.AbstractParameterization` used (its
            ``certify(params)`` rebuilds `design`).
        robustness: when the disturbance/noise channels are known (a `robustness` term, or an
            ``objective="hinf"``/``"h2"`` starting design): ``{"terms": [...], "initial": {...},
            "final": {...}}``, the norms of the starting and the tuned design's error system
            (``hinf_norm`` and ``peak_frequency`` by SLICOT AB13DD; ``gamma``: a certified bound
            ≥ ‖T‖∞, 1e-4 to 1e-2 above it, from the bounded-real Riccati equation and re-checked by the
            H∞ designs' float64 BRL test, ``None`` if that fails; ``h2_norm`` by SciPy's
            Lyapunov solver, ``inf`` with a feedthrough; `fojax.design._hinf.error_norms`);
            ``None`` otherwise.
    """

    design: object
    params: dict
    history: dict
    initial_heldout: float | None
    final_heldout: float | None
    live_parameters: LiveParameters | None = None
    parameterization: AbstractParameterization | None = None
    robustness: dict | None = None


def _loss_fn(xi, coords, par, study, loss, quantile, weights, cfg, barrier, extra_loss, terms=()):
    params = coords.params(xi)
    obs = par.observer(params)
    value = study_loss(study, obs, loss=loss, quantile=quantile, weights=weights, cfg=cfg)
    value = value + barrier * par.barrier(params)
    if extra_loss is not None:
        value = value + extra_loss(obs, par.design_params(params))
    for term in terms:  # built-in robustness terms (fojax.tuning._robustness)
        value = value + term(par.structure, par.design_params(params))
    return value


@eqx.filter_jit
def _step(xi, opt_state, coords, par, study, optimizer, loss, quantile, weights, cfg, barrier, extra_loss, terms=()):
    """The loss, its gradient and the optimizer's update (the step rule that turns the update
    into the next iterate runs on the host, `fojax.tuning._loop.backtracked_update`)."""
    TRACE_COUNTS["tune_step"] += 1
    value, grads = eqx.filter_value_and_grad(_loss_fn)(xi, coords, par, study, loss, quantile, weights, cfg,
                                                       barrier, extra_loss, terms)
    updates, new_state = transformation(optimizer).update(grads, opt_state, xi)
    return value, updates, new_state


@eqx.filter_jit
def _margin_grad(xi, coords, par):
    """The gradient of the margin in the optimizer's coordinates: the step rule's tangential
    candidates (compiled on the first step that needs them)."""
    return jax.grad(lambda x: par.margin(coords.params(x)))(xi)


@eqx.filter_jit
def _evaluate(params, par, study, loss, quantile, weights, cfg):
    TRACE_COUNTS["evaluate"] += 1
    return study_loss(study, par.observer(params), loss=loss, quantile=quantile, weights=weights, cfg=cfg)


@removed_keywords
def tune(
    design,
    train_study: Study,
    *,
    heldout: Study | None = None,
    steps: int = 100,
    optimizer: optax.GradientTransformation | None = None,
    loss: str = "iae",
    quantile: float | None = None,
    weights=None,
    extra_loss: Callable | None = None,
    robustness=None,
    region=None,
    parameterization=None,
    tune_Z: bool | None = None,
    barrier: float | None = None,
    precondition: str = "live",
    min_margin: float = 1e-6,
    max_backtracks: int = 8,
    eval_every: int = 1,
    key=None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 1,
    resume: bool = False,
    stepper=None,
    callback: Callable | None = None,
    quiet: bool = False,
    devices=None,
) -> TuneResult:
    r"""Tune the free parameters of a functional-observer design by gradient descent.

    See the module docstring for the parameterizations, the whitened coordinates,
    backtracking, host certification of every iterate, and checkpoints.

    **Arguments:**

    - `design`: an LMI design: a `fojax.design.FunctionalObserverDesign` (disk region) or a
      `fojax.design.TakagiSugenoObserverDesign`, ``kind="generalized"`` or
      ``"proportional"``.
    - `train_study`: a `fojax.studies.Study` whose signals the observer estimates.
    - `heldout`: a study of samples never used for training (its loss is reported).
    - `steps`: total number of optimizer steps (including those of a resumed run).
    - `optimizer`: an optax transformation (default
      ``shared_optimizer("adam", learning_rate=1e-2)``); the jitted step compiles once per
      optax object, or, for `fojax.tuning.shared_optimizer`'s, once whatever the values of
      its float hyperparameters (a learning-rate sweep compiles once).
    - `loss`: ``"iae"`` or ``"ise"`` of $\hat z - z$ (mean over signals, or `weights`).
      IAE weighs an error's sign, not its size, and can buy a lower integral with overshoot:
      on `fojax study`'s §3.3.7 benchmark (60 steps, 512 evaluation samples of other seeds)
      the IAE-tuned observer had IAE −1.7 % and mean peak errors +154 % against its LMI
      design, the ISE-tuned one −9.8 % and −30 %; `fojax study` therefore trains on ISE by
      default (``[tuning] loss``). This function keeps ``"iae"`` as its default, so that
      earlier scripts and the recorded benchmarks reproduce. `quantile`: use this quantile over samples instead of the mean (a number in [0, 1],
      given to the compiled step as data: a new level does not compile it again).
    - `extra_loss`: user terms added to the training loss, ``extra_loss(observer,
      design_params) -> scalar`` (`design_params`: ``Z, Y1, Y2, Y3, J, G``); a pure JAX
      function. The held-out loss is the study loss alone.
    - `robustness`: built-in robustness terms added to the training loss, a
      `fojax.tuning.H2Term` (the exact ‖T‖₂² of the iterate's error system from
      $d = [w;\nu]$ to $\hat z - z$), a `fojax.tuning.HinfTerm` (a smooth surrogate of ‖T‖∞
      on a frequency grid, not a bound), or a list of them, e.g.
      ``robustness=fojax.tuning.H2Term(weight=0.1)``; the channels default to the starting
      ``objective="hinf"``/``"h2"`` design's (`fojax.tuning._robustness`). Linear designs
      only. Whenever the channels are known (given, or from the starting design's
      certificate) the result reports the tuned design's ‖T‖∞ (SLICOT AB13DD), a certified
      γ ≥ ‖T‖∞ (Riccati) and ‖T‖₂ (SciPy) in `TuneResult.robustness` and
      ``solver["tuning"]["robustness"]``.
    - `region`: the region to stay in (default: the design's region).
    - `parameterization`: an `fojax.design.AbstractParameterization` (instance or class) or
      ``"direct"`` / ``"disk"`` / ``"common_certificate"``; default ``SteinDisk`` (LTI) or
      ``CommonCertificate`` (T-S).
    - `tune_Z`: move ``Z`` too (default: the parameterization's).
    - `barrier`: weight of the parameterization's barrier (default 1e-3 for ``SteinDisk``,
      1e-4 for ``CommonCertificate``, 0 for ``FixedCertificateDisk``). With ``barrier=0`` the
      iterate can reach the region's boundary; the step rule then slides along it
      (`fojax.tuning._loop.backtracked_update`), so steps are not rejected at the boundary
      (``benchmarks/tuning_circuit.py`` compares both settings).
    - `precondition`: ``"live"`` (default), ``"project"``, ``"whiten"`` or ``"none"`` (module docstring).
    - `min_margin`, `max_backtracks`: acceptance rule of a step (backtracking).
    - `eval_every`: held-out evaluation period (steps).
    - `key`: PRNG key stored with the checkpoint (reserved for stochastic training).
    - `checkpoint`, `checkpoint_every`, `resume`: see the module docstring.
    - `stepper`: how the study's samples are stepped (`fojax.Auto()` by default,
      `fojax.Exact()`, `fojax.Exponential(...)`, `fojax.Diffrax(...)`; see
      `fojax.studies.study_loss`). A time-varying affine study (δ(t)) trains on the
      exponential engine: its schedule is decided on the host before the first step
      (`fojax.studies.resolve_engine`, with the starting observer).
    - `callback`: called as ``callback(step, record)`` after every step; ``record`` is the
      step's history entry plus ``params`` (the current, accepted parameters).
    - `quiet`: no progress bar (by default one on stderr, as `fojax.run_study` shows; in a
      run over several processes only process 0's).
    - `devices`: spread the training samples over these devices (e.g. ``jax.devices()``
      after `jax.distributed.initialize`: every process's devices; each process computes
      its share of the loss and gradient). The iterates are bit-identical to the default
      (``None``: one device), see `fojax.studies` (its multi-process helpers). Several
      devices need a training study on the exact engine (`fojax.studies.exact_refusal` is
      None: LTI samples with known signals); any other (Takagi–Sugeno observers, a
      time-varying δ(t)) raises `fojax.errors.InputError`, because the diffrax path's reverse mode
      fails inside `jax.shard_map` (equinox 0.13 compares sharding metadata when it calls a
      closure-converted loop body: patrick-kidger/diffrax#765). Every process runs the same
      `tune` call (checked; `fojax.errors.DistributedError` otherwise or when another dies).
      With `checkpoint`, only process 0 writes it (at its `checkpoint` path), and with
      `resume` every process continues from process 0's checkpoint (sent to the others:
      no file system shared by the hosts is needed); the other processes' paths are
      neither written nor read.

    **Returns:** a `TuneResult`.

    **Raises:** `fojax.errors.InputError` (bad options, a design or region the parameterization
    cannot take); `fojax.errors.DesignVerificationError` if the final design fails its float64
    verification (it cannot, as every accepted iterate passed the same check).
    """
    if getattr(design, "dt", None) is not None:
        raise InputError(f"fojax.tune tunes continuous-time designs; this design is discrete-time (dt = {design.dt:g}), "
                         "and its parameterizations build continuous observers. Use the verified design as it is.")
    if loss not in ("iae", "ise"):
        raise InputError(f"loss must be 'iae' or 'ise', got {loss!r}.")
    q_level = _quantile_level(quantile)  # data of the compiled programs
    quantile = None if q_level is None else float(q_level)
    terms, channels = robustness_terms(robustness, design)
    par = make_parameterization(design, parameterization, region, tune_Z=tune_Z)
    params0 = par.init(design)
    out_size = design.observer.output_size
    if train_study.num_signals != out_size:
        raise InputError(
            f"the study has {train_study.num_signals} signals but the observer estimates "
            f"{out_size}; build the study with the design's L."
        )
    if extra_loss is not None:
        check_extra_loss(extra_loss, par.observer(params0), par.design_params(params0))
    barrier = _DEFAULT_BARRIER.get(type(par), 0.0) if barrier is None else float(barrier)
    optimizer = shared_optimizer("adam", learning_rate=1e-2) if optimizer is None else optimizer
    key = jax.random.PRNGKey(0) if key is None else key
    cfg = SimConfig(stepper=resolve_stepper(stepper, who="tune"),
                    devices=None if devices is None else tuple(devices))
    local = devices is None or not spans_processes(devices)
    if not local:
        check_same_on_every_process((params0, train_study, heldout), "tune")
    w = None if weights is None else jnp.asarray(weights, dtype=jnp.float64)
    path = None if checkpoint is None else os.fspath(checkpoint)

    # the engine of each study decided once on its concrete values (a time-varying study: the
    # exponential engine's schedule, so the jitted step, where the study is traced, runs on it)
    obs0 = par.host_observer(params0)  # NumPy: the traced map would be compiled at start-up
    if cfg.devices is not None and len(cfg.devices) > 1:
        why = exact_refusal(train_study, (obs0,), cfg.stepper)
        if why is not None:
            raise InputError(
                f"tune over {len(cfg.devices)} devices differentiates the study on the exact engine only, and this "
                f"study is not on it ({why}): its loss would run on diffrax, whose reverse mode fails inside "
                "jax.shard_map with equinox 0.13 (closure conversion compares sharding metadata; upstream "
                "patrick-kidger/diffrax#765). Pass devices=None (one device).")
    cfg_train = resolve_engine(train_study, obs0, cfg)
    cfg_held = resolve_engine(heldout, obs0, cfg) if heldout is not None else cfg

    def step_args(coords):
        return (coords, par, train_study, step_optimizer(optimizer), loss, q_level, w, cfg_train, jnp.asarray(barrier),
                extra_loss, terms)

    def start(coords):  # the optimizer's state at xi = 0, on the mesh (where the step's outputs are)
        xi = {"xi": jnp.zeros(coords.B.shape[1])}
        return replicate((xi, optimizer.init(xi)), devices)

    # The step's program depends on shapes only, and for these preconditions B is square
    # (total x total) whatever `live` finds: it compiles on a thread while `live` computes on
    # this one; waited for before the first step.
    compiling_step = None
    if local and precondition in ("live", "project", "none"):
        names = tuple(sorted((k, tuple(np.shape(v))) for k, v in params0.items()))
        total = sum(int(np.prod(shape)) for _, shape in names)
        placeholder = Coordinates(jnp.zeros(total), jnp.zeros((total, total)), names)
        compiling_step = _compile_in_background(_step, (*start(placeholder), *step_args(placeholder)))

    def heldout_args(p):
        # on the mesh, as the iterates are (the starting parameters are not): one compilation
        return replicate(p, devices), par, heldout, loss, q_level, w, cfg_held

    # the held-out program compiles on a thread too (XLA compiles without the GIL); nothing
    # runs until it is done
    compiling = (None if heldout is None or not local
                 else _compile_in_background(_evaluate, heldout_args(params0)))
    live = par.live(params0)
    coords = coordinates(params0, live, precondition)
    xi, opt_state = start(coords)
    if compiling_step is not None:
        concurrent.futures.wait([compiling_step])  # its errors, if any, are the step's: raised by it

    def heldout_loss(p):
        if compiling is not None:
            compiling.result()  # (re-raises its error: the call below would raise it too)
        return float(_evaluate(*heldout_args(p)))

    with distributed_errors("tune"):  # every collective of the run (a dead process: DistributedError)
        xi, history = run_loop(
            xi, opt_state, key, steps=steps, step=_step, step_args=step_args(coords),
            backtrack=lambda x, u: backtracked_update(
                x, u, lambda c: par.host_margin(coords.params(c)), float(min_margin), int(max_backtracks),
                lambda c: _margin_grad(c, coords, par)),
            host_check=lambda x, margin: par.host_check(coords.params(x), margin=margin),
            heldout_loss=(lambda x: heldout_loss(coords.params(x))) if heldout is not None else None,
            eval_every=eval_every, callback=callback, to_params=coords.params, path=path, resume=resume,
            checkpoint_every=checkpoint_every, quiet=quiet, desc="tune",
            devices=devices, place=lambda t: replicate(t, devices),
        )  # fmt: skip
        params = coords.params(xi)
        initial_heldout = heldout_loss(params0) if heldout is not None else None
        final_heldout = heldout_loss(params) if heldout is not None else None
    tuned = par.certify(params)
    robust = None if channels is None else {
        "terms": [term.describe() for term in terms],
        "initial": error_norms(design.structure, design.params, *channels),
        "final": error_norms(tuned.structure, tuned.params, *channels)}
    options = dict(loss=loss, quantile=quantile, steps=steps, tune_Z=tune_Z, barrier=barrier,
                   parameterization=type(par).__name__, precondition=precondition, extra_loss=_name(extra_loss),
                   live_parameters=live.live, free_parameters=live.total,
                   **({} if robust is None else {"robustness": robust}))
    tuned = dataclasses.replace(tuned, solver=dict(design.solver, tuning=options))
    if "balance" in tuned.solver:  # a balance=True start: T in the model's units, verified there too
        dl = np.asarray(tuned.solver["balance"]["row_factors"], dtype=float)
        tuned = dataclasses.replace(tuned, T=np.asarray(tuned.T) * dl[None, :])
        tuned = dataclasses.replace(tuned, report=tuned.verify())
    return TuneResult(design=tuned, params=params, history=history, initial_heldout=initial_heldout,
                      final_heldout=final_heldout, live_parameters=live, parameterization=par, robustness=robust)


def _quantile_level(quantile):
    """`quantile` as a float64 array (data of the jitted step and evaluation: a new level
    reuses their programs), or None; `fojax.errors.InputError` outside [0, 1]."""
    if quantile is None:
        return None
    try:
        q = float(quantile)
    except (TypeError, ValueError):
        q = float("nan")
    if not 0.0 <= q <= 1.0:
        raise InputError(f"quantile must be a number in [0, 1] (e.g. 0.9: the 90 % quantile of the per-sample "
                         f"losses) or None (their mean), got {quantile!r}.")
    return jnp.asarray(q, dtype=jnp.float64)


def _compile_in_background(fn, args) -> concurrent.futures.Future:
    """Trace and compile the `equinox.filter_jit` function `fn` for `args` on a thread
    (``fn.lower(*args).compile()``: the executable JAX's caches give the later call
    ``fn(*args)``); a future of it (`fojax._background.in_background`). Only compiles:
    executing two programs at once on the same devices could order their collectives
    differently per device."""
    return in_background(lambda: fn.lower(*args).compile())


def _name(fn) -> str | None:
    """A readable name of a user function, for the design's record of the tuning options."""
    return None if fn is None else getattr(fn, "__qualname__", type(fn).__name__)
