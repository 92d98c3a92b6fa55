r"""Time signals (plant inputs, faults, uncertainty profiles) as equinox modules.

Every signal maps a scalar time ``t`` to a vector of fixed size. Amplitudes,
times and frequencies are array leaves, so a signal with a leading batch axis on
its leaves is a *family* of signals that `jax.vmap` maps over (fault scenarios,
random input profiles). Signals add: ``Step(...) + Sine(...)`` is a `SumSignal`.

Conventions: frequencies are angular (rad/s); a `Step` switches on at ``t >= t0``;
signals are zero before their onset unless stated.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_float_array
from .._errors import ShapeError


def _vec(name, v):
    v = as_float_array(name, v)
    if v.ndim == 0:
        v = v[None]
    return v


def _scalar(name, v):
    v = as_float_array(name, v)
    if v.ndim != 0:
        raise ShapeError(name, "a scalar", tuple(v.shape))
    return v


class AbstractSignal(eqx.Module):
    """A vector-valued function of time, ``t -> (size,)``."""

    @abc.abstractmethod
    def __call__(self, t) -> Float[Array, " size"]: ...

    @property
    @abc.abstractmethod
    def size(self) -> int: ...

    def breakpoints(self) -> Float[Array, " k"]:
        """Times where the signal (or its derivative) jumps; used to guide step sizes."""
        return jnp.zeros((0,))

    def __add__(self, other: AbstractSignal) -> SumSignal:
        return SumSignal((self, other))


class Zero(AbstractSignal):
    """The zero signal of a given size (e.g. ``m = 0`` for autonomous systems)."""

    n: int = eqx.field(static=True)

    def __init__(self, size: int):
        self.n = int(size)

    def __call__(self, t):
        return jnp.zeros((self.n,))

    @property
    def size(self):
        return self.n


class Constant(AbstractSignal):
    """``u(t) = value`` for all ``t``."""

    value: Float[Array, " size"]

    def __init__(self, value):
        self.value = _vec("value", value)

    def __call__(self, t):
        return self.value

    @property
    def size(self):
        return self.value.shape[-1]


class Step(AbstractSignal):
    """``u(t) = amplitude`` for ``t >= t0``, zero before."""

    amplitude: Float[Array, " size"]
    t0: Float[Array, ""]

    def __init__(self, amplitude, t0=0.0):
        self.amplitude = _vec("amplitude", amplitude)
        self.t0 = _scalar("t0", t0)

    def __call__(self, t):
        return jnp.where(t >= self.t0, 1.0, 0.0) * self.amplitude

    @property
    def size(self):
        return self.amplitude.shape[-1]

    def breakpoints(self):
        return self.t0[None]


class Ramp(AbstractSignal):
    """``u(t) = slope · (t - t0)`` for ``t >= t0`` (zero before), optionally saturating at ``t1``."""

    slope: Float[Array, " size"]
    t0: Float[Array, ""]
    t1: Float[Array, ""]

    def __init__(self, slope, t0=0.0, t1=jnp.inf):
        self.slope = _vec("slope", slope)
        self.t0 = _scalar("t0", t0)
        self.t1 = as_float_array("t1", t1, check_finite=False)

    def __call__(self, t):
        tau = jnp.clip(t, self.t0, self.t1) - self.t0
        return self.slope * tau

    @property
    def size(self):
        return self.slope.shape[-1]

    def breakpoints(self):
        return jnp.stack([self.t0, jnp.where(jnp.isfinite(self.t1), self.t1, self.t0)])


class Sine(AbstractSignal):
    """``u(t) = offset + amplitude · sin(omega · t + phase)`` (omega in rad/s)."""

    amplitude: Float[Array, " size"]
    omega: Float[Array, " size"]
    phase: Float[Array, " size"]
    offset: Float[Array, " size"]

    def __init__(self, amplitude, omega, phase=0.0, offset=0.0):
        a = _vec("amplitude", amplitude)
        self.amplitude = a
        self.omega = jnp.broadcast_to(_vec("omega", omega), a.shape)
        self.phase = jnp.broadcast_to(_vec("phase", phase), a.shape)
        self.offset = jnp.broadcast_to(_vec("offset", offset), a.shape)

    def __call__(self, t):
        return self.offset + self.amplitude * jnp.sin(self.omega * t + self.phase)

    @property
    def size(self):
        return self.amplitude.shape[-1]


class PiecewiseConstant(AbstractSignal):
    """Piecewise-constant signal: ``values[k]`` on ``[times[k-1], times[k])``.

    **Arguments:**

    - `times`: ``(K,)`` increasing switching times.
    - `values`: ``(K + 1, size)``; ``values[0]`` holds before ``times[0]`` and
      ``values[K]`` after ``times[K-1]``.

    Intermittent faults are piecewise-constant signals with zero rows between
    their active windows (see `intermittent`).
    """

    times: Float[Array, " K"]
    values: Float[Array, "K+1 size"]

    def __init__(self, times, values):
        times = as_float_array("times", times)
        if times.ndim != 1:
            raise ShapeError("times", "(K,)", tuple(times.shape))
        values = as_float_array("values", values)
        if values.ndim == 1:
            values = values[:, None]
        if values.shape[0] != times.shape[0] + 1:
            raise ShapeError(
                "values",
                (times.shape[0] + 1, "size"),
                tuple(values.shape),
                "PiecewiseConstant needs one more row of values than switching times.",
            )
        self.times, self.values = times, values

    def __call__(self, t):
        k = jnp.searchsorted(self.times, t, side="right")
        return self.values[k]

    @property
    def size(self):
        return self.values.shape[-1]

    def breakpoints(self):
        return self.times


def intermittent(amplitude, windows) -> PiecewiseConstant:
    """A fault that is ``amplitude`` inside each ``(start, stop)`` window and zero elsewhere."""
    amplitude = jnp.atleast_1d(jnp.asarray(amplitude, dtype=float))
    times, values = [], [jnp.zeros_like(amplitude)]
    for start, stop in windows:
        times += [start, stop]
        values += [amplitude, jnp.zeros_like(amplitude)]
    return PiecewiseConstant(jnp.asarray(times, dtype=float), jnp.stack(values))


class SumSignal(AbstractSignal):
    """The sum of several signals of the same size."""

    terms: tuple[AbstractSignal, ...]

    def __init__(self, terms):
        terms = tuple(
            t for term in terms for t in (term.terms if isinstance(term, SumSignal) else (term,))
        )
        sizes = {t.size for t in terms}
        if len(sizes) > 1:
            raise ShapeError("signal sizes", "all equal", sorted(sizes), "Only signals of equal size add.")
        self.terms = terms

    def __call__(self, t):
        out = self.terms[0](t)
        for term in self.terms[1:]:
            out = out + term(t)
        return out

    @property
    def size(self):
        return self.terms[0].size

    def breakpoints(self):
        return jnp.concatenate([t.breakpoints() for t in self.terms])


class Stack(AbstractSignal):
    """Concatenate signals into one vector signal (e.g. separate faults into ``f``)."""

    parts: tuple[AbstractSignal, ...]

    def __init__(self, parts):
        self.parts = tuple(parts)

    def __call__(self, t):
        return jnp.concatenate([p(t) for p in self.parts])

    @property
    def size(self):
        return sum(p.size for p in self.parts)

    def breakpoints(self):
        return jnp.concatenate([p.breakpoints() for p in self.parts])


def as_signal(u, size: int | None = None) -> AbstractSignal:
    """Coerce ``None`` / constant vector / signal to an `AbstractSignal`."""
    if isinstance(u, AbstractSignal):
        if size is not None and u.size != size:
            raise ShapeError("input signal", f"size {size}", f"size {u.size}")
        return u
    if u is None:
        return Zero(size or 0)
    c = Constant(u)
    if size is not None and c.size != size:
        raise ShapeError("input signal", f"size {size}", f"size {c.size}")
    return c
