r"""`simulate`: plants and observers on an output grid, exact (LTI) or with diffrax.

The method is a stepper object (`fojax.simulation._steppers`): ``"exact"`` below is
`fojax.Exact()`, ``"diffrax"`` is `fojax.Diffrax(solver, rtol, atol, max_steps)`, and
`fojax.Auto()` (the default) picks between them; `Solution.method` records the name of
the one that ran.

Both methods work in the SVD coordinates of ``E`` described in
`fojax.simulation._reduction` (full-size coordinates with a slow mask, so that
shapes never depend on ``rank E`` and plants built inside `jax.jit`/`jax.vmap`
work).

- ``"exact"`` (linear time-invariant plant and observers): the joint system is
  reduced to its slow ODE $\dot w = \mathcal A w + \mathcal B u$ and stepped on the
  uniform output grid with the matrix exponential. The input enters through the
  convolution integral over each interval $[t_k, t_k + h]$,

  $$w_{k+1} = e^{\mathcal A h} w_k + \int_0^h e^{\mathcal A (h - s)}\mathcal B\,u(t_k + s)\,\mathrm ds,$$

  which is evaluated by *product Gauss–Legendre integration*: ``u`` is sampled at
  the $\nu = 4$ Gauss–Legendre nodes of the interval, replaced by its interpolating
  polynomial, and that polynomial is integrated against the matrix exponential
  exactly (one augmented `expm` of size $N + \nu m$, Van Loan's construction). The
  matrices are computed once per call; the time loop is a `jax.lax.scan`.
  Accuracy: exact (to round-off) for inputs that are polynomials of degree
  $< \nu$ on each grid interval — zero, constant, and `Step`/`Ramp`/
  `PiecewiseConstant` signals whose switching times lie on the grid; for smooth
  inputs the local error is $O(h^{2\nu+1}\,\|u^{(2\nu)}\|)$ (the superconvergence of
  Gauss points), globally $O(h^8)$ (the order of the 4-point Gauss rule): on example
  4.1.3 with a sine input, ~3e-11 relative error at $\omega h = 1$ and ~2e-13 at
  $\omega h = 0.5$. A jump
  *between* grid points costs $O(h)$ on that interval — `fojax.Auto` then uses
  diffrax.
- ``"diffrax"`` (everything else): the slow coordinates (and observer states) are
  integrated with an adaptive stiff solver (default `diffrax.Kvaerno5`, its Newton
  steps solved by `fojax.simulation._implicit.SmallLU`, with a
  `diffrax.PIDController`); the fast coordinates are solved from the algebraic
  equations at every right-hand-side evaluation (one linear solve, or warm-started
  Newton for nonlinear plants) and again at every output time, so the returned
  trajectory satisfies the constraints to round-off whatever the integration
  error. Breakpoints of the input (and of a time-varying uncertainty) are passed
  as ``jump_ts``.

For nonlinear plants the diffrax state also carries the fast coordinates as a
*warm start* for Newton: they evolve with the implicit-function-theorem rate
$\dot x_2 = -J_{22}^{-1}(\partial_t h + J_{21}\dot x_1)$, are excluded from error
control, and carry no derivative information (the returned $x_2$ is always the
Newton solution, whose derivative is the implicit-function one).

Gradients: reverse mode through `lax.scan` and `expm` (exact) or through diffrax's
default `RecursiveCheckpointAdjoint` (diffrax). Only ``E`` receives no gradient
(see `fojax.simulation._reduction`).
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._dtype import as_float_array
from .._errors import InputError, removed_keywords, ShapeError
from .._small_linalg import solve_small
from ..observer import AbstractObserver
from ..plant import AbstractPlant, AbstractSignal, as_signal
from ._discretize import discretize, step_exact
from ._implicit import default_implicit_solver
from ._joint import joint_matrices
from ._reduction import (
    check_x0,
    constraint_residual_norm,
    host_initial_checks,
    is_concrete,
    lti_feedthrough,
    lti_matrices,
    project_initial_state,
    RHS_NEWTON_ITERS,
    slow_rate,
    solve_fast,
    svd_split,
    SVDSplit,
)
from ._save import Trajectory
from ._solution import Solution
from ._steppers import (  # noqa: F401
    _breakpoints,
    AbstractStepper,
    grid_deviation_traced,
    resolve_stepper,
    UNIFORM_GRID_RTOL,
)


#: Number of traces of the compiled simulation core (tests use it to prove that a
#: second call with new numbers does not recompile).
TRACE_COUNTS: collections.Counter = collections.Counter()

#: A projected initial state must satisfy the constraints to this relative level.
IC_RESIDUAL_RTOL = 1e-8


@dataclasses.dataclass(frozen=True)
class _Config:
    method: str
    rtol: float
    atol: float
    max_steps: int
    throw: bool
    strict: bool
    consistency_tol: float
    runtime_checks: bool  # inputs traced: checks that could not run on the host run in XLA


# --------------------------------------------------------------------------- public entry


@removed_keywords
def simulate(
    plant: AbstractPlant,
    x0,
    ts,
    u=None,
    *,
    observers: Sequence[AbstractObserver] = (),
    observer_x0=None,
    stepper: AbstractStepper | None = None,
    save: Trajectory | None = None,
    strict: bool = False,
    consistency_tol: float = 1e-10,
    throw: bool = True,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> Solution:
    r"""Simulate a descriptor plant, and observers driven by its input and output.

    $$E\dot x = f(t, x, u),\quad y = g(t, x, u),\qquad
      \dot\xi_i = \phi_i(t, \xi_i, u, y),\quad \hat z_i = \psi_i(t, \xi_i, u, y).$$

    The plant must be regular and impulse-free (index 1); ``x0`` is made consistent
    by keeping its slow part (see `fojax.simulation.consistent_initial_condition`). See the
    module docstring for the two methods and their accuracy.

    **Arguments:**

    - `plant`: any `fojax.plant.AbstractPlant`. A discrete-time plant (``dt`` set) is stepped on its
      samples ``ts = t0 + k dt`` by `fojax.simulation.Discrete` (with observers of the same
      ``dt``).
    - `x0`: ``(n,)`` initial state at ``ts[0]`` (projected onto the constraints
      unless `strict`).
    - `ts`: ``(T,)`` increasing output times, ``T ≥ 2``; ``ts[0]`` is the initial time.
      `fojax.Exact` needs a uniform grid (e.g. `jnp.linspace`).
    - `u`: input signal (`fojax.plant.AbstractSignal`), a constant ``(m,)`` vector, or
      ``None`` (zero).
    - `observers`: a sequence of `fojax.observer.AbstractObserver`, integrated together with
      the plant.
    - `observer_x0`: one initial state per observer (``None``: each observer's
      `initial_state()`).
    - `stepper`: how to step (`fojax.simulation._steppers`): `fojax.Auto()` (default:
      `fojax.Exact()` when the plant is a `DescriptorSystem` or an
      `UncertainDescriptorSystem` with constant ``δ``, every observer has
      `linear_matrices()`, the grid is uniform and the input's breakpoints lie on
      it; its `fojax.Diffrax` otherwise), `fojax.Exact()` or `fojax.Diffrax(solver,
      rtol, atol, max_steps)` (default solver: `diffrax.Kvaerno5`, stiff-safe, whose
      Newton step uses fojax's LAPACK-free `SmallLU`, so that it also runs inside
      `jax.vmap` and `jax.shard_map` — see `fojax.simulation._implicit`; a plain
      ``diffrax.Kvaerno5()`` fails inside `fojax.studies.run_study`). When ``ts`` (or
      the input's breakpoints) are traced, `Auto` cannot inspect them and assumes a
      uniform grid; a non-uniform traced grid then fails at run time (``throw``) or
      sets ``stats["success"] = False``. `fojax.Exponential` runs studies only.
    - `save`: `fojax.Trajectory()` (the default and only choice here: states, outputs
      and estimates on ``ts``).
    - `strict`: raise `fojax.errors.InconsistentInitialConditionError` when
      ``‖U2ᵀ f(t0, x0, u0)‖ > consistency_tol`` instead of projecting.
    - `throw`: raise on solver failure or non-finite results; with ``False`` check
      ``sol.stats["success"]`` (use ``False`` under `jax.vmap` if some samples may
      fail).
    - `adjoint`: diffrax adjoint (default `diffrax.RecursiveCheckpointAdjoint()`,
      reverse mode; use `diffrax.ForwardMode()` for `jax.jacfwd`).

    **Returns:** a `fojax.simulation.Solution`.

    **Raises:** `TypeError` for the keywords the stepper replaced (``method``, ``solver``,
    ``rtol``, ``atol``, ``max_steps``; the message names the stepper to pass),
    `fojax.errors.ShapeError` (shapes of ``x0``, ``u``, observer states),
    `fojax.errors.IrregularSystemError`, `fojax.errors.ImpulsiveSystemError`,
    `fojax.errors.InconsistentInitialConditionError` (`strict`), `fojax.errors.InputError` (bad
    grid, stepper or save). Structural checks run on the host whenever the inputs are
    concrete arrays; under `jax.vmap`/`jax.grad` they run inside XLA (`throw=True`)
    with the same meaning but as `equinox` runtime errors.

    Compilation happens once per *structure* (types, shapes, static fields, the
    stepper); new numbers reuse the compiled code. Batch with `jax.vmap`
    (write the single-trajectory call inside), differentiate with `jax.grad`.

    !!! example

        ```python
        sys = fojax.DescriptorSystem(E, A + B @ L, B)
        ts = jnp.linspace(0.0, 5.0, 501)
        sol = fojax.simulate(sys, x0, ts, fojax.Step(jnp.array([1.0, 0.0]), 0.5))
        sol.xs, sol.stats["constraint_residual"]
        ```
    """
    if not isinstance(plant, AbstractPlant):
        raise InputError(f"plant must be a fojax.plant.AbstractPlant, got {type(plant).__name__}.")
    stepper = resolve_stepper(stepper, who="simulate")
    if save is not None and not isinstance(save, Trajectory):
        raise InputError(
            f"simulate(save=...) keeps one trajectory: save=fojax.Trajectory() (the default); got "
            f"{type(save).__name__}. Metrics need a target z = Lx and run on studies: "
            "fojax.run_study(fojax.Study(plant, x0, ts, L, ...), observers, save=fojax.Metrics(...))."
        )
    x0 = check_x0(plant, x0)
    ts = _check_ts(ts)
    u = as_signal(u, plant.m)
    observers, xi0s = _check_observers(observers, observer_x0)
    concrete = is_concrete(plant, x0, u)
    host_initial_checks(plant, x0, ts[0], u, strict=strict, tol=consistency_tol)
    if getattr(plant, "dt", None) is not None:  # discrete time: fojax.simulation._discrete
        from ._discrete import discrete_stepper, simulate_discrete

        discrete_stepper(plant, stepper).select(plant, observers, ts, u)
        return simulate_discrete(plant, x0, ts, u, observers, xi0s, throw=throw)
    chosen = stepper.select(plant, observers, ts, u)  # Exact() or a Diffrax (fojax.simulation._steppers)
    opts = chosen.diffrax_options
    solver = default_implicit_solver() if opts.solver is None else opts.solver
    if adjoint is None:
        adjoint = diffrax.RecursiveCheckpointAdjoint()
    runtime_checks = not (concrete and is_concrete(ts))
    # `strict` was enforced on the host when possible; it only enters the compiled
    # code (and its cache key) when it must be checked at run time.
    runtime_strict = bool(strict) and runtime_checks
    cfg = _Config(
        method=chosen.method,
        rtol=float(opts.rtol),
        atol=float(opts.atol),
        max_steps=int(opts.max_steps),
        throw=bool(throw),
        strict=runtime_strict,
        consistency_tol=float(consistency_tol) if runtime_strict else 0.0,
        runtime_checks=runtime_checks,
    )
    return _simulate_core(plant, x0, ts, u, observers, xi0s, solver, adjoint, cfg)


# --------------------------------------------------------------------------- validation


def _check_ts(ts):
    ts = as_float_array("ts", ts, ndim=1)
    if ts.shape[0] < 2:
        raise ShapeError("ts", "(T,) with T >= 2", tuple(ts.shape), "ts[0] is the initial time.")
    if is_concrete(ts):
        d = np.diff(np.asarray(ts))
        if not np.all(d > 0):
            k = int(np.argmax(~(d > 0)))
            raise InputError(
                f"ts must be strictly increasing; ts[{k}] = {float(ts[k])} and "
                f"ts[{k + 1}] = {float(ts[k + 1])}."
            )
    return ts


def _check_observers(observers, observer_x0):
    if isinstance(observers, AbstractObserver):
        observers = (observers,)
    observers = tuple(observers)
    for i, o in enumerate(observers):
        if not isinstance(o, AbstractObserver):
            raise InputError(
                f"observers[{i}] is a {type(o).__name__}, not a fojax.observer.AbstractObserver."
            )
    if observer_x0 is None:
        xi0s = tuple(o.initial_state() for o in observers)
    else:
        if isinstance(observer_x0, jax.Array | np.ndarray) and len(observers) == 1:
            observer_x0 = (observer_x0,)
        observer_x0 = tuple(observer_x0)
        if len(observer_x0) != len(observers):
            raise ShapeError(
                "observer_x0",
                f"{len(observers)} initial states",
                f"{len(observer_x0)}",
                "Pass one initial state per observer.",
            )
        xi0s = observer_x0
    out = []
    for i, (o, xi0) in enumerate(zip(observers, xi0s)):
        xi0 = as_float_array(f"observer_x0[{i}]", xi0)
        if xi0.shape != (o.state_size,):
            raise ShapeError(f"observer_x0[{i}]", (o.state_size,), tuple(xi0.shape))
        out.append(xi0)
    return observers, tuple(out)


# --------------------------------------------------------------------------- core


@eqx.filter_jit
def _simulate_core(plant, x0, ts, u, observers, xi0s, solver, adjoint, cfg: _Config):
    TRACE_COUNTS["simulate"] += 1
    split = svd_split(plant.E)
    t0 = ts[0]
    u0 = u(t0)
    x0c, dist, res0 = project_initial_state(plant, split, t0, x0, u)
    if cfg.method == "exact":
        out = _exact(plant, split, x0, ts, u, observers, xi0s, cfg)
    else:
        out = _diffrax(plant, split, x0c, ts, u, observers, xi0s, solver, adjoint, cfg)
    xs, xis, solver_stats = out
    us = jax.vmap(u)(ts)
    ys = jax.vmap(plant.output)(ts, xs, us)
    estimates = tuple(
        jax.vmap(o.output)(ts, xi, us, ys) for o, xi in zip(observers, xis)
    )
    residuals = jax.vmap(lambda t, x, ut: constraint_residual_norm(plant, split, t, x, ut))(
        ts, xs, us
    )
    stats = dict(
        constraint_residual=jnp.max(residuals),
        initial_residual=res0,
        projection_distance=dist,
        **solver_stats,
    )
    if cfg.throw:
        x_first = lax.stop_gradient(xs[0])
        scale = jnp.maximum(
            1.0, jnp.maximum(jnp.linalg.norm(x_first), jnp.linalg.norm(plant.rhs(t0, x_first, u0)))
        )
        xs = eqx.error_if(
            xs,
            ~(residuals[0] <= IC_RESIDUAL_RTOL * scale),
            "fojax.simulate: could not make x0 consistent (the algebraic equations "
            "U2ᵀ f(t0, x, u0) = 0 were not solved; Newton did not converge from the "
            "given x0, or the algebraic Jacobian is singular: index > 1). Pass an x0 "
            "closer to the constraint set.",
        )
        xs = eqx.error_if(
            xs,
            ~jnp.all(jnp.isfinite(xs)),
            "fojax.simulate produced non-finite states: the plant may be impulsive "
            "(index > 1) or irregular for these parameters (checked on the host only "
            "for concrete inputs), or the solution blows up.",
        )
    if cfg.strict:
        xs = eqx.error_if(
            xs,
            res0 > cfg.consistency_tol,
            "x0 violates the algebraic constraints and strict=True (runtime check).",
        )
    return Solution(
        ts=ts,
        xs=xs,
        ys=ys,
        us=us,
        observer_states=tuple(xis),
        estimates=estimates,
        stats=stats,
        method=cfg.method,
    )


# --------------------------------------------------------------------------- exact LTI


def _exact(plant, split: SVDSplit, x0, ts, u, observers, xi0s, cfg: _Config):
    A, B, C = lti_matrices(plant)
    n = A.shape[0]
    T = ts.shape[0]
    # Joint slow system w = (z, ξ_1, ..., ξ_k) driven by u, with y = C(Tx z + Tu u) + D u: the
    # one joint builder of the batch kernels (z: the plant's slow coordinates, fast ones 0)
    Aj, w_joint0, out_map, _, Bj, in_map = joint_matrices(plant.E, A, B, C, observers, x0, inputs=True,
                                                          D=lti_feedthrough(plant))
    w_plant0 = w_joint0[:n]
    dev, h = grid_deviation_traced(ts)
    Phi, W, c = discretize(Aj, Bj, h)
    ws = step_exact(Phi, W, c, jnp.concatenate([w_plant0, *xi0s]), ts, h, u)
    us = jax.vmap(u)(ts)
    xs = ws[:, :n] @ out_map[:n, :n].T + us @ in_map[:n].T
    xis, off = [], n
    for o in observers:
        xis.append(ws[:, off : off + o.state_size])
        off += o.state_size
    success = jnp.asarray(True)
    if cfg.runtime_checks:
        uniform = dev <= UNIFORM_GRID_RTOL
        if cfg.throw:
            xs = eqx.error_if(
                xs,
                ~uniform,
                "stepper Exact() needs a uniform grid ts (runtime check); use "
                "jnp.linspace or stepper=fojax.Diffrax().",
            )
        success = uniform
    n_steps = jnp.asarray(T - 1)
    stats = dict(
        num_steps=n_steps,
        num_accepted_steps=n_steps,
        num_rejected_steps=jnp.asarray(0),
        success=success,
    )
    return xs, xis, stats


# --------------------------------------------------------------------------- diffrax


class _SlowRMSNorm(eqx.Module):
    """RMS error norm over the slow components and the observer states.

    The fast components of the diffrax state only carry Newton's warm start; they are
    not error-controlled (the returned fast states are always re-solved).
    """

    slow: jax.Array

    def __call__(self, y):
        z, xis = y
        # `where`, not a product: diffrax passes inf (e.g. an initial root-finder
        # difference) through the norm, and 0 * inf would poison it with NaN.
        total = jnp.sum(jnp.where(self.slow > 0, z, 0.0) ** 2)
        count = jnp.sum(self.slow)
        for xi in jax.tree.leaves(xis):
            total = total + jnp.sum(xi**2)
            count = count + xi.size
        return jnp.sqrt(total / jnp.maximum(count, 1.0))


class _JointField(eqx.Module):
    plant: AbstractPlant
    split: SVDSplit
    u: AbstractSignal
    observers: tuple
    carry_fast: bool = eqx.field(static=True)

    def __call__(self, t, state, args):
        z, xis = state
        plant, split = self.plant, self.split
        u_t = self.u(t)
        if self.carry_fast:
            z, lin = solve_fast(
                plant, split, t, z, self.u, guess=z, iters=RHS_NEWTON_ITERS, linearization=True
            )
        else:
            z = solve_fast(plant, split, t, z, self.u)
        dz = slow_rate(plant, split, t, z, u_t)
        if self.observers:
            y = plant.output(t, split.V @ z, u_t)
            dxis = tuple(o.vector_field(t, xi, u_t, y) for o, xi in zip(self.observers, xis))
        else:
            dxis = None
        if self.carry_fast:
            dz = dz + _fast_rate(lin, dz)
        return dz, dxis


def _fast_rate(lin, dz_slow):
    r"""$\dot x_2 = -J_{22}^{-1}(\partial_t h + J_{21}\dot x_1)$, the Newton warm start's rate.

    Only a warm start: no derivative flows through it (the returned fast states are
    re-solved), and it is not error-controlled.
    """
    Jt, Jz, M = lin
    return -solve_small(M, Jt + Jz @ lax.stop_gradient(dz_slow))


def _diffrax(plant, split, x0c, ts, u, observers, xi0s, solver, adjoint, cfg: _Config):
    carry = not plant.linear_in_state
    z0 = split.V.T @ x0c
    # Empty subtrees are None: diffrax's implicit solvers reject empty tuples.
    y0 = (z0, tuple(xi0s) if observers else None)
    field = _JointField(plant, split, u, tuple(observers), carry)
    controller = diffrax.PIDController(rtol=cfg.rtol, atol=cfg.atol, norm=_SlowRMSNorm(split.slow))
    bps = [b for b in _breakpoints(plant, u) if b.size > 0]
    if bps:
        controller = diffrax.ClipStepSizeController(controller, jump_ts=jnp.concatenate(bps))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=None,
        y0=y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=cfg.max_steps,
        adjoint=adjoint,
        throw=cfg.throw,
    )
    zs, xis = sol.ys

    def state(t, z):
        guess = z if carry else None
        return split.V @ solve_fast(plant, split, t, z, u, guess=guess, iters=RHS_NEWTON_ITERS)

    xs = jax.vmap(state)(ts, zs)
    stats = dict(
        num_steps=sol.stats["num_steps"],
        num_accepted_steps=sol.stats["num_accepted_steps"],
        num_rejected_steps=sol.stats["num_rejected_steps"],
        success=sol.result == diffrax.RESULTS.successful,
    )
    return xs, list(xis) if observers else [], stats
