r"""Gradient tuning of functional-observer gains under uncertainty (optax), certified at every iterate.

Two parameterizations (``parameterization=``), both keeping conditions a.–d. exact and
every returned iterate inside the named disk $\mathcal Q(\alpha, \tau)$ (default: the
design's region):

**"direct" (default): the free parameters themselves, with a Stein barrier and
rejection.** The parameters are $Z, Y_1, Y_2, Y_3, J, G$ of
`fojax.design.observer_matrices` (``Z`` frozen with ``tune_Z=False``). For the error
dynamics $\mathbb A$, the Stein solution $P$ of
$\bar A^\top P\bar A - P = -I$, $\bar A = (\mathbb A-\alpha I)/\tau$ (Smith doubling,
`stein_certificate`) is $\succ 0$ iff every eigenvalue is in the disk, and is then a
Lyapunov certificate of the disk LMI. The loss gets the barrier
``barrier · log tr P`` (finite inside, $\to\infty$ at the boundary); a step whose
candidate has no positive definite $P$ (margin ``1/λ_max(P)`` ≤ `min_margin`) is
backtracked. *Deviation from the thesis:* the thesis tunes through the explicit
$(\mathcal L, \gamma)$ map with a fixed certificate; with a fixed certificate the
error modes set by $Z$ cannot move (see "disk" below), which on the §3.3.7 benchmark
limits the held-out improvement to about 8 %, against about 15–19 % here. The returned
design carries the float64 Stein certificate of the tuned gain (SciPy
``solve_discrete_lyapunov``), re-checked by `fojax.design.verify`.

**"disk": the exact disk parameterization with the LMI certificate fixed.** The LMI
design returns a certificate $X \succ 0$ for its disk region
$\mathcal Q(\alpha, \tau)$. `fojax.design.disk_gain` maps *every* parameter $\Theta$
(through the contraction $\mathcal L = \Theta(I + \Theta^\top\Theta)^{-1/2}$, Cholesky
form) and every $Y_\perp$ to a gain $\mathbb Y$ whose error dynamics
$\mathbb A = \mathbb A_1(Z) - \mathbb Y\mathbb A_2$ satisfy
$(\mathbb A - \alpha I)^\top X(\mathbb A - \alpha I) \prec \tau^2 X$ — all eigenvalues in the
disk — as long as the margin $\tau - \|A_\perp(Z)\|$ is positive. The free parameters
are

- ``Theta`` ``(d, k)`` (the gain $\mathbb Y = [Y_1\,J;\,Y_2\,G]$; the component
  $Y_\perp$ outside the range of $\tilde B$ is kept at the LMI value: it multiplies
  $\mathbb A_2$ and $F_3$, whose columns lie in the range of $\mathbb A_2$, so it changes
  nothing — its gradient is identically zero),
- ``Y3`` ``(q, c)`` (enters only $P, Q$, i.e. which combination of $\varepsilon$ and $w$ is
  output; conditions a.–d. hold for every value),
- optionally ``Z`` (`tune_Z=True`): it moves $\mathbb A_1$, so the margin can shrink.

In both modes a step whose margin is $\le$ `min_margin` is *backtracked* (the update is
halved up to `max_backtracks` times, all candidates evaluated inside the same jitted
step); if no fraction is valid the iterate is rejected and the parameters stay. A
rejected iterate is never returned.

The observer matrices are rebuilt from `fojax.design.observer_matrices` at every
step, so conditions a.–d. hold identically (they are built in, not penalized). Tuning
starts exactly at the LMI design (in "disk" mode by inverting the map at the LMI gain).
Every accepted iterate is re-checked on the host (eigenvalues of $\mathbb A$ in the
region with a positive margin).

Only ``kind="generalized"`` and ``"proportional"`` designs are tunable (the PI
constraint $S = -Y_2N_3 = 0$ is not preserved by either map).

**One jitted step.** Loss (batched mean or quantile of IAE/ISE over the training
study, plus the user's `extra_loss` terms), gradient and the optax update (with the
backtracking candidates) form one `equinox.filter_jit` function, compiled once
(`TRACE_COUNTS["tune_step"]`).

**Checkpoints.** ``checkpoint=path`` writes, every `checkpoint_every` steps, the
parameters, the optimizer state, the step, the PRNG key and the history (``path.npz`` +
``path.json``, each written to a temporary file and moved with `os.replace`; both hold
the step, and a pair that disagrees — a run killed between the two writes — is refused).
``resume=True`` continues from it; the result equals an uninterrupted run.
"""

