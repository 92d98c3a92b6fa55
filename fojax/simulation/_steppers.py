r"""Steppers: *how* `fojax.simulate` and `fojax.run_study` step a plant and its observers.

The stepping method is an argument object, as diffrax's ``diffeqsolve(terms, solver, …)``
takes its solver (and lineax's ``linear_solve`` its ``AutoLinearSolver``): one entry point,
several final classes of one abstract base, options as static fields (hashable: a stepper
is part of the compile key, and an equal stepper never recompiles).

| stepper | exact for | `simulate` | `run_study`: batch candidates, tried in order, then |
|---|---|---|---|
| `Exact()` | LTI plant and observers, uniform grid, input breakpoints on the grid | ✓ | ``(Exact(),)``, else every sample through `simulate` with `Exact()` |
| `Exponential(...)` | LTI observers; signals (δ(t), faults, inputs) entering the differential equations affinely, breakpoints on the step grid | ✗ (studies only) | ``(self,)``, else `fojax.errors.InputError` |
| `Diffrax(solver, rtol, atol, max_steps)` | any index-1 plant (nonlinear, Takagi–Sugeno, noise) to its tolerances | ✓ | every sample through `simulate` |
| `Auto(diffrax=Diffrax())` | picks the first of the above that is exact for the model | ✓ | ``(Exact(), Exponential())``, else every sample through `simulate` with this `Auto` |

`Auto` decides from the plant's *capabilities* (`linear_matrices()` of the plant and the
observers, the grid, the signals' `breakpoints()`), in one place: `Auto.select` for one
simulation, `AbstractStepper.batch_candidates` for the batch kernels a study tries, in
order (each checks on the host whether the study qualifies and says why not:
`fojax.studies._engines`, keyed by stepper class, since this floor does not know
studies), and `AbstractStepper.simulates` for whether the samples may then run through
`simulate`. An explicit stepper that is not exact for the model raises
`fojax.errors.InputError` naming the stepper and the reason.

The stepper is the only way to choose the method: the keywords it replaced (``method=``,
``solver=``, ``rtol=``, ``atol=``, ``max_steps=``) raise a `TypeError` naming the stepper to
pass instead (`removed_keywords`).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import numpy as np

from .._errors import InputError
from ..plant import UncertainDescriptorSystem
from ._reduction import is_concrete, lti_matrices


#: Relative tolerance on ``|ts_k − (t0 + k h)| / h`` for a grid to count as uniform.
UNIFORM_GRID_RTOL = 1e-9

class AbstractStepper(eqx.Module):
    """Base of the steppers (see the module docstring). Final subclasses: `Auto`, `Exact`,
    `Exponential`, `Diffrax`, and `Discrete` for discrete-time plants
    (`fojax.simulation._discrete`)."""

    #: the name of this stepper's method (recorded in ``StudyResult.attrs`` and `Solution.method`)
    method: ClassVar[str]
    #: whether a study's samples may each run through `fojax.simulate` with this stepper
    #: when none of its `batch_candidates` takes the study
    simulates: ClassVar[bool] = True

    @property
    def batch_candidates(self) -> tuple[AbstractStepper, ...]:
        """The steppers whose batch kernels `run_study` and `fojax.studies.study_loss` try,
        in order, before every sample runs through `fojax.simulate` (`simulates`); what
        each does with a study is `fojax.studies._engines`, keyed by the stepper's class."""
        return ()

    @property
    def diffrax_options(self) -> Diffrax:
        """The adaptive stepper used when this one falls back to diffrax (``Auto``) or, for
        the others, the defaults (unused by their own stepping)."""
        return Diffrax()

    @abc.abstractmethod
    def select(self, plant, observers, ts, u) -> AbstractStepper:
        """The stepper one `fojax.simulate` call runs with (`Exact` or `Diffrax`); raises
        `fojax.errors.InputError` when this stepper is not exact for the model."""


class Diffrax(AbstractStepper):
    """Adaptive stepping of the index-1 reduction with a diffrax solver (any plant).

    **Arguments:**

    - `solver`: a diffrax solver (default ``None``: `diffrax.Kvaerno5` with fojax's
      LAPACK-free `SmallLU`, stiff-safe and usable under `jax.vmap`/`jax.shard_map`; for
      non-stiff loops ``diffrax.Tsit5()`` compiles and runs much faster).
    - `rtol`, `atol`: tolerances of the `diffrax.PIDController`.
    - `max_steps`: step budget of one simulation.
    """

    solver: object = eqx.field(static=True, default=None)
    rtol: float = eqx.field(static=True, default=1e-8)
    atol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=100_000)

    method: ClassVar[str] = "diffrax"

    def __check_init__(self):
        for name in ("rtol", "atol"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float | np.floating) or not v > 0:
                raise InputError(f"Diffrax({name}=...) must be a positive float, got {v!r}.")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int | np.integer) or self.max_steps < 1:
            raise InputError(f"Diffrax(max_steps=...) must be a positive integer, got {self.max_steps!r}.")

    @property
    def diffrax_options(self) -> Diffrax:
        return self

    def select(self, plant, observers, ts, u) -> AbstractStepper:
        return self


