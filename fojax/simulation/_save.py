r"""What to save: `Trajectory()` (one simulation's states and estimates) or `Metrics(...)`
(per-sample error metrics of a study, optionally with time-wise quantile `Bands`).

Like diffrax's ``SaveAt``, the object says what the loop keeps, not how it steps (that is
the stepper's job, `fojax.simulation._steppers`).

**The metric vocabulary** (one table for every engine; $e = \hat z - z$ per estimated
signal on the grid $t_0 < \dots < t_{T-1}$, integrals by the trapezoidal rule on the grid;
`error_metrics` is the definition, the batch kernels accumulate the same sums inside the
time loop):

| name | per signal (``reduce="none"``) | ``reduce="sum"`` (over signals) |
|---|---|---|
| ``"iae"`` | $\int \lvert e_i\rvert\,dt$ | $\int \lVert e\rVert_1\,dt$ |
| ``"ise"`` | $\int e_i^2\,dt$ | $\int \lVert e\rVert_2^2\,dt$ |
| ``"itae"`` | $\int (t - t_0)\lvert e_i\rvert\,dt$ | $\int (t-t_0)\lVert e\rVert_1\,dt$ |
| ``"peak"`` | $\max_k \lvert e_i(t_k)\rvert$ | – (not a sum) |
| ``"settling_time"`` | first $t_k - t_0$ after which $\lvert e_i\rvert \le$ `settle_tol` for good ($0$ if never above, $+\infty$ if above at $t_{T-1}$) | – |

The sums are exact identities of the per-signal values (the trapezoid rule is linear), so
``reduce="sum"`` equals summing the per-signal metrics over the signal axis.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._errors import InputError


#: The metric names of `Metrics` and `error_metrics`, in this order.
METRIC_NAMES = ("iae", "ise", "itae", "peak", "settling_time")
#: Metrics whose sum over signals is the integral of a norm of the error (``reduce="sum"``).
SUMMABLE = ("iae", "ise", "itae")
#: Default number of time points of the quantile bands.
DEFAULT_BAND_POINTS = 201
DEFAULT_QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)


class AbstractSave(eqx.Module):
    """Base of what a simulation or study keeps: `Trajectory`, `Metrics`."""


class Trajectory(AbstractSave):
    """Keep the states, outputs and estimates on the output grid ``ts``: `fojax.simulate`
    returns a `fojax.simulation.Solution` (its default and only save for one simulation)."""


class Bands(eqx.Module):
    """Time-wise quantiles of the error over all samples of a study (confidence bands).

    **Arguments:**

    - `quantiles`: levels in ``[0, 1]`` (default 0.05, 0.25, 0.5, 0.75, 0.95).
    - `points`: most time points of the bands (default 201): the errors are kept on
      ``ts[::k]`` with the smallest ``k`` giving at most `points` points, and the bands
      are exactly ``np.quantile`` there; ``None``: every grid point.
    """

    quantiles: tuple[float, ...] = eqx.field(static=True, default=DEFAULT_QUANTILES)
    points: int | None = eqx.field(static=True, default=DEFAULT_BAND_POINTS)

    def __init__(self, quantiles=DEFAULT_QUANTILES, points=DEFAULT_BAND_POINTS):
        qs = tuple(float(q) for q in np.atleast_1d(np.asarray(quantiles, dtype=float)))
        if not qs or not all(0.0 <= q <= 1.0 for q in qs):
            raise InputError(f"Bands(quantiles=...) must be a non-empty sequence of levels in [0, 1]; got {quantiles!r}.")
        if points is not None and (isinstance(points, bool) or not isinstance(points, int | np.integer)
                                   or points < 2):
            raise InputError(f"Bands(points=...) must be an integer >= 2 or None (every grid point); got {points!r}.")
        self.quantiles = qs
        self.points = None if points is None else int(points)


class Metrics(AbstractSave):
    """Per-sample error metrics of a study, accumulated inside the time loop (module table).

    **Arguments:**

    - `kinds`: metric names from ``"iae", "ise", "itae", "peak", "settling_time"``
      (default all five); `fojax.StudyResult.metrics` holds these (and ``"success"``).
      The exact and exponential batch engines accumulate only these in the time loop
      (plus the peak when no integral is named: the finiteness of the accumulated
      metrics is the success test); the ``"vmap-simulate"``
      engine computes all five from each trajectory and keeps these.
    - `settle_tol`: tolerance of the settling time (default 0.05).
    - `reduce`: ``"none"`` (one value per estimated signal, default) or ``"sum"`` (summed
      over the signals, for ``"iae"``, ``"ise"``, ``"itae"`` only: the integrals of
      $\\lVert e\\rVert_1$, $\\lVert e\\rVert_2^2$, $(t-t_0)\\lVert e\\rVert_1$); those
      metrics then have no signal axis (``(observer, uncertainty, fault)`` in `run_study`).
    - `bands`: `Bands` (default ``Bands()``) or ``None`` (no trajectories kept).
    """

    kinds: tuple[str, ...] = eqx.field(static=True, default=METRIC_NAMES)
    settle_tol: float = eqx.field(static=True, default=0.05)
    reduce: str = eqx.field(static=True, default="none")
    bands: Bands | None = eqx.field(static=True, default=Bands())

    def __init__(self, kinds=METRIC_NAMES, settle_tol=0.05, reduce="none", bands=Bands()):
        kinds = (kinds,) if isinstance(kinds, str) else tuple(kinds)
        bad = [k for k in kinds if k not in METRIC_NAMES]
        if not kinds or bad:
            raise InputError(f"Metrics(kinds=...) must name metrics from {METRIC_NAMES}; got {bad or kinds!r}.")
        if reduce not in ("none", "sum"):
            raise InputError(f"Metrics(reduce=...) must be 'none' or 'sum', got {reduce!r}.")
        if reduce == "sum" and any(k not in SUMMABLE for k in kinds):
            raise InputError(
                f"Metrics(reduce='sum') sums over signals, defined for {SUMMABLE} only; got kinds {kinds}. "
                "Drop 'peak'/'settling_time' or use reduce='none'."
            )
        if isinstance(settle_tol, bool) or not isinstance(settle_tol, int | float) or not settle_tol >= 0:
            raise InputError(f"Metrics(settle_tol=...) must be a float >= 0, got {settle_tol!r}.")
        if bands is not None and not isinstance(bands, Bands):
            raise InputError(f"Metrics(bands=...) must be fojax.Bands(...) or None, got {type(bands).__name__}.")
        self.kinds, self.settle_tol, self.reduce, self.bands = kinds, float(settle_tol), reduce, bands


def as_save(quantiles=DEFAULT_QUANTILES, band_points=DEFAULT_BAND_POINTS, settle_tol=0.05) -> Metrics:
    """The `Metrics` that `run_study`'s legacy keywords name (the one mapping):
    ``quantiles=()`` → no bands; else ``Bands(quantiles, band_points)``."""
    bands = Bands(quantiles, band_points) if len(tuple(quantiles)) > 0 else None
    return Metrics(settle_tol=settle_tol, bands=bands)


class _Unset:
    """Marks a legacy keyword the caller did not pass (``None`` is a value of `band_points`)."""

    def __repr__(self):
        return "UNSET"


UNSET = _Unset()


def resolve_save(save, quantiles=UNSET, band_points=UNSET, settle_tol=UNSET, *, who: str) -> Metrics:
    """`save`, or the `Metrics` the legacy keywords name (`as_save`; unset ones take its
    defaults); `fojax.errors.InputError` when both are given or `save` is not `Metrics`."""
    legacy = dict(quantiles=quantiles, band_points=band_points, settle_tol=settle_tol)
    given = {k: v for k, v in legacy.items() if v is not UNSET}
    if save is None:
        return as_save(**given)
    if not isinstance(save, Metrics):
        raise InputError(f"{who}(save=...) must be fojax.Metrics(...) (a study saves metrics; one trajectory is "
                         f"fojax.simulate's Trajectory()); got {type(save).__name__}.")
    if given:
        raise InputError(f"{who}: pass either save= or the legacy keywords {sorted(given)}, not both (e.g. "
                         "save=fojax.Metrics(settle_tol=..., bands=fojax.Bands(quantiles=..., points=...))).")
    return save


def error_metrics(ts, e, settle_tol: float = 0.05) -> dict[str, Array]:
    r"""IAE, ISE, ITAE, peak and settling time of errors ``e`` ``(T, q)`` on the grid ``ts``
    (the definitions of the module table, per signal).

    Trapezoidal rule on the grid; settling time: first grid time ``t_k - t_0`` after
    which ``|e| ≤ settle_tol`` for good (``inf`` if violated at the last time).
    """
    a = jnp.abs(e)
    dt = jnp.diff(ts)[:, None]
    tr = ts - ts[0]

    def trap(v):
        return jnp.sum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)

    above = a > settle_tol
    T = ts.shape[0]
    k = jnp.arange(T)[:, None]
    last = jnp.max(jnp.where(above, k, -1), axis=0)
    settle = jnp.where(last < 0, 0.0, jnp.where(last == T - 1, jnp.inf, tr[jnp.minimum(last + 1, T - 1)]))
    return {
        "iae": trap(a),
        "ise": trap(e**2),
        "itae": trap(tr[:, None] * a),
        "peak": jnp.max(a, axis=0),
        "settling_time": settle,
    }