from __future__ import annotations

import collections
import dataclasses
import os
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import scipy.linalg
from jax import lax

from .._errors import InputError
from ..design import Disk, FunctionalObserverDesign, pieces
from ..design._functional import build_observer, verify_structure_design
from ..design._gain_parameterization import contraction, disk_gain
from ..design._parameterization import error_dynamics, observer_matrices
from ..studies._runner import SimConfig, Study, study_loss
from ..studies._sharding import (
    check_same_on_every_process,
    distributed_errors,
    replicate,
    spans_processes,
)
from ._loop import backtracked_update, check_extra_loss, run_loop
from ._optimizer import shared_optimizer


#: Number of traces of the jitted tuning step and of the held-out evaluation.
TRACE_COUNTS: collections.Counter = collections.Counter()


class _Fixed(eqx.Module):
    """The fixed data of the parameterization (arrays; sizes static)."""

    structure: object
    X: jax.Array
    N1: jax.Array
    N2: jax.Array
    A2: jax.Array
    Z: jax.Array
    Yperp: jax.Array
    center: float = eqx.field(static=True)
    radius: float = eqx.field(static=True)
    rank: int = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    mode: str = eqx.field(static=True, default="disk")
    frozen: tuple = eqx.field(static=True, default=())


def _A1(fx: _Fixed, Z):
    s = fx.structure
    q0, q1 = s.q0, s.q1
    top = fx.N1 - Z @ fx.N2
    if q1 == 0:
        return top
    return jnp.block([[top, jnp.zeros((q0, q1))], [jnp.zeros((q1, q0 + q1))]])


def _gain(fx: _Fixed, params):
    Z = params.get("Z", fx.Z)
    Y, margin = disk_gain(fx.X, _A1(fx, Z), fx.A2, fx.center, fx.radius, contraction(params["Theta"]),
                          fx.Yperp, rank=fx.rank)
    return Z, Y, margin


def _split(fx: _Fixed, Y):
    s = fx.structure
    q0, c = s.q0, s.q0 + s.nw
    return {"Y1": Y[:q0, :c], "J": Y[:q0, c:], "Y2": Y[q0:, :c], "G": Y[q0:, c:]}


def stein_certificate(fx: _Fixed, Aa):
    r"""``P`` solving $\bar A^\top P\bar A - P = -I$, $\bar A = (\mathbb A - \alpha I)/\tau$
    (traceable). All eigenvalues of $\mathbb A$ lie in the open disk iff ``P ≻ 0`` (then
    ``P ⪰ I``), and $(\mathbb A-\alpha I)^\top P(\mathbb A-\alpha I) - \tau^2P = -\tau^2 I$,
    so ``P`` is the disk certificate $X$."""
    d = Aa.shape[0]
    Ab = (Aa - fx.center * jnp.eye(d)) / fx.radius

    # Smith's doubling: P = Σ_k (Āᵀ)^k Ā^k summed over 2^40 terms (matrix products only:
    # cheap to compile and differentiate; outside the disk Ā^(2^j) overflows to inf and
    # the margin test rejects the point, the host eigenvalue check catches the rest).
    def double(_, carry):
        P, A = carry
        return P + A.T @ P @ A, A @ A

    P, _ = lax.fori_loop(0, 40, double, (jnp.eye(d), Ab))
    return 0.5 * (P + P.T)


def _direct_margin(fx: _Fixed, params):
    """``(P, margin)``: margin ``1/λ_max(P) ∈ (0, 1]`` inside the disk (it tends to 0 at its
    boundary), ``-1`` outside."""
    mats = observer_matrices(fx.structure, **_direct_params(fx, params))
    P = stein_certificate(fx, error_dynamics(mats)[0])
    ev = jnp.linalg.eigvalsh(P)
    inside = jnp.all(jnp.isfinite(ev)) & (ev[0] > 0)
    return P, jnp.where(inside, 1.0 / jnp.where(inside, ev[-1], 1.0), -1.0)


def _direct_params(fx: _Fixed, params):
    """All six free parameters: the tuned ones, the frozen ``Z`` and empty blocks."""
    out = {}
    for name, shape in fx.structure.param_shapes().items():
        if name in params:
            out[name] = params[name]
        elif name == "Z":
            out[name] = fx.Z
        else:
            out[name] = jnp.zeros(shape)
    return out