class Exact(AbstractStepper):
    r"""Exact matrix-exponential stepping of an LTI loop on a uniform grid.

    One simulation: the joint slow ODE is discretised once (``expm`` of a Van Loan matrix
    with product Gauss–Legendre weights for the input; exact for inputs that are
    polynomials of degree < 4 between grid points) and stepped with `jax.lax.scan` (see
    `fojax.simulate`). A study: the batch-last blocked kernel with the metrics accumulated
    in the time loop (`fojax.studies._exact`), for LTI samples driven by known signals.
    Needs an LTI plant (`linear_matrices()`), LTI observers and a uniform grid.
    """

    method: ClassVar[str] = "exact"

    @property
    def batch_candidates(self) -> tuple[AbstractStepper, ...]:
        return (self,)

    def select(self, plant, observers, ts, u) -> AbstractStepper:
        cap = capabilities(plant, observers, ts, u)
        if not cap["lti"]:
            raise InputError(
                f"stepper Exact() needs a linear time-invariant plant (DescriptorSystem, or "
                f"UncertainDescriptorSystem with a Constant δ); got {type(plant).__name__}. "
                "Use stepper=Diffrax() (or Auto())."
            )
        if not cap["observers_lti"]:
            bad = [type(o).__name__ for o in observers if o.linear_matrices() is None]
            raise InputError(
                f"stepper Exact() needs LTI observers (linear_matrices() not None); {bad} are not. "
                "Use stepper=Diffrax() (or Auto())."
            )
        if not cap["uniform"]:
            raise InputError(
                "stepper Exact() steps on a uniform grid with one matrix exponential "
                f"expm(As·h); ts is not uniform (max |ts_k − (t0 + k h)| / h = {cap['deviation']:.2e} > "
                f"{UNIFORM_GRID_RTOL:.0e}). Use ts = jnp.linspace(t0, t1, T), or "
                "stepper=Diffrax() for non-uniform output times."
            )
        return self


class Exponential(AbstractStepper):
    r"""Exponential integrator (Krogstad's ETDRK4) for time-varying affine studies.

    For samples that vary in time only through signals entering the index-1 plant's
    differential equations affinely (a time-varying δ(t), `FaultyPlant` faults, known
    inputs) with LTI observers: the nominal loop is integrated exactly, the rest by fixed
    steps of ``h / s`` (``h`` the study grid's step). Runs inside `run_study` and
    `fojax.studies.study_loss` (`fojax.studies._exponential`); not available for one
    `simulate` call (use `Auto()` or `Diffrax()` there).

    **Arguments:**

    - `step_rate`: largest step × rate: ``s`` is the smallest integer with
      ``(h/s)·ρ ≤ step_rate``, ``ρ`` the larger of the nominal loop's fastest mode
      ``|λ|max`` and the fastest `fojax.Sine` signal's angular frequency (default 0.5).
    - `startup_factor`: the steps over the initial layer (``⌈5/(|λ|max h)⌉`` grid
      intervals) are this many times smaller (default 2).
    - `substeps`: fix ``s`` instead of choosing it from `step_rate` (default ``None``).

    Fixed steps, no error control: the accuracy is checked by halving the step (module
    docstring of `fojax.studies._exponential`), not bounded.
    """

    step_rate: float = eqx.field(static=True, default=0.5)
    startup_factor: int = eqx.field(static=True, default=2)
    substeps: int | None = eqx.field(static=True, default=None)

    method: ClassVar[str] = "exponential"
    simulates: ClassVar[bool] = False  # no `simulate` path: a study it cannot run is refused

    @property
    def batch_candidates(self) -> tuple[AbstractStepper, ...]:
        return (self,)

    def __check_init__(self):
        if isinstance(self.step_rate, bool) or not isinstance(self.step_rate, int | float) or not self.step_rate > 0:
            raise InputError(f"Exponential(step_rate=...) must be a positive float, got {self.step_rate!r}.")
        for name in ("startup_factor", "substeps"):
            v = getattr(self, name)
            if v is None and name == "substeps":
                continue
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise InputError(f"Exponential({name}=...) must be a positive integer, got {v!r}.")

    def schedule(self, rate: float, h: float) -> tuple[int, int]:
        """``(substeps, substeps over the initial layer)`` for the loop's rate ``ρ`` and grid step ``h``."""
        import math

        s = self.substeps if self.substeps is not None else max(1, math.ceil(rate * h / self.step_rate))
        return int(s), int(self.startup_factor) * int(s)

    def select(self, plant, observers, ts, u) -> AbstractStepper:
        raise InputError(
            "stepper Exponential() runs studies (run_study, study_loss) only, not one simulate call; "
            "use stepper=Auto() (exact for LTI loops) or Diffrax() in simulate."
        )


