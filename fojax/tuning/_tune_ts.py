"""`tune_takagi_sugeno`: kept for its callers; `fojax.tuning.tune` tunes T-S designs itself."""

from __future__ import annotations

from ..design._tunable import CommonCertificate
from ._tune import tune, TuneResult


def tune_takagi_sugeno(design, train_study, **options) -> TuneResult:
    """``tune(design, train_study, parameterization=CommonCertificate, **options)``.

    A thin wrapper kept for existing callers: `fojax.tuning.tune` takes
    `fojax.design.TakagiSugenoObserverDesign` directly (its default parameterization for
    them is `fojax.design.CommonCertificate`). Every keyword of `tune` is accepted.
    """
    options.setdefault("parameterization", CommonCertificate)
    return tune(design, train_study, **options)