def free_parameters_to_design_params(fx: _Fixed, params) -> tuple[dict, jax.Array]:
    """``({Z, Y1, Y2, Y3, J, G}, margin)`` for the tuning parameters (traceable)."""
    if fx.mode == "direct":
        _, margin = _direct_margin(fx, params)
        return _direct_params(fx, params), margin
    Z, Y, margin = _gain(fx, params)
    out = dict(_split(fx, Y), Z=Z, Y3=params["Y3"])
    return out, margin


def _observer_and_design_params(fx: _Fixed, params):
    """``(observer, {Z, Y1, Y2, Y3, J, G}, margin)`` for the tuning parameters (traceable)."""
    p, margin = free_parameters_to_design_params(fx, params)
    return build_observer(fx.structure, observer_matrices(fx.structure, **p), kind=fx.kind), p, margin


def _margin(fx: _Fixed, params):
    return _direct_margin(fx, params)[1] if fx.mode == "direct" else _gain(fx, params)[2]


def observer_from_parameters(fx: _Fixed, params):
    """The observer for the tuning parameters (traceable), and the margin."""
    obs, _, margin = _observer_and_design_params(fx, params)
    return obs, margin


def _inverse_contraction(Lc: np.ndarray) -> np.ndarray:
    """Θ with ``contraction(Θ) = Lc`` (``‖Lc‖ < 1``): ``Θ = Lc C_u``, ``C_u C_uᵀ = (I − LcᵀLc)^{-1}``
    with ``C_u`` upper triangular (a reversed Cholesky factor)."""
    k = Lc.shape[1]
    S = np.linalg.inv(np.eye(k) - Lc.T @ Lc)
    S = 0.5 * (S + S.T)
    J = np.eye(k)[::-1]
    Cu = J @ np.linalg.cholesky(J @ S @ J) @ J
    return Lc @ Cu


