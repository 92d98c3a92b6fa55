r"""Uncertainty and scenario families: batched pytrees of arrays with seeded samplers.

A `Family` is a pytree `values` whose every array leaf has a leading sample axis of
size `size`, and a static `path` (tuple of attribute names) saying where a sample goes
in a study's template: ``("plant", "delta")`` replaces the uncertainty profile of an
`fojax.UncertainDescriptorSystem`, ``("plant", "theta")`` the parameters of a
nonlinear model, ``("plant", "noise")`` the noise of a `NoisyPlant`,
``("plant", "fault")`` the fault of a `FaultyPlant`, ``("x0",)`` the initial state.
Paths are strings (not lambdas) so that a new family with new numbers has the same
static structure and reuses the compiled study.

Every sampler takes a `jax.random` key and a count; the same key gives the same
family (bit for bit). The draws of `constant_delta`, `fault_scenarios` and
`constant_faults` are one compiled program per shape (their ranges are traced): drawn
eagerly, every `jax.random` primitive would be compiled on its own, a noticeable part of
`fojax study`'s start-up; the bits are the eager ones.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PyTree

from .._errors import InputError
from ..plant import Constant, FaultProfile, PiecewiseConstant, Sine


class Family(eqx.Module):
    """A batch of replacements for one part of a study's template (module docstring)."""

    values: PyTree
    path: tuple[str, ...] = eqx.field(static=True)

    def __init__(self, values, path):
        leaves = jax.tree.leaves(values)
        if not leaves:
            raise InputError("a Family needs at least one array leaf.")
        sizes = {jnp.shape(x)[0] if jnp.ndim(x) else None for x in leaves}
        if len(sizes) != 1 or None in sizes:
            raise InputError(
                f"every leaf of a Family must have the same leading sample axis; got sizes {sizes}."
            )
        self.values = values
        self.path = tuple(str(p) for p in path)

    @property
    def size(self) -> int:
        return int(jnp.shape(jax.tree.leaves(self.values)[0])[0])

    def take(self, i):
        """Sample ``i`` (works with a traced / batched index)."""
        return jax.tree.map(lambda a: a[i], self.values)

    def apply(self, tree, i):
        """`tree` with the part at `path` replaced by sample ``i``."""

        def where(t):
            for name in self.path:
                t = getattr(t, name)
            return t

        return eqx.tree_at(where, tree, self.take(i))

    def __getitem__(self, idx) -> Family:
        return Family(jax.tree.map(lambda a: a[idx], self.values), self.path)


def _uniform(key, shape, bounds):
    lo, hi = bounds
    return jax.random.uniform(key, shape, minval=lo, maxval=hi, dtype=jnp.float64)


# ----------------------------------------------------------------- affine uncertainty


def constant_delta(key, count: int, k: int, bounds=(-1.0, 1.0), path=("plant", "delta")) -> Family:
    r"""$\delta_j$ constant per sample, uniform in `bounds` (``(count, k)``), as `fojax.Constant`.

    With a constant $\delta$ the uncertain plant is time-invariant, so
    `fojax.Exact` (matrix exponential) applies.
    """
    return Family(_constant_delta(key, int(count), int(k), _range(bounds)), path)


def _range(bounds):
    """A ``(lo, hi)`` range as a traced ``(2,)`` float64 array (new numbers, same program)."""
    lo, hi = bounds
    return jnp.stack([jnp.asarray(lo, dtype=jnp.float64), jnp.asarray(hi, dtype=jnp.float64)])


@eqx.filter_jit
def _constant_delta(key, count, k, bounds):
    return jax.vmap(Constant)(_uniform(key, (count, k), (bounds[0], bounds[1])))


