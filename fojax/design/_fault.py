r"""Simultaneous estimation of a functional and of faults (thesis §3.3.7, eq. 3.196)."""

from __future__ import annotations

import dataclasses
from operator import attrgetter
from typing import Any

import numpy as np

from .._errors import ShapeError
from ..plant import augment_faults, check_functional, DescriptorSystem
from . import _lmi
from ._base import AbstractDesign
from ._conditions import check_regular
from ._functional import check_kind, design_functional_observer, FunctionalObserverDesign


@dataclasses.dataclass(frozen=True)
class FaultEstimatorDesign(AbstractDesign):
    """A functional observer of the fault-augmented system that estimates ``[z; f]``.

    Attributes: `design` (the verified `FunctionalObserverDesign` on the augmented
    system), `augmented` (the augmented `DescriptorSystem` on ``[x; f]`` or
    ``[x; f; ḟ]``), `q` (rows of ``L``), `n_faults`, `ramp`.
    """

    design: FunctionalObserverDesign
    augmented: DescriptorSystem
    q: int
    n_faults: int
    ramp: bool

    # what every design has is that of the design on the augmented system
    observer = property(attrgetter("design.observer"))
    report = property(attrgetter("design.report"))
    region = property(attrgetter("design.region"))
    certificate = property(attrgetter("design.X"))
    kind = property(attrgetter("design.kind"))

    def verify(self):
        """Re-run the float64 verification of the augmented design
        (`fojax.design.AbstractDesign.verify`)."""
        return self.design.verify()

    def split(self, estimates):
        """Split estimates ``(..., q + n_f)`` into ``(ẑ, f̂)``."""
        estimates = np.asarray(estimates) if not hasattr(estimates, "at") else estimates
        return estimates[..., : self.q], estimates[..., self.q : self.q + self.n_faults]

    def __str__(self):
        return (
            f"fault estimator: z ({self.q} functions) and f ({self.n_faults} faults"
            f"{', ramp model' if self.ramp else ''}) from one {self.design.kind} observer\n"
            f"{self.design.report}"
        )


def design_fault_estimator(
    sys: DescriptorSystem,
    L,
    *,
    Fa=None,
    Fs=None,
    ramp: bool = False,
    kind: str = "generalized",
    region: Any = None,
    R=None,
    q0: int | None = None,
    q1: int | None = None,
    solver: str = _lmi.DEFAULT_SOLVER,
) -> FaultEstimatorDesign:
    r"""Design an observer of $[z; f]$ for $E\dot x = Ax + Bu + F_af$, $y = Cx + F_sf$.

    The faults are augmented into the state (`fojax.plant.augment_faults`: constant faults,
    or ramps with `ramp=True`, Remark 9) and the functional
    $\mathbf L = \operatorname{blkdiag}(L, I_{n_f})$ (eq. 3.196) is estimated by
    `design_functional_observer` (all of its arguments and errors apply). `L` may be an
    empty ``(0, n)`` matrix to estimate the faults only.

    **Returns:** a `FaultEstimatorDesign`; `split(estimates)` gives ``(ẑ, f̂)``.
    """
    L = np.asarray(check_functional(sys, L))
    check_kind(kind)
    # the augmented pencil is regular iff (E, A) is (det = det(sE - A) s^nf): name the plant
    check_regular(np.asarray(sys.E), np.asarray(sys.A), fname="design_fault_estimator")
    aug = augment_faults(sys, Fa=Fa, Fs=Fs, ramp=ramp)
    nf = (aug.n - sys.n) // (2 if ramp else 1)
    q = L.shape[0]
    L_aug = np.zeros((q + nf, aug.n))
    L_aug[:q, : sys.n] = L
    L_aug[q:, sys.n : sys.n + nf] = np.eye(nf)
    if R is not None and np.shape(R)[-1] != aug.n:
        raise ShapeError("R", ("q0", aug.n), tuple(np.shape(R)),
                         "R acts on the augmented state [x; f] (n + n_f columns).")
    d = design_functional_observer(aug, L_aug, kind=kind, region=region, R=R, q0=q0, q1=q1,
                                   solver=solver)
    return FaultEstimatorDesign(d, aug, q, nf, ramp)