def initial_parameters(design: FunctionalObserverDesign, region: Disk | None = None, *,
                       tune_Z: bool | None = None, parameterization: str = "direct"):
    """``(fixed, params)`` reproducing the LMI design's observer exactly (host).

    ``parameterization="direct"``: the parameters are the design's free parameters
    ``Z, Y1, Y2, Y3, J, G`` themselves (``Z`` frozen when ``tune_Z=False``).
    ``"disk"``: inverts `disk_gain` at the design's 𝕐: ``𝓛 = F⁻¹ M V_b`` with
    ``M = L_xᵀ(𝔸 − αI)L_x^{-ᵀ}``, ``Y_⊥ = L_xᵀ 𝕐``, and ``Θ`` from the inverse
    contraction (``Z`` tuned only when ``tune_Z=True``).
    """
    if parameterization not in ("direct", "disk"):
        raise InputError(f"parameterization must be 'direct' or 'disk', got {parameterization!r}.")
    if design.kind not in ("generalized", "proportional"):
        raise InputError(
            f"tune supports generalized and proportional designs; got kind={design.kind!r} (the PI "
            "constraint S = -Y2 N3 = 0 is not preserved by the disk parameterization)."
        )
    region = design.region if region is None else region
    if not isinstance(region, Disk):
        raise InputError(
            f"tune parameterizes disk regions only; got {region.describe()}. Design the observer "
            "with region=fojax.Disk(center, radius)."
        )
    s = design.structure
    if s.num_rules != 1:
        raise InputError("tune supports single-rule (LTI) structures only.")
    if parameterization == "direct":
        tune_Z = True if tune_Z is None else bool(tune_Z)
        p = {k: jnp.asarray(np.asarray(v)) for k, v in design.params.items()}
        fx = _Fixed(s, jnp.zeros((0, 0)), jnp.zeros((0, 0)), jnp.zeros((0, 0)), jnp.zeros((0, 0)), p["Z"],
                    jnp.zeros((0, 0)), float(region.center), float(region.radius), 0, design.kind, "direct",
                    () if tune_Z else ("Z",))
        if design.kind == "proportional":  # no v-dynamics: Y2, J, G are empty
            p = {k: v for k, v in p.items() if v.size}
        if not tune_Z:
            p.pop("Z")
        _, margin = _direct_margin(fx, p)
        if not float(margin) > 0:
            raise InputError(
                f"the design's error dynamics are not inside {region.describe()}; pass the region the "
                "design was made for (or one containing its eigenvalues)."
            )
        return fx, p
    tune_Z = bool(tune_Z)
    pc = pieces(s, xp=np)
    q0, q1 = s.q0, s.q1
    c = pc.N3.shape[0]
    N1, N2, N3 = np.asarray(pc.N1[0]), np.asarray(pc.N2[0]), np.asarray(pc.N3)
    A2 = N3 if q1 == 0 else np.block([[N3, np.zeros((c, q1))], [np.zeros((q1, q0)), -np.eye(q1)]])
    p = design.params
    Z = np.asarray(p["Z"])
    Y = np.asarray(p["Y1"]) if q1 == 0 else np.block([[p["Y1"], p["J"]], [p["Y2"], p["G"]]])
    A1 = N1 - Z @ N2 if q1 == 0 else np.block([[N1 - Z @ N2, np.zeros((q0, q1))], [np.zeros((q1, q0 + q1))]])
    X = 0.5 * (design.X + design.X.T)
    d = X.shape[0]
    k = int(np.linalg.matrix_rank(A2))
    al, tau = region.center, region.radius
    Lx = np.linalg.cholesky(X)
    LxinvT = np.linalg.inv(Lx.T)
    Aa = A1 - Y @ A2
    M = Lx.T @ (Aa - al * np.eye(d)) @ LxinvT
    U, sv, Vt = np.linalg.svd(A2 @ LxinvT)
    Vb, Vp = Vt[:k].T, Vt[k:].T
    M0 = Lx.T @ (A1 - al * np.eye(d)) @ LxinvT
    F = np.linalg.cholesky(tau**2 * np.eye(d) - (M0 @ Vp) @ (M0 @ Vp).T)
    Lc = np.linalg.solve(F, M @ Vb)
    if not np.linalg.norm(Lc, 2) < 1.0:
        raise InputError(
            f"the design's certificate X does not certify {region.describe()} for its own gain "
            f"(‖𝓛‖ = {np.linalg.norm(Lc, 2):.4f} ≥ 1); pass the region the design was made for."
        )
    params = {"Theta": jnp.asarray(_inverse_contraction(Lc)), "Y3": jnp.asarray(p["Y3"])}
    if tune_Z:
        params["Z"] = jnp.asarray(Z)
    fx = _Fixed(s, jnp.asarray(X), jnp.asarray(N1), jnp.asarray(N2), jnp.asarray(A2), jnp.asarray(Z),
                jnp.asarray(Lx.T @ Y), float(al), float(tau), k, design.kind)
    return fx, params


@dataclasses.dataclass
class TuneResult:
    """Result of `tune`.

    Attributes:
        design: the tuned, verified `FunctionalObserverDesign` (same structure, region and
            certificate X as the LMI design; ``solver["tuning"]`` holds the run's options).
        params: the tuning parameters of the returned design (``Theta, Y3[, Z]``).
        history: dict of lists per step: ``step, train_loss, heldout_loss`` (``nan`` when
            not evaluated), ``margin``, ``accepted``, ``backtracks``, ``max_real_eig``.
        initial_heldout, final_heldout: held-out loss of the LMI design and of the result.
    """

    design: FunctionalObserverDesign
    params: dict
    history: dict
    initial_heldout: float | None
    final_heldout: float | None


def _loss_fn(params, fx, study, loss, quantile, weights, cfg, barrier=0.0, extra_loss=None):
    obs, design_params, _ = _observer_and_design_params(fx, params)
    value = study_loss(study, obs, loss=loss, quantile=quantile, weights=weights, cfg=cfg)
    if fx.mode == "direct" and barrier:
        P, _ = _direct_margin(fx, params)
        value = value + barrier * jnp.log(jnp.trace(P))
    if extra_loss is not None:
        value = value + extra_loss(obs, design_params)
    return value


@eqx.filter_jit
def _step(params, opt_state, fx, study, optimizer, loss, quantile, weights, cfg, min_margin, n_back, barrier,
          extra_loss):
    TRACE_COUNTS["tune_step"] += 1
    value, grads = eqx.filter_value_and_grad(_loss_fn)(params, fx, study, loss, quantile, weights, cfg, barrier,
                                                       extra_loss)
    updates, new_state = optimizer.update(grads, opt_state, params)
    new_params, margin, accepted, backtracks = backtracked_update(
        params, updates, lambda cand: _margin(fx, cand), min_margin, n_back)
    return value, new_params, new_state, margin, accepted, backtracks