def sinusoidal_delta(
    key, count: int, k: int, amplitude=(0.0, 1.0), omega=(0.5, 5.0), path=("plant", "delta")
) -> Family:
    r"""$\delta_j(t) = a_j\sin(\omega_j t + \varphi_j)$, uniform $a_j$, $\omega_j$ (rad/s), $\varphi_j\in[0, 2\pi)$."""
    ka, kw, kp = jax.random.split(key, 3)
    a = _uniform(ka, (count, k), amplitude)
    w = _uniform(kw, (count, k), omega)
    ph = _uniform(kp, (count, k), (0.0, 2 * jnp.pi))
    return Family(jax.vmap(Sine)(a, w, ph), path)


def piecewise_constant_delta(
    key, count: int, k: int, t_end: float, pieces: int = 4, bounds=(-1.0, 1.0), dt: float | None = None,
    path=("plant", "delta"),
) -> Family:
    r"""Random piecewise-constant $\delta(t)$ with `pieces` levels (like thesis Figure 3.7).

    Switching times are sorted uniform draws in ``(0, t_end)``, rounded to multiples of
    `dt` when given (so that they lie on a simulation grid); levels uniform in `bounds`.
    """
    kt, kv = jax.random.split(key)
    times = jnp.sort(_uniform(kt, (count, pieces - 1), (0.0, t_end)), axis=-1)
    if dt is not None:
        times = jnp.clip(jnp.round(times / dt) * dt, dt, t_end)
    values = _uniform(kv, (count, pieces, k), bounds)
    return Family(jax.vmap(PiecewiseConstant)(times, values), path)


# ------------------------------------------------------------- nonlinear parameters


def parameter_uncertainty(
    key, count: int, theta: dict, spread: dict, path=("plant", "theta")
) -> Family:
    r"""Physical-parameter uncertainty: ``θ_name = nominal · (1 + s · U(-1, 1))`` for each
    ``name`` in `spread` (relative half-widths, e.g. ``{"k": 0.2, "m": 0.2, "J_l": 0.2}``);
    the other entries of `theta` (a dict of arrays) are repeated unchanged.
    """
    unknown = sorted(set(spread) - set(theta))
    if unknown:
        raise InputError(f"spread names {unknown} are not parameters; theta has {sorted(theta)}.")
    keys = jax.random.split(key, len(spread))
    out = {}
    for name, value in theta.items():
        value = jnp.asarray(value, dtype=jnp.float64)
        out[name] = jnp.broadcast_to(value, (count,) + value.shape)
    for kk, name in zip(keys, sorted(spread)):
        value = jnp.asarray(theta[name], dtype=jnp.float64)
        r = _uniform(kk, (count,) + value.shape, (-1.0, 1.0))
        out[name] = value * (1.0 + spread[name] * r)
    return Family(out, path)


# ---------------------------------------------------------------- noise and x0


def output_noise(
    key, count: int, p: int, t0: float, t1: float, dt: float, std=1.0, path=("plant", "noise")
) -> Family:
    r"""Seeded zero-order-hold Gaussian output noise: $\nu(t) = \sigma\,\eta_k$ on
    $[t_0 + k\,dt,\, t_0 + (k+1)dt)$, $\eta_k \sim \mathcal N(0, I_p)$ (for `NoisyPlant`).

    `std` is a scalar or ``(p,)``. The grid is shared by all samples.
    """
    K = int(round((t1 - t0) / dt))
    times = t0 + dt * jnp.arange(1, K + 1, dtype=jnp.float64)
    eta = jax.random.normal(key, (count, K + 1, p), dtype=jnp.float64)
    vals = eta * jnp.asarray(std, dtype=jnp.float64)
    return Family(jax.vmap(lambda v: PiecewiseConstant(times, v))(vals), path)


