r"""The study side of the batch steppers: how a study becomes a batch problem, keyed by stepper class.

A stepper says *which* batch kernels a study may run on (`AbstractStepper.batch_candidates`,
in order; `fojax.simulation._steppers`), and whether every sample may otherwise run
through `fojax.simulate` (`AbstractStepper.simulates`). The simulation floor does not know
studies, so what a candidate does with a `Study` lives here, in one object per stepper
class (`study_engine`, the registry `ENGINES`):

| stepper class | batch problem (`run_study`) | differentiable loss (`study_loss`) | ``attrs["engine"]`` |
|---|---|---|---|
| `fojax.Exact` | `fojax.studies._exact.exact_problem` (`StudyProblem`) | `fojax.studies._exact.sample_metrics_traced` | ``"exact-batch"`` |
| `fojax.Exponential` | `fojax.studies._exponential.exponential_problem` (`ExponentialProblem`) | `fojax.studies._exponential.exponential_metrics_traced` | ``"exponential-batch"`` |

`run_study`, `study_loss`, `resolve_engine` (what `fojax.tune` decides on the host) and the
CLI try the stepper's candidates in order through these objects; when none takes the study,
a stepper that `simulates` runs every sample through `fojax.simulate` (``"vmap-simulate"``).
The strings are only the labels ``StudyResult.attrs`` records.
"""

from __future__ import annotations

import abc
import dataclasses

from ..simulation._save import METRIC_NAMES
from ..simulation._steppers import AbstractStepper, Exact, Exponential
from ._exact import exact_problem, exact_refusal, sample_metrics_traced
from ._exponential import exponential_metrics_traced, exponential_problem, exponential_schedule


#: The label of the per-sample path (every sample through `fojax.simulate`).
SIMULATE_LABEL = "vmap-simulate"


class AbstractStudyEngine(abc.ABC):
    """How a study runs on one batch stepper's kernel (module docstring)."""

    #: ``StudyResult.attrs["engine"]``
    label: str

    @abc.abstractmethod
    def problem(self, stepper, study, observers, *, settle_tol, keep, kinds=METRIC_NAMES, strict=False):
        """Host: ``((problem, basis, params), None)`` for `fojax.simulation._driver.run_batched`,
        or ``(None, reason)`` when the study does not qualify (with `strict`: raise
        `fojax.errors.InputError` saying why)."""

    @abc.abstractmethod
    def attrs(self, problem) -> dict:
        """``method`` and ``solver`` as ``StudyResult.attrs`` records them."""

    @abc.abstractmethod
    def resolve(self, stepper, study, observers, cfg):
        """Host: the `SimConfig` with which `study_loss` runs the concrete `study` on this
        kernel once the study is traced, or ``None`` when it does not qualify."""

    @abc.abstractmethod
    def loss_metrics(self, stepper, study, observers, cfg, mesh, metric: str):
        """Traced: the per-sample ``(metrics (1, K, B), success (B,))`` of `metric`,
        reverse-differentiable with respect to the observers, or ``None`` when the study
        does not qualify."""


class ExactEngine(AbstractStudyEngine):
    """`fojax.Exact`'s kernel: LTI samples driven by known signals (`fojax.studies._exact`)."""

    label = "exact-batch"

    def problem(self, stepper, study, observers, *, settle_tol, keep, kinds=METRIC_NAMES, strict=False):
        return exact_problem(study, observers, settle_tol, keep, kinds=kinds)

    def attrs(self, problem) -> dict:
        return dict(method="exact", solver="none (exact matrix-exponential stepping)")

    def resolve(self, stepper, study, observers, cfg):
        return cfg if exact_refusal(study, observers) is None else None  # decided on traced studies too

    def loss_metrics(self, stepper, study, observers, cfg, mesh, metric: str):
        if exact_refusal(study, observers) is not None:
            return None
        return sample_metrics_traced(study, observers, cfg.settle_tol, mesh, metric=metric)


class ExponentialEngine(AbstractStudyEngine):
    """`fojax.Exponential`'s kernel: time-varying affine samples (`fojax.studies._exponential`),
    with the stepper's step options; one device for the loss."""

    label = "exponential-batch"

    def problem(self, stepper, study, observers, *, settle_tol, keep, kinds=METRIC_NAMES, strict=False):
        return exponential_problem(study, observers, settle_tol, keep, strict=strict, options=stepper, kinds=kinds)

    def attrs(self, problem) -> dict:
        n_start, sub_start, substeps = problem.schedule
        return dict(method="exponential",
                    solver=f"ETDRK4, {substeps} steps per grid interval ({sub_start} in the first {n_start})")

    def resolve(self, stepper, study, observers, cfg):
        if cfg.devices is not None:
            return None
        schedule = exponential_schedule(study, observers, cfg.settle_tol, stepper)
        return None if schedule is None else dataclasses.replace(cfg, exponential_schedule=schedule)

    def loss_metrics(self, stepper, study, observers, cfg, mesh, metric: str):
        if mesh is not None:
            return None
        return exponential_metrics_traced(study, observers, cfg.settle_tol, options=stepper,
                                          schedule=cfg.exponential_schedule, metric=metric)


#: The study engine of each batch stepper class (`study_engine`).
ENGINES: dict[type, AbstractStudyEngine] = {Exact: ExactEngine(), Exponential: ExponentialEngine()}


def study_engine(stepper: AbstractStepper) -> AbstractStudyEngine:
    """The study engine of a batch candidate (an element of ``stepper.batch_candidates``)."""
    return ENGINES[type(stepper)]