@eqx.filter_jit
def _evaluate(params, fx, study, loss, quantile, weights, cfg):
    TRACE_COUNTS["evaluate"] += 1
    return _loss_fn(params, fx, study, loss, quantile, weights, cfg)


def _host_check(fx: _Fixed, params, region) -> tuple[bool, float, float]:
    p, margin = free_parameters_to_design_params(fx, params)
    mats = observer_matrices(fx.structure, **{k: np.asarray(v) for k, v in p.items()}, xp=np)
    eigs = np.linalg.eigvals(np.asarray(error_dynamics(mats, xp=np))[0])
    inside = bool(np.all(region.margin(eigs) > 0))
    return inside and float(margin) > 0, float(margin), float(np.max(eigs.real))


def tune(
    design: FunctionalObserverDesign,
    train_study: Study,
    *,
    heldout: Study | None = None,
    steps: int = 100,
    optimizer: optax.GradientTransformation | None = None,
    loss: str = "iae",
    quantile: float | None = None,
    weights=None,
    extra_loss: Callable | None = None,
    region: Disk | None = None,
    parameterization: str = "direct",
    tune_Z: bool | None = None,
    barrier: float = 1e-3,
    min_margin: float = 1e-6,
    max_backtracks: int = 8,
    eval_every: int = 1,
    key=None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 1,
    resume: bool = False,
    method: str = "auto",
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    callback: Callable | None = None,
    quiet: bool = True,
    devices=None,
) -> TuneResult:
    r"""Tune the free parameters of a functional-observer design by gradient descent.

    See the module docstring for the parameterization (every iterate is a valid
    observer with eigenvalues in the disk), backtracking, and checkpoints.

    **Arguments:**

    - `design`: an LMI design (`fojax.design.design_functional_observer`,
      ``kind="generalized"`` or ``"proportional"``, disk region).
    - `train_study`: a `fojax.studies.Study` whose signals the observer estimates.
    - `heldout`: a study of samples never used for training (its loss is reported).
    - `steps`: total number of optimizer steps (including those of a resumed run).
    - `optimizer`: an optax transformation (default
      ``shared_optimizer("adam", learning_rate=1e-2)``). The jitted step is compiled once
      per optimizer *object* (optax transformations are closures, keyed by identity):
      use `fojax.tuning.shared_optimizer`, or pass the same object to several `tune`
      calls, to reuse the compiled step.
    - `loss`: ``"iae"`` or ``"ise"`` of $\hat z - z$ (mean over signals, or `weights`);
      `quantile`: use this quantile over samples instead of the mean.
    - `extra_loss`: user terms added to the training loss, ``extra_loss(observer,
      design_params) -> scalar``: `observer` is the iterate's observer (the thesis's
      matrices by name, e.g. ``observer.F``), `design_params` the dict ``Z, Y1, Y2, Y3,
      J, G``. A pure JAX function (traced and differentiated with the loss; the step
      compiles once per function object). Example: ``lambda obs, p: 1e-3 *
      jnp.sum(obs.F ** 2)`` penalizes the output-injection gain. The training loss in the
      history includes it (and the barrier); the held-out loss is the study loss alone.
      A checkpoint does not store it: pass the same function when resuming.
    - `region`: the disk to stay in (default: the design's region).
    - `parameterization`: ``"direct"`` (default) or ``"disk"`` (module docstring).
    - `tune_Z`: move ``Z`` too (default: yes for ``"direct"``, no for ``"disk"``).
    - `barrier`: weight of ``log tr P`` in the ``"direct"`` loss.
    - `min_margin`, `max_backtracks`: acceptance rule of a step (backtracking).
    - `eval_every`: held-out evaluation period (steps).
    - `key`: PRNG key stored with the checkpoint (reserved for stochastic training).
    - `checkpoint`, `checkpoint_every`, `resume`: see the module docstring.
    - `method`, `rtol`, `atol`, `max_steps`: simulation options (`fojax.simulate`).
    - `callback`: called as ``callback(step, record)`` after every step.
    - `quiet`: no progress bar.
    - `devices`: spread the training samples over these devices (e.g. ``jax.devices()``
      after `jax.distributed.initialize`: every process's devices; each process computes
      its share of the loss and gradient). The iterates are bit-identical to the default
      (``None``: one device), see `fojax.studies._sharding`. Every process runs the same
      `tune` call (checked; `fojax.DistributedError` otherwise or when another dies);
      with `checkpoint`, give each process its own path or let only process 0's file count.

    **Returns:** a `TuneResult`.
    """
    if loss not in ("iae", "ise"):
        raise InputError(f"loss must be 'iae' or 'ise', got {loss!r}.")
    region = design.region if region is None else region
    fx, params = initial_parameters(design, region, tune_Z=tune_Z, parameterization=parameterization)
    if extra_loss is not None:
        check_extra_loss(extra_loss, *_observer_and_design_params(fx, params)[:2])
    optimizer = shared_optimizer("adam", learning_rate=1e-2) if optimizer is None else optimizer
    opt_state = optimizer.init(params)
    key = jax.random.PRNGKey(0) if key is None else key
    cfg = SimConfig(method=method, rtol=float(rtol), atol=float(atol), max_steps=int(max_steps),
                    devices=None if devices is None else tuple(devices))
    if devices is not None and spans_processes(devices):
        check_same_on_every_process((params, train_study, heldout), "tune")
    # on the mesh from the first step on (the step's outputs are): one compilation
    params, opt_state = replicate((params, opt_state), devices)
    w = None if weights is None else jnp.asarray(weights, dtype=jnp.float64)
    path = None if checkpoint is None else os.fspath(checkpoint)

    def heldout_loss(p):
        return float(_evaluate(p, fx, heldout, loss, quantile, w, cfg))

    initial_heldout = (heldout_loss(initial_parameters(design, region, tune_Z=tune_Z,
                                                       parameterization=parameterization)[1])
                       if heldout else None)

    with distributed_errors("tune"):
        params, history = run_loop(
            params, opt_state, key, steps=steps, step=_step,
            step_args=(fx, train_study, optimizer, loss, quantile, w, cfg, float(min_margin), int(max_backtracks),
                       float(barrier), extra_loss),
            host_check=lambda p: _host_check(fx, p, region),
            heldout_loss=heldout_loss if heldout is not None else None, eval_every=eval_every,
            callback=callback, callback_params=False, path=path, resume=resume,
            checkpoint_every=checkpoint_every, quiet=quiet, desc="tune",
        )  # fmt: skip
        final_heldout = heldout_loss(params) if heldout is not None else None
    tuned = _verified_design(design, fx, params, region, dict(loss=loss, quantile=quantile, steps=steps,
                                                               tune_Z=tune_Z, parameterization=parameterization,
                                                               barrier=barrier, extra_loss=_name(extra_loss)))
    return TuneResult(design=tuned, params=params, history=history, initial_heldout=initial_heldout,
                      final_heldout=final_heldout)


