r"""Faults and output noise: plant wrappers (`FaultyPlant`, `NoisyPlant`, on the delegating
base `AbstractPlantWrapper`) and the fault signal `FaultProfile`.

They change *what* is simulated without touching the simulator: a wrapped plant is
still an `fojax.plant.AbstractPlant` (and every leaf can carry a batch axis).
"""

from __future__ import annotations

from operator import attrgetter

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_float_array, as_matrix
from .._errors import ShapeError
from ._base import AbstractPlant
from ._signals import AbstractSignal


class FaultProfile(AbstractSignal):
    r"""A fault that starts at `onset` and reaches `amplitude` after `rise` seconds:

    $$f(t) = a\,\operatorname{clip}\big((t - t_0)/t_r,\,0,\,1\big)$$

    ``rise = 0`` is an abrupt (step) fault, ``rise > 0`` an incipient (ramp-then-hold)
    fault. One class for every shape, so a family of mixed shapes is one pytree of
    arrays (`jax.vmap` needs a single structure).

    **Arguments:** `amplitude` ``(n_f,)``, `onset` scalar, `rise` scalar ``≥ 0``.
    """

    amplitude: Float[Array, " nf"]
    onset: Float[Array, ""]
    rise: Float[Array, ""]

    def __init__(self, amplitude, onset=0.0, rise=0.0):
        a = as_float_array("amplitude", amplitude)
        self.amplitude = a[None] if a.ndim == 0 else a
        self.onset = as_float_array("onset", onset)
        self.rise = as_float_array("rise", rise)

    def __call__(self, t):
        tau = t - self.onset
        ramp = jnp.clip(tau / jnp.where(self.rise > 0, self.rise, 1.0), 0.0, 1.0)
        step = jnp.where(tau >= 0, 1.0, 0.0)
        return jnp.where(self.rise > 0, ramp, step) * self.amplitude

    @property
    def size(self):
        return self.amplitude.shape[-1]

    def breakpoints(self):
        return jnp.stack([self.onset, self.onset + self.rise])


class AbstractPlantWrapper(AbstractPlant):
    """A plant that adds signals to another plant, `base`: it keeps the base's `E`, input and
    output sizes and `linear_in_state`; each final wrapper says what it adds in `rhs` and
    `output`."""

    base: eqx.AbstractVar[AbstractPlant]

    E = property(attrgetter("base.E"))
    m = property(attrgetter("base.m"))
    p = property(attrgetter("base.p"))
    linear_in_state = property(attrgetter("base.linear_in_state"))  # type: ignore[assignment]


class FaultyPlant(AbstractPlantWrapper):
    r"""A plant with additive actuator/process and sensor faults:

    $$E\dot x = f(t, x, u) + F_a\,\phi(t), \qquad y = g(t, x, u) + F_s\,\phi(t).$$

    **Arguments:** `base` (any plant), `Fa` ``(n, n_f)``, `Fs` ``(p, n_f)`` (``None``:
    zeros), `fault` an `AbstractSignal` of size ``n_f`` (e.g. `FaultProfile`).
    """

    base: AbstractPlant
    Fa: Float[Array, "n nf"]
    Fs: Float[Array, "p nf"]
    fault: AbstractSignal

    def __init__(self, base: AbstractPlant, Fa=None, Fs=None, fault: AbstractSignal | None = None):
        n, p = base.n, base.p
        if fault is None:
            raise ShapeError("fault", "an AbstractSignal of size n_f", "None")
        nf = fault.size
        self.base = base
        self.Fa = jnp.zeros((n, nf)) if Fa is None else as_matrix("Fa", Fa, rows=n, cols=nf)
        self.Fs = jnp.zeros((p, nf)) if Fs is None else as_matrix("Fs", Fs, rows=p, cols=nf)
        self.fault = fault

    def rhs(self, t, x, u):
        return self.base.rhs(t, x, u) + self.Fa @ self.fault(t)

    def output(self, t, x, u):
        return self.base.output(t, x, u) + self.Fs @ self.fault(t)

    def breakpoints(self):
        return self.fault.breakpoints()


class NoisyPlant(AbstractPlantWrapper):
    r"""Measurement noise on the output: $y = g(t, x, u) + \nu(t)$.

    `noise` is any signal of size ``p``; `fojax.studies.output_noise` draws seeded zero-order-hold
    (piecewise-constant) Gaussian sequences on a grid, so the simulator is unchanged
    and every sample is reproducible from its key.
    """

    base: AbstractPlant
    noise: AbstractSignal

    def __init__(self, base: AbstractPlant, noise: AbstractSignal):
        if noise.size != base.p:
            raise ShapeError("noise", f"a signal of size p = {base.p}", f"size {noise.size}")
        self.base, self.noise = base, noise

    def rhs(self, t, x, u):
        return self.base.rhs(t, x, u)

    def output(self, t, x, u):
        return self.base.output(t, x, u) + self.noise(t)
