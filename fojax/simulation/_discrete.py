r"""The `Discrete` stepper: discrete-time plants and observers on their sample grid.

A plant with a sampling period (``DescriptorSystem(..., dt=h)``),

$$Ex[k+1] = Ax[k] + Bu[k],\qquad y[k] = Cx[k],$$

is stepped on ``ts = t0 + k h`` with $u[k] = u(t_k)$, together with observers of the same
period, $\xi[k+1] = \phi(t_k, \xi[k], u[k], y[k])$ (their `vector_field` is the next state),
$\hat z[k] = \psi(t_k, \xi[k], u[k], y[k])$.

**Singular E (the index-1 split at each step).** The simulation layer's reduction in the
SVD coordinates of $E$ (`fojax.simulation._reduction.reduce_linear_masked`, the split of
`fojax.analysis`) is algebraic, so it holds with $\dot x$ replaced by $x[k+1]$: with the
slow coordinates $w$ and $x[k] = T_xw[k] + T_uu[k]$ (the algebraic equations
$0 = U_2^\top(Ax[k] + Bu[k])$ solved at every sample),
$w[k+1] = A_sw[k] + B_su[k]$ — the same $A_s$, $B_s$ that the continuous steppers
exponentiate. A causal (index $\le 1$) plant is required, as an impulse-free one is in
continuous time; ``x0`` is made consistent as by `fojax.simulate` (its slow part kept).
The time loop is one `jax.lax.scan`; `jax.vmap` and `jax.grad` apply as for the other
steppers (``E`` gets no gradient).
"""

from __future__ import annotations

import collections
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._errors import InputError
from ._reduction import (
    constraint_residual_norm,
    is_concrete,
    lti_matrices,
    project_initial_state,
    reduce_linear_masked,
    svd_split,
)
from ._solution import Solution
from ._steppers import AbstractStepper, Auto, UNIFORM_GRID_RTOL


#: Traces of the compiled discrete-time core (tests prove that new numbers do not recompile).
TRACE_COUNTS: collections.Counter = collections.Counter()


def plant_dt(plant):
    """The sampling period of `plant` (``None``: continuous time)."""
    return getattr(plant, "dt", None)


class Discrete(AbstractStepper):
    r"""Stepping of a discrete-time plant (``dt`` set) and its observers on the grid
    $t_k = t_0 + kh$ (module docstring); `fojax.Auto` picks it for every discrete-time plant.

    Needs a linear time-invariant discrete-time `fojax.DescriptorSystem`, observers with
    the same ``dt`` (designed on the discrete model, or `fojax.discretize`d) and
    ``ts = t0 + h * jnp.arange(T)``. In `run_study` it runs every sample through
    `fojax.simulate` (no batch candidates).
    """

    method: ClassVar[str] = "discrete"

    def select(self, plant, observers, ts, u) -> AbstractStepper:
        dt = plant_dt(plant)
        if dt is None:
            raise InputError(
                f"stepper Discrete() steps discrete-time plants (DescriptorSystem(..., dt=h)); this "
                f"{type(plant).__name__} is continuous-time. Use stepper=Auto(), or fojax.discretize(plant, h)."
            )
        if lti_matrices(plant) is None:
            raise InputError(f"stepper Discrete(): a discrete-time plant must be a linear DescriptorSystem; "
                             f"got {type(plant).__name__}.")
        for i, o in enumerate(observers):
            odt = getattr(o, "dt", None)
            if odt is None or abs(float(odt) - dt) > 1e-12 * dt:
                raise InputError(
                    f"observers[{i}] ({type(o).__name__}) has dt = {odt}, the plant dt = {dt:g}: a discrete-time "
                    "plant runs observers with the same sampling period. Design on the discrete model, or use "
                    "fojax.discretize(observer, dt)."
                )
        if is_concrete(ts):
            t = np.asarray(ts)
            dev = float(np.max(np.abs(t - (t[0] + dt * np.arange(t.shape[0]))))) / dt
            if not dev <= UNIFORM_GRID_RTOL:
                raise InputError(
                    f"a discrete-time plant (dt = {dt:g}) is simulated on its samples ts = t0 + k*dt; ts deviates "
                    f"from that grid by {dev:.2e} periods. Use ts = t0 + {dt:g} * jnp.arange(T)."
                )
        return self


def discrete_stepper(plant, stepper: AbstractStepper) -> AbstractStepper:
    """The stepper `simulate`/`run_study` use for `plant`: `Discrete` for a discrete-time plant
    when `stepper` is `Auto` or `Discrete` (`fojax.errors.InputError` for any other), else `stepper`."""
    if plant_dt(plant) is None:
        return stepper
    if not isinstance(stepper, Auto | Discrete):
        raise InputError(
            f"stepper {type(stepper).__name__}() steps continuous-time models; this plant is discrete-time "
            f"(dt = {plant_dt(plant):g}). Use stepper=fojax.Auto() (the default) or Discrete()."
        )
    return Discrete()


def simulate_discrete(plant, x0, ts, u, observers, xi0s, *, throw: bool = True) -> Solution:
    """`fojax.simulate` for a discrete-time plant (arguments already validated there)."""
    return _discrete_core(plant, x0, ts, u, tuple(observers), tuple(xi0s), bool(throw))


@eqx.filter_jit
def _discrete_core(plant, x0, ts, u, observers, xi0s, throw: bool):
    TRACE_COUNTS["simulate"] += 1
    A, B, _ = lti_matrices(plant)
    split = svd_split(plant.E)
    red = reduce_linear_masked(plant.E, A, B, split)
    x0c, dist, res0 = project_initial_state(plant, split, ts[0], x0, u)
    us = jax.vmap(u)(ts)
    w0 = split.slow * (split.V.T @ x0c)

    def step(carry, tk_uk):
        w, xis = carry
        t, uk = tk_uk
        x = red.Tx @ w + red.Tu @ uk
        y = plant.output(t, x, uk)
        nxt = tuple(o.vector_field(t, xi, uk, y) for o, xi in zip(observers, xis))
        return (red.As @ w + red.Bs @ uk, nxt), (x, y, xis)

    _, (xs, ys, xis) = lax.scan(step, (w0, xi0s), (ts, us))
    estimates = tuple(jax.vmap(o.output)(ts, xi, us, ys) for o, xi in zip(observers, xis))
    residuals = jax.vmap(lambda t, x, uk: constraint_residual_norm(plant, split, t, x, uk))(ts, xs, us)
    finite = jnp.all(jnp.isfinite(xs))
    if throw:
        xs = eqx.error_if(xs, ~finite, "fojax.simulate produced non-finite states for the discrete-time plant: "
                          "it may be non-causal (index > 1; checked on the host for concrete inputs) or the "
                          "recursion grows without bound.")
    n_steps = jnp.asarray(ts.shape[0] - 1)
    stats = dict(constraint_residual=jnp.max(residuals), initial_residual=res0, projection_distance=dist,
                 num_steps=n_steps, num_accepted_steps=n_steps, num_rejected_steps=jnp.asarray(0), success=finite)
    return Solution(ts=ts, xs=xs, ys=ys, us=us, observer_states=tuple(xis), estimates=estimates, stats=stats,
                    method="discrete")