def _name(fn) -> str | None:
    """A readable name of a user function, for the design's record of the tuning options."""
    return None if fn is None else getattr(fn, "__qualname__", type(fn).__name__)


def _verified_design(design, fx, params, region, options) -> FunctionalObserverDesign:
    p, _ = free_parameters_to_design_params(fx, params)
    p = {k: np.asarray(v) for k, v in p.items()}
    if fx.mode == "direct":
        # the certificate of the tuned gain: the Stein solution (see `stein_certificate`),
        # recomputed in float64 by SciPy and re-checked by `verify` as an LMI
        mats = observer_matrices(fx.structure, **p, xp=np)
        Aa = np.asarray(error_dynamics(mats, xp=np))[0]
        Ab = (Aa - region.center * np.eye(Aa.shape[0])) / region.radius
        X = scipy.linalg.solve_discrete_lyapunov(Ab.T, np.eye(Aa.shape[0]))
        X = 0.5 * (X + X.T)
    else:
        X = np.asarray(fx.X)
    mats, report = verify_structure_design(fx.structure, p, region, X)
    return FunctionalObserverDesign(
        observer=build_observer(fx.structure, mats, kind=design.kind),
        kind=design.kind,
        region=region,
        structure=fx.structure,
        params=p,
        T=np.asarray(mats.T),
        K=np.asarray(mats.K),
        Z_eff=np.asarray(mats.Z_eff),
        X=X,
        report=report,
        solver=dict(design.solver, tuning=options),
    )