def initial_conditions(key, count: int, mean, std=0.0, bounds=None, path=("x0",)) -> Family:
    r"""Initial states ``x0 = mean + std ⊙ N(0, I)`` or, with `bounds` ``(lo, hi)``, uniform
    ``mean + U(lo, hi)`` (arrays broadcastable to ``(n,)``)."""
    mean = jnp.asarray(mean, dtype=jnp.float64)
    # explicit leading sample axis (no implicit rank promotion: (count, n) with (n,))
    if bounds is None:
        std = jnp.broadcast_to(jnp.asarray(std, dtype=jnp.float64), mean.shape)
        x = mean[None] + std[None] * jax.random.normal(key, (count,) + mean.shape, dtype=jnp.float64)
    else:
        lo, hi = (jnp.broadcast_to(jnp.asarray(b, dtype=jnp.float64), mean.shape)[None] for b in bounds)
        x = mean[None] + jax.random.uniform(key, (count,) + mean.shape, dtype=jnp.float64) * (hi - lo) + lo
    return Family(x, path)


# ---------------------------------------------------------------- faults


def fault_scenarios(
    key,
    count: int,
    nf: int,
    magnitude=(0.5, 2.0),
    onset=(0.0, 0.0),
    rise=(0.0, 0.0),
    which: str = "one",
    signed: bool = True,
    path=("plant", "fault"),
) -> Family:
    r"""Random fault scenarios as `FaultProfile` (for `FaultyPlant`).

    - `which`: ``"one"`` (one fault, chosen uniformly, is active per scenario) or
      ``"all"`` (every fault active with its own magnitude).
    - `magnitude`: uniform range of $|a|$; with `signed`, a random sign.
    - `onset`: uniform onset time range; `rise`: uniform rise-time range
      (``(0, 0)``: abrupt faults; ``(0, 0)`` onset and rise: constant faults).
    """
    if which not in ("one", "all"):
        raise InputError(f"which must be 'one' or 'all', got {which!r}.")
    values = _fault_scenarios(key, int(count), int(nf), _range(magnitude), _range(onset), _range(rise), which,
                              bool(signed))
    return Family(values, path)


@eqx.filter_jit
def _fault_scenarios(key, count, nf, magnitude, onset, rise, which, signed):
    km, ks, kw, ko, kr = jax.random.split(key, 5)
    a = _uniform(km, (count, nf), (magnitude[0], magnitude[1]))
    if signed:
        a = a * jnp.where(jax.random.bernoulli(ks, 0.5, (count, nf)), 1.0, -1.0)
    if which == "one":
        pick = jax.random.randint(kw, (count,), 0, nf)
        # a · one_hot, written as the select XLA makes of it, with the sign of a · 0 kept (-0.0
        # for a < 0, as drawn eagerly; XLA's select would give +0.0)
        a = jnp.where(jax.nn.one_hot(pick, nf, dtype=bool), a, jnp.copysign(0.0, a))
    t_on = _uniform(ko, (count,), (onset[0], onset[1]))
    t_r = _uniform(kr, (count,), (rise[0], rise[1]))
    return jax.vmap(FaultProfile)(a, t_on, t_r)


def constant_faults(key, count: int, x0, nf: int, magnitude=(0.5, 2.0), which: str = "all",
                    signed: bool = True, path=("x0",)) -> Family:
    r"""Constant faults present from ``t0`` for a *fault-augmented* plant
    (`fojax.plant.augment_faults`, state $\chi = [x;\,f]$): a family of initial states equal to
    `x0` (``(n + nf,)``) with the last ``nf`` entries replaced by random fault magnitudes
    (drawn as in `fault_scenarios`).
    """
    fam = fault_scenarios(key, count, nf, magnitude=magnitude, which=which, signed=signed)
    return Family(_with_faults(jnp.asarray(x0, dtype=jnp.float64), fam.values.amplitude, int(nf)), path)


@eqx.filter_jit
def _with_faults(x0, amplitude, nf):
    count = amplitude.shape[0]
    base = jnp.broadcast_to(x0[: x0.shape[0] - nf], (count, x0.shape[0] - nf))
    return jnp.concatenate([base, amplitude], axis=1)