class Auto(AbstractStepper):
    """The fastest stepper that is exact for the model (the one place that decides).

    - One simulation (`Auto.select`): `Exact()` when the plant and every observer are LTI
      (`linear_matrices()`), the grid is uniform and the breakpoints of the input (and of
      a time-varying δ) lie on it; otherwise `diffrax`. When ``ts`` or the breakpoints are
      traced they cannot be inspected and the grid is assumed uniform (a non-uniform
      traced grid then fails at run time).
    - A study (`run_study`, `study_loss`): the exact batch kernel if the study qualifies,
      else the exponential integrator (`Exponential()`: time-varying affine samples), else
      every sample through `fojax.simulate` with this `Auto` (engines in that order).

    **Arguments:**

    - `diffrax`: the `Diffrax` stepper used when nothing exact applies (default
      ``Diffrax()``).
    """

    diffrax: Diffrax = eqx.field(static=True, default=Diffrax())

    method: ClassVar[str] = "auto"

    @property
    def batch_candidates(self) -> tuple[AbstractStepper, ...]:
        return (Exact(), Exponential())

    def __check_init__(self):
        if not isinstance(self.diffrax, Diffrax):
            raise InputError(f"Auto(diffrax=...) must be a fojax.Diffrax stepper, got {type(self.diffrax).__name__}.")

    @property
    def diffrax_options(self) -> Diffrax:
        return self.diffrax

    def select(self, plant, observers, ts, u) -> AbstractStepper:
        if getattr(plant, "dt", None) is not None:  # a discrete-time plant (fojax.simulation._discrete)
            from ._discrete import Discrete

            return Discrete().select(plant, observers, ts, u)
        cap = capabilities(plant, observers, ts, u)
        exact = cap["lti"] and cap["observers_lti"] and cap["uniform"] and cap["on_grid"]
        return Exact() if exact else self.diffrax


def grid_deviation(t) -> tuple[float, float]:
    """``(max_k |t_k − (t_0 + k h)| / h, h)`` of a concrete grid ``t`` with ``h = (t_{T-1} − t_0)/(T − 1)``
    (``inf`` deviation when ``h ≤ 0``): the one uniform-grid test on the host (a grid is
    uniform when the deviation is ``≤ UNIFORM_GRID_RTOL``), used by `Auto`/`Exact`, the
    batch kernels' entries and the studies' engines."""
    t = np.asarray(t)
    T = t.shape[0]
    h = float((t[-1] - t[0]) / (T - 1))
    if not h > 0:
        return float("inf"), h
    return float(np.max(np.abs(t - (t[0] + np.arange(T) * h))) / h), h


def grid_deviation_traced(ts):
    """`grid_deviation` of a grid that may be traced (`jax.numpy`): ``(deviation, h)`` as arrays
    (no special value for ``h ≤ 0``: the caller tests ``h > 0``)."""
    import jax.numpy as jnp

    T = ts.shape[0]
    h = (ts[-1] - ts[0]) / (T - 1)
    k = jnp.arange(T, dtype=ts.dtype)
    return jnp.max(jnp.abs(ts - (ts[0] + k * h))) / h, h


def _breakpoints(plant, u) -> list:
    bps = [u.breakpoints()]
    if isinstance(plant, UncertainDescriptorSystem):
        bps.append(plant.delta.breakpoints())
    return bps


def capabilities(plant, observers, ts, u) -> dict:
    """What `Auto` and `Exact` decide from: ``lti`` (the plant has `linear_matrices`),
    ``observers_lti``, ``uniform`` (grid, within `UNIFORM_GRID_RTOL`; ``True`` when ``ts``
    is traced), ``on_grid`` (concrete breakpoints of the input and of δ on the grid) and
    the grid's relative ``deviation``."""
    lti = lti_matrices(plant) is not None
    obs_lin = all(o.linear_matrices() is not None for o in observers)
    uniform, on_grid, dev = True, True, 0.0
    if is_concrete(ts):
        # NumPy, not jax.numpy: inside an outer `jax.jit` jnp operations on a concrete
        # ts return tracers, and float() of them would fail.
        t = np.asarray(ts)
        dev, h = grid_deviation(t)
        uniform = dev <= UNIFORM_GRID_RTOL
        bps = [b for b in _breakpoints(plant, u) if is_concrete(b)]
        if uniform and bps:
            b = np.concatenate([np.asarray(v).ravel() for v in bps])
            t0, t1 = float(t[0]), float(t[-1])
            b = b[(b > t0) & (b < t1)]
            k = (b - t0) / h
            on_grid = bool(np.all(np.abs(k - np.round(k)) <= 1e-9 * np.maximum(1.0, k)))
    return dict(lti=lti, observers_lti=obs_lin, uniform=uniform, on_grid=on_grid, deviation=dev)


def resolve_stepper(stepper, *, who: str) -> AbstractStepper:
    """`stepper` (``None``: `Auto()`); `fojax.errors.InputError` when it is not a stepper."""
    if stepper is None:
        return Auto()
    if not isinstance(stepper, AbstractStepper):
        raise InputError(f"{who}(stepper=...) must be fojax.Auto(), Exact(), Exponential(...) or Diffrax(...); "
                         f"got {type(stepper).__name__}.")
    return stepper
