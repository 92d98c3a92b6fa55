r"""Gradient tuning of Takagi–Sugeno functional observers, with the common certificate fixed.

**Free parameters.** The T-S observer (thesis eq. 3.152) of
`fojax.design.design_ts_observer` has one common $Z$ (one $T$) and per-rule
$Y_{1i}, Y_{2i}, Y_{3i}, J_i, G_i$ (`fojax.design.observer_matrices` with a leading
rule axis). Every value gives matrices satisfying conditions a.–d. for every rule
(built in, not penalized); tuning moves all of them (``Z`` frozen with
``tune_Z=False``).

**Why the certificate stays fixed.** The blended error dynamics
$\dot\sigma = \sum_i w_i(y)\,\mathbb A_i\sigma$ are only guaranteed stable (for
arbitrarily time-varying weights) with a *common* certificate: per-rule Stein or
Lyapunov certificates, as in `fojax.tuning.tune`'s ``"direct"`` mode, would place every
frozen rule's poles but prove nothing about the blend. The LMI design's $X$ is kept,
and a parameter value is *admissible* when, in float64 inside the jitted step, for
every rule $i$

- the region LMI $L_R\otimes X + M_R\otimes(\mathbb A_i^\top X) + M_R^\top\otimes(X\mathbb A_i)
  \prec 0$ holds (`fojax.design.AbstractRegion.lmi_matrix`; for a disk
  $\mathcal Q(\alpha, \tau)$ this is, by a Schur complement,
  $\tau^2X - (\mathbb A_i - \alpha I)^\top X(\mathbb A_i - \alpha I) \succ 0$), and
- the Lyapunov inequality $\mathbb A_i^\top X + X\mathbb A_i \prec 0$ (quadratic stability
  under time-varying weights) holds,

both with the relative margin $\lambda_{\min}(-\,\cdot\,)/\|X\|$ above `min_margin`. Both
inequalities are affine in $\mathbb A_i$, so they then hold for every convex combination
of the rules: frozen-weight region placement and quadratic stability of the blend, the
guarantees of `design_ts_observer`. Any region the T-S design accepts works (disks,
half-planes, sectors, intersections: the characteristic matrices $L_R, M_R$ are used).

**Loss, barrier, acceptance.** The loss is the batched mean (or `quantile`) of the
IAE/ISE of $\hat z - z$ over the training study (`fojax.studies.study_loss`: any plant,
e.g. the nonlinear robot arm with physical-parameter uncertainty, simulated with the
observer driven by the plant's measured output), plus the user's `extra_loss` terms, plus
$-\texttt{barrier}\sum_i\big(\log\det(-\mathcal R_i/\|X\|) + \log\det(-\mathcal L_i/\|X\|)\big)$,
$\mathcal R_i$, $\mathcal L_i$ the region and Lyapunov LMI matrices (finite inside,
$+\infty$ at the boundary). A step whose candidate violates the margin is *backtracked*
(the update halved up to `max_backtracks` times, all candidates evaluated inside the
same jitted step); if no fraction is admissible the iterate is rejected and the
parameters stay. Every accepted iterate is re-verified on the host (residuals of a.–d.,
eigenvalues of every rule in the region, region LMI and Lyapunov inequality at $X$, in
float64, as `design_ts_observer` verifies); an iterate that fails is rejected, never
returned. The returned design is verified again the same way
(`TakagiSugenoObserverDesign`, certificate $X$ unchanged).

*Deviation from the thesis:* the thesis gives no tuning of T-S observers; with a common
certificate the explicit $(\mathcal L, \gamma)$ parameterization of one rule does not
apply (one $\mathcal L_i$ per rule would need the same $X$ and a common $Z$), so the
parameters are moved directly and the common LMI is enforced by a barrier and rejection.

**One jitted step.** Loss (with the barrier), gradient, the optax update and the
backtracking candidates form one `equinox.filter_jit` function, compiled once
(``TRACE_COUNTS["tune_ts_step"]``; held-out evaluation: ``"evaluate_ts"``).

**Checkpoints** as in `fojax.tuning.tune` (``checkpoint=path``, ``resume=True``).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._errors import DesignVerificationError, InputError
from ..design import TakagiSugenoObserverDesign
from ..design._functional import verify_structure_design
from ..design._parameterization import design_residuals, error_dynamics, observer_matrices
from ..design._regions import AbstractRegion, as_region
from ..design._takagi_sugeno import _lyapunov_recheck
from ..design._verify import LMI_MARGIN, verify
from ..observer import TakagiSugenoObserver
from ..plant._takagi_sugeno import AbstractMembership
from ..studies._runner import SimConfig, Study, study_loss
from ._loop import backtracked_update, check_extra_loss, run_loop
from ._optimizer import shared_optimizer
from ._tune import _name, TRACE_COUNTS, TuneResult


_RULE_PARAMS = ("Y1", "Y2", "Y3", "J", "G")


class _TSFixed(eqx.Module):
    """The fixed data of a T-S tuning run (arrays; sizes and options static)."""

    structure: object
    membership: AbstractMembership
    X: jax.Array
    LR: jax.Array
    MR: jax.Array
    Z: jax.Array
    Wu: jax.Array
    Wy: jax.Array
    xnorm: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    frozen: tuple = eqx.field(static=True, default=())


def _full_params(fx: _TSFixed, params) -> dict:
    """All six free parameters (the frozen ``Z``, empty blocks of a proportional design)."""
    s = fx.structure
    out = {}
    for name, shape in s.param_shapes().items():
        if name in params:
            out[name] = params[name]
        elif name == "Z":
            out[name] = fx.Z
        else:
            out[name] = jnp.zeros((s.num_rules,) + shape)
    return out


def _lmi_blocks(fx: _TSFixed, As):
    """``(region, lyapunov)``: ``-𝓡_i/‖X‖`` and ``-𝓛_i/‖X‖`` for every rule (``≻ 0`` iff admissible)."""
    X = fx.X
    XA = jnp.einsum("ij,kjl->kil", X, As)
    XAt = jnp.swapaxes(XA, -1, -2)

    def kron(a, b):  # a (r, r), b (k, d, d) -> (k, r d, r d)
        r, d = a.shape[0], b.shape[-1]
        return jnp.einsum("ij,kab->kiajb", a, b).reshape(b.shape[0], r * d, r * d)

    k = As.shape[0]
    region = kron(fx.LR, jnp.broadcast_to(X, (k,) + X.shape)) + kron(fx.MR, XAt) + kron(fx.MR.T, XA)
    region = 0.5 * (region + jnp.swapaxes(region, -1, -2))
    lyap = XAt + XA
    lyap = 0.5 * (lyap + jnp.swapaxes(lyap, -1, -2))
    return -region / fx.xnorm, -lyap / fx.xnorm


def _margin_and_barrier(fx: _TSFixed, params):
    """``(margin, logdet)``: the smallest eigenvalue of all ``-𝓡_i/‖X‖``, ``-𝓛_i/‖X‖``
    (``> 0`` iff every rule satisfies both LMIs at the common ``X``) and the sum of their
    log-determinants (finite only inside)."""
    mats = observer_matrices(fx.structure, **_full_params(fx, params))
    R, Ly = _lmi_blocks(fx, error_dynamics(mats))
    er, el = jnp.linalg.eigvalsh(R), jnp.linalg.eigvalsh(Ly)
    margin = jnp.minimum(jnp.min(er), jnp.min(el))
    inside = margin > 0
    safe = lambda e: jnp.where(inside, e, 1.0)  # noqa: E731
    logdet = jnp.sum(jnp.log(safe(er))) + jnp.sum(jnp.log(safe(el)))
    margin = jnp.where(jnp.isfinite(margin), margin, -jnp.inf)
    return margin, jnp.where(inside, logdet, -jnp.inf)


def _observer(fx: _TSFixed, mats) -> TakagiSugenoObserver:
    return TakagiSugenoObserver(
        mats.N, mats.J, mats.F, mats.H, mats.S, mats.G, mats.M, mats.P, mats.Q,
        fx.Wu, fx.Wy, mats.T, fx.membership, kind=fx.kind,
    )  # fmt: skip


def ts_observer_from_parameters(fx: _TSFixed, params) -> TakagiSugenoObserver:
    """The `TakagiSugenoObserver` for the tuning parameters (traceable)."""
    return _observer(fx, observer_matrices(fx.structure, **_full_params(fx, params)))


def initial_ts_parameters(design: TakagiSugenoObserverDesign, region: AbstractRegion | None = None, *,
                          tune_Z: bool = True) -> tuple[_TSFixed, dict]:
    """``(fixed, params)`` reproducing the T-S design's observer exactly (host).

    ``params`` holds ``Z`` (common; omitted with ``tune_Z=False``) and ``Y1, Y2, Y3, J,
    G`` with their leading rule axis (the blocks that are empty for a proportional
    design are omitted). Raises `InputError` if `design` is not a
    `TakagiSugenoObserverDesign` of kind ``"generalized"`` or ``"proportional"``, or if
    its certificate does not satisfy the region and Lyapunov LMIs of `region` with a
    positive margin.
    """
    if not isinstance(design, TakagiSugenoObserverDesign):
        raise InputError(
            f"tune_takagi_sugeno needs a TakagiSugenoObserverDesign (fojax.design.design_ts_observer), got "
            f"{type(design).__name__}; for LTI designs use fojax.tuning.tune."
        )
    if design.kind not in ("generalized", "proportional"):
        raise InputError(
            f"tune_takagi_sugeno supports generalized and proportional designs; got kind={design.kind!r} "
            "(the PI constraint S_i = -Y2_i N3 = 0 is not preserved when Y2_i moves)."
        )
    region = design.region if region is None else as_region(region)
    s = design.structure
    X = 0.5 * (np.asarray(design.X, dtype=float) + np.asarray(design.X, dtype=float).T)
    LR, MR = (np.asarray(a, dtype=float) for a in region.characteristic())
    obs = design.observer
    p = {k: jnp.asarray(np.asarray(v)) for k, v in design.params.items()}
    fx = _TSFixed(s, obs.membership, jnp.asarray(X), jnp.asarray(LR), jnp.asarray(MR), p["Z"],
                  jnp.asarray(obs.Wu), jnp.asarray(obs.Wy), float(np.linalg.norm(X, 2)), design.kind,
                  () if tune_Z else ("Z",))
    p = {k: v for k, v in p.items() if v.size and not (k == "Z" and not tune_Z)}
    margin, _ = _margin_and_barrier(fx, p)
    if not float(margin) > 0:
        raise InputError(
            f"the design's certificate X does not satisfy the LMI of {region.describe()} and the Lyapunov "
            f"inequality for every rule (relative margin {float(margin):.3e} <= 0); pass the region the "
            "design was made for."
        )
    return fx, p


def _loss_fn(params, fx, study, loss, quantile, weights, cfg, barrier, extra_loss=None):
    obs = ts_observer_from_parameters(fx, params)
    value = study_loss(study, obs, loss=loss, quantile=quantile, weights=weights, cfg=cfg)
    if barrier:
        _, logdet = _margin_and_barrier(fx, params)
        value = value - barrier * logdet
    if extra_loss is not None:
        value = value + extra_loss(obs, _full_params(fx, params))
    return value


@eqx.filter_jit
def _step(params, opt_state, fx, study, optimizer, loss, quantile, weights, cfg, min_margin, n_back, barrier,
          extra_loss):
    TRACE_COUNTS["tune_ts_step"] += 1
    value, grads = eqx.filter_value_and_grad(_loss_fn)(params, fx, study, loss, quantile, weights, cfg, barrier,
                                                       extra_loss)
    updates, new_state = optimizer.update(grads, opt_state, params)
    new_params, margin, accepted, backtracks = backtracked_update(
        params, updates, lambda cand: _margin_and_barrier(fx, cand)[0], min_margin, n_back)
    return value, new_params, new_state, margin, accepted, backtracks


@eqx.filter_jit
def _evaluate(params, fx, study, loss, quantile, weights, cfg):
    TRACE_COUNTS["evaluate_ts"] += 1
    return _loss_fn(params, fx, study, loss, quantile, weights, cfg, 0.0)


def host_verify(fx: _TSFixed, params, region: AbstractRegion):
    """Float64 host verification of the tuning parameters, as `design_ts_observer` verifies.

    Returns ``(mats, report, lyapunov_max_eig)``; ``report.passed`` is ``False`` (no
    exception) when a residual of a.–d. exceeds 1e-8 (relative), an eigenvalue of some
    rule is outside `region`, or the region LMI / the Lyapunov inequality fails at the
    common ``X``.
    """
    p = {k: np.asarray(v) for k, v in _full_params(fx, params).items()}
    s = fx.structure
    mats = observer_matrices(s, **p, xp=np)
    res = design_residuals(s, mats, xp=np)
    scale = float(res.pop("scale"))
    As = np.asarray(error_dynamics(mats, xp=np))
    X = np.asarray(fx.X)
    report = verify({k: float(v) for k, v in res.items()}, scale, As, region, X, raise_on_failure=False)
    lyap = max(float(np.linalg.eigvalsh(A.T @ X + X @ A).max()) for A in As)
    return mats, report, lyap


def _host_check(fx, params, region) -> tuple[bool, float, float]:
    mats, report, lyap = host_verify(fx, params, region)
    ok = report.passed and lyap < -LMI_MARGIN * fx.xnorm
    margin = float(_margin_and_barrier(fx, params)[0])
    eigs = np.concatenate([np.linalg.eigvals(A) for A in np.asarray(error_dynamics(mats, xp=np))])
    return bool(ok) and margin > 0, margin, float(np.max(eigs.real))


def tune_takagi_sugeno(
    design: TakagiSugenoObserverDesign,
    train_study: Study,
    *,
    heldout: Study | None = None,
    steps: int = 100,
    optimizer: optax.GradientTransformation | None = None,
    loss: str = "iae",
    quantile: float | None = None,
    weights=None,
    extra_loss: Callable | None = None,
    region: AbstractRegion | None = None,
    tune_Z: bool = True,
    barrier: float = 1e-4,
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
    solver=None,
    callback: Callable | None = None,
    quiet: bool = True,
) -> TuneResult:
    r"""Tune a Takagi–Sugeno functional observer by gradient descent, common certificate fixed.

    See the module docstring for the parameters (common $Z$, per-rule gains), the
    admissibility test (region LMI and Lyapunov inequality at the design's $X$ for every
    rule), the barrier, backtracking, and checkpoints.

    **Arguments:**

    - `design`: a `TakagiSugenoObserverDesign` (`fojax.design.design_ts_observer`,
      ``kind="generalized"`` or ``"proportional"``).
    - `train_study`: a `fojax.studies.Study` whose signals ($z = Lx$) the observer
      estimates; its plant may be nonlinear (e.g. `fojax.models.robot_arm` with
      `fojax.studies.parameter_uncertainty`).
    - `heldout`: a study of samples never used for training (its loss is reported).
    - `steps`: total number of optimizer steps (including those of a resumed run).
    - `optimizer`: an optax transformation (default
      ``shared_optimizer("adam", learning_rate=1e-2)``; see `fojax.tuning.tune` on reusing
      the compiled step).
    - `loss`: ``"iae"`` or ``"ise"`` of $\hat z - z$ (mean over signals, or `weights`);
      `quantile`: use this quantile over samples instead of the mean.
    - `extra_loss`: user terms added to the training loss, ``extra_loss(observer,
      design_params) -> scalar`` (`observer`: the iterate's `TakagiSugenoObserver`;
      `design_params`: ``Z, Y1, Y2, Y3, J, G`` with their rule axis); see
      `fojax.tuning.tune`.
    - `region`: the region to stay in (default: the design's region); the design's $X$
      must certify it.
    - `tune_Z`: move the common ``Z`` too (default ``True``).
    - `barrier`: weight of the log-det barrier of the LMIs.
    - `min_margin`, `max_backtracks`: acceptance rule of a step (relative LMI margin).
    - `eval_every`: held-out evaluation period (steps).
    - `key`: PRNG key stored with the checkpoint (reserved for stochastic training).
    - `checkpoint`, `checkpoint_every`, `resume`: as in `fojax.tuning.tune`.
    - `method`, `rtol`, `atol`, `max_steps`, `solver`: simulation options
      (`fojax.simulate`; e.g. ``solver=diffrax.Tsit5()`` for the non-stiff robot arm).
    - `callback`: called as ``callback(step, record)`` after every step; ``record`` is
      the step's history entry plus ``params`` (the current, accepted parameters).
    - `quiet`: no progress bar.

    **Returns:** a `fojax.tuning.TuneResult` whose `design` is a verified
    `TakagiSugenoObserverDesign` (same structure, region and certificate $X$;
    ``solver["tuning"]`` holds the run's options) and whose `params` are the tuned
    ``Z, Y1, ...``.

    **Raises:** `InputError` (wrong design type or kind, bad `loss`, a region the design's
    $X$ does not certify); `DesignVerificationError` if the final design fails its float64
    verification (it cannot, as every accepted iterate passed the same checks).
    """
    if loss not in ("iae", "ise"):
        raise InputError(f"loss must be 'iae' or 'ise', got {loss!r}.")
    region = design.region if region is None else as_region(region)
    fx, params = initial_ts_parameters(design, region, tune_Z=tune_Z)
    if train_study.num_signals != design.observer.output_size:
        raise InputError(
            f"the study has {train_study.num_signals} signals but the observer estimates "
            f"{design.observer.output_size}; build the study with the design's L."
        )
    if extra_loss is not None:
        check_extra_loss(extra_loss, ts_observer_from_parameters(fx, params), _full_params(fx, params))
    optimizer = shared_optimizer("adam", learning_rate=1e-2) if optimizer is None else optimizer
    opt_state = optimizer.init(params)
    key = jax.random.PRNGKey(0) if key is None else key
    cfg = SimConfig(method=method, rtol=float(rtol), atol=float(atol), max_steps=int(max_steps), solver=solver)
    w = None if weights is None else jnp.asarray(weights, dtype=jnp.float64)
    path = None if checkpoint is None else os.fspath(checkpoint)
    initial = params

    def heldout_loss(p):
        return float(_evaluate(p, fx, heldout, loss, quantile, w, cfg))

    initial_heldout = heldout_loss(initial) if heldout is not None else None

    params, history = run_loop(
        params, opt_state, key, steps=steps, step=_step,
        step_args=(fx, train_study, optimizer, loss, quantile, w, cfg, float(min_margin), int(max_backtracks),
                   float(barrier), extra_loss),
        host_check=lambda p: _host_check(fx, p, region),
        heldout_loss=heldout_loss if heldout is not None else None, eval_every=eval_every,
        callback=callback, callback_params=True, path=path, resume=resume,
        checkpoint_every=checkpoint_every, quiet=quiet, desc="tune T-S",
    )  # fmt: skip
    final_heldout = heldout_loss(params) if heldout is not None else None
    options = dict(loss=loss, quantile=quantile, steps=steps, tune_Z=tune_Z, barrier=barrier,
                   parameterization="takagi_sugeno_fixed_X", extra_loss=_name(extra_loss))
    tuned = _verified_design(design, fx, params, region, options)
    return TuneResult(design=tuned, params=params, history=history, initial_heldout=initial_heldout,
                      final_heldout=final_heldout)


def _verified_design(design, fx, params, region, options) -> TakagiSugenoObserverDesign:
    """The tuned design, verified like `design_ts_observer` (raises `DesignVerificationError`)."""
    p = {k: np.asarray(v) for k, v in _full_params(fx, params).items()}
    X = np.asarray(fx.X)
    mats, report = verify_structure_design(fx.structure, p, region, X)
    if not report.passed:  # verify raises on failure; keep the guard explicit
        raise DesignVerificationError("tuned design failed its float64 verification", report)
    report = _lyapunov_recheck(report, X, mats)
    obs = design.observer
    tuned = TakagiSugenoObserver(
        mats.N, mats.J, mats.F, mats.H, mats.S, mats.G, mats.M, mats.P, mats.Q,
        obs.Wu, obs.Wy, mats.T, obs.membership, kind=design.kind,
    )  # fmt: skip
    return TakagiSugenoObserverDesign(
        observer=tuned,
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
