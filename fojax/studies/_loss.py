r"""`study_loss`: the differentiable scalar loss of one observer over a study (what `fojax.tune`
minimises), on the same engines as `run_study`, and `resolve_engine`, the host decision that
lets a traced study keep its engine."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._errors import InputError
from ..observer import AbstractObserver
from ..simulation._discrete import discrete_stepper
from ..simulation._save import error_metrics
from ._engines import study_engine
from ._runner import _indices, sample_errors, SimConfig, Study
from ._sharding import per_sample, sample_mesh, sum_rows


def _discrete_cfg(study: Study, cfg: SimConfig) -> SimConfig:
    """`cfg`, or for a discrete-time plant `cfg` with the `Discrete` stepper (every sample
    through `fojax.simulate`; `fojax.simulation._discrete`)."""
    st = discrete_stepper(study.plant, cfg.stepper)
    if st is cfg.stepper:
        return cfg
    return dataclasses.replace(cfg, stepper=st)


def resolve_engine(study: Study, observers, cfg: SimConfig = SimConfig()) -> SimConfig:
    r"""Host: the `SimConfig` with which `study_loss` runs the concrete `study` on the same
    engine when the study is later traced (e.g. an argument of a jitted step, as in
    `fojax.tune`, so that new study numbers do not recompile).

    When the exact engine does not take the study and the exponential one does
    (`fojax.studies._exponential.exponential_schedule`: the qualification, the affine check
    and the step schedule, decided with the concrete `observers`, e.g. the starting design
    of a tuning run), returns `cfg` with ``exponential_schedule`` set to that schedule;
    otherwise `cfg` unchanged (the exact engine decides on traced studies by itself;
    anything else runs `fojax.simulate` under `jax.vmap`). The schedule belongs to this
    study: another study needs its own call.
    """
    observers = tuple(observers) if isinstance(observers, (tuple, list)) else (observers,)
    if _discrete_cfg(study, cfg) is not cfg:
        return _discrete_cfg(study, cfg)
    for candidate in cfg.stepper.batch_candidates:  # in order; the first that takes the study decides
        resolved = study_engine(candidate).resolve(candidate, study, observers, cfg)
        if resolved is not None:
            return resolved
    return cfg


def study_loss(study: Study, observer: AbstractObserver, *, loss: str = "iae", quantile: float | None = None,
               weights=None, cfg: SimConfig = SimConfig()) -> Array:
    r"""Differentiable scalar loss of one observer over all samples of `study`.

    Per sample: the (weighted) mean over signals of the IAE or ISE of $\hat z - z$; then
    the mean over samples, or the `quantile` (e.g. 0.9) of the per-sample values.
    Traceable (use inside `jax.jit` / `jax.grad`).

    With ``cfg.stepper`` `Auto` or `Exact` and a study of LTI samples with known
    signals (the types `run_study`'s exact engine accepts; a traced grid is assumed
    uniform), every sample runs on the exact batch-last kernel, reverse-differentiable with
    respect to the observer (`fojax.studies._exact.sample_metrics_traced`: blocks of 32
    samples; its reverse mode is the adjoint recurrence of `fojax.studies._adjoint` at the
    observer's size, the plant's trajectory being independent of the observer,
    checkpointed, so memory does not grow with the number of time steps; like `jax.grad`,
    it takes the derivative of $|e|$ as $\mathrm{sign}(e)$, 0 at 0; differentiating with
    respect to the study's arrays raises `fojax.errors.InputError`: use
    ``cfg=SimConfig(stepper=fojax.Diffrax())`` for that). With ``cfg.stepper`` `Auto` (or
    `Exponential`), no
    ``cfg.devices`` and a *concrete* study whose samples vary in time only through signals
    entering the differential equations affinely (`run_study`'s exponential engine: a
    time-varying δ(t), faults on the step grid, known inputs), or a traced study with
    ``cfg.exponential_schedule`` set by `resolve_engine` on its concrete values (as
    `fojax.tune` does), the samples run on that engine (`fojax.studies._exponential.exponential_metrics_traced`: ETDRK4 in blocks of 64 samples,
    every term per sample, the time loop in `jax.checkpoint`-ed segments of about √S of the
    S steps, so the memory of the backward pass grows like √S), differentiable with respect
    to the observer; the host decisions (qualification, the affine check, the step
    schedule) are taken with the observer when it is concrete and with a zero stand-in of
    it when it is traced (the schedule then ignores the observer's poles). A traced study
    without ``cfg.exponential_schedule`` does not qualify. Otherwise each sample runs
    `fojax.simulate` under `jax.vmap`.

    With ``cfg.devices`` (e.g. ``jax.devices()`` after `jax.distributed.initialize`: all
    processes' devices) the samples are spread over those devices, each computing its own;
    the loss and its gradient with respect to the observer are bit-identical to
    ``cfg.devices=None`` (one device): see `fojax.studies._sharding`.
    """
    if loss not in ("iae", "ise"):
        raise InputError(f"loss must be 'iae' or 'ise', got {loss!r}.")
    w = jnp.full((study.num_signals,), 1.0 / study.num_signals) if weights is None else jnp.asarray(weights)
    mesh = sample_mesh(cfg.devices)
    cfg = _discrete_cfg(study, cfg)
    stepper = cfg.stepper
    for candidate in stepper.batch_candidates:  # its batch kernels, in order (fojax.studies._engines)
        out = study_engine(candidate).loss_metrics(candidate, study, (observer,), cfg, mesh, loss)
        if out is not None:
            per = w @ out[0][0]  # (B,): the one metric accumulated
            return sum_rows(per) / per.shape[0] if quantile is None else jnp.quantile(per, quantile)
    if not stepper.simulates:
        raise InputError(
            f"study_loss: stepper {stepper!r} cannot run this study (the exponential engine needs a concrete "
            "study of time-varying affine samples on one device; run_study(stepper=...) says why not). Use "
            "SimConfig(stepper=fojax.Auto()) or Diffrax()."
        )
    iu, jf = (jnp.asarray(a) for a in _indices(study))

    def local(study, p):
        def one(i, j, obs):
            (e,), _ = sample_errors(study, (obs,), i, j, cfg)
            return error_metrics(study.ts, e, cfg.settle_tol)[loss] @ w

        return jax.vmap(one)(*p)

    per = per_sample(local, study, observer, iu, jf, mesh)
    return sum_rows(per) / per.shape[0] if quantile is None else jnp.quantile(per, quantile)
