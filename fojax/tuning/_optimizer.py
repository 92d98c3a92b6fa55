"""Optimizers shared between tuning runs, so that the jitted tuning step compiles once.

`fojax.tuning.tune` compiles its step (loss, gradient, optax update) once per optimizer:
an optax transformation is a pair of closures, which JAX can only key by identity, and
its hyperparameters are constants inside them. ``optax.adam(0.1)`` written twice is two
objects, and ``optax.adam(0.05)`` a third program: each compiles the step again (seconds
on the default §3.3.7 study, `benchmarks/tuning_step.py`).

`shared_optimizer` describes the optimizer as data instead (`OptimizerSpec`): its optax
name and its non-float hyperparameters decide the program, its float hyperparameters
(learning rate, decay rates, ε, weight decay, ...) are float64 arrays that the step
receives as inputs. Runs that differ only in those numbers — a learning-rate sweep —
share one compilation, and the update is the same arithmetic as the optax object's
(`tests/test_tuning.py` compares the histories bit for bit). An optimizer whose float
hyperparameters cannot be traced (an optax function that branches on their values in
Python) keeps them as constants: one compilation per value, as for any other optax object.
"""

from __future__ import annotations

import functools
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from .._errors import InputError


class OptimizerSpec(eqx.Module):
    """An optax optimizer as data: ``optax.<name>(**static, **numeric)``.

    `name` and `static` (the hyperparameters that are not floats: integers, booleans,
    strings, schedule objects) are static fields, so they decide the compiled program;
    `numeric` (the float hyperparameters) holds float64 arrays, so new values reuse it."""

    name: str = eqx.field(static=True)
    static: tuple = eqx.field(static=True)
    numeric: dict

    def build(self) -> optax.GradientTransformation:
        """The optax transformation (traceable: `numeric` may be tracers)."""
        return getattr(optax, self.name)(**dict(self.static), **self.numeric)


def _is_float(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, numbers.Integral))


#: The `OptimizerSpec` of each object `shared_optimizer` returned (by ``id``: the objects stay
#: alive in `_build`'s cache, so an ``id`` is never reused), or None when its float
#: hyperparameters cannot be traced.
_SPECS: dict[int, OptimizerSpec | None] = {}


@functools.cache
def _build(name: str, hyperparameters: tuple) -> optax.GradientTransformation:
    """One object per configuration, its `OptimizerSpec` registered in `_SPECS`."""
    optimizer = getattr(optax, name)(**dict(hyperparameters))
    _SPECS[id(optimizer)] = _spec(name, hyperparameters, optimizer)
    return optimizer


def _spec(name: str, hyperparameters: tuple, optimizer) -> OptimizerSpec | None:
    numeric = {k: jnp.asarray(float(v), dtype=jnp.float64) for k, v in hyperparameters if _is_float(v)}
    static = tuple((k, v) for k, v in hyperparameters if not _is_float(v))
    spec = OptimizerSpec(name, static, numeric)
    if not numeric:
        return spec
    # the traced form must update like the object: trace it once on a one-parameter state
    params = {"xi": jnp.zeros(1)}
    try:
        state = optimizer.init(params)
        jax.eval_shape(lambda num: OptimizerSpec(name, static, num).build().update(params, state, params),
                       numeric)
    except Exception:  # noqa: BLE001 - any failure to trace: keep the constants (module docstring)
        return None
    return spec


def shared_optimizer(name: str = "adam", **hyperparameters) -> optax.GradientTransformation:
    r"""The optax transformation ``optax.<name>(**hyperparameters)``, shared between tuning runs.

    Two calls with the same `name` and hyperparameters return *the same* object, and
    `fojax.tuning.tune` gives its step the float hyperparameters as data (module
    docstring): runs with this optimizer compile the step once, whatever their values
    (e.g. ``learning_rate=0.1``, then ``0.05``). `tune` defaults to
    ``shared_optimizer("adam", learning_rate=1e-2)``.

    **Arguments:**

    - `name`: an optax optimizer, e.g. ``"adam"``, ``"sgd"``, ``"adamw"``.
    - `hyperparameters`: its keyword arguments; they must be hashable (numbers, strings,
      or a schedule *object* created once and reused).

    **Raises:** `fojax.errors.InputError` for an unknown name or unhashable hyperparameters.
    """
    factory = getattr(optax, name, None) if isinstance(name, str) else None
    if not callable(factory):
        raise InputError(f"shared_optimizer: optax has no optimizer named {name!r}; pass the name of an "
                         "optax function such as 'adam', 'sgd' or 'adamw'.")
    key = tuple(sorted(hyperparameters.items()))
    try:
        hash(key)
    except TypeError as e:
        raise InputError(f"shared_optimizer({name!r}): the hyperparameters must be hashable ({e}); create "
                         "an unhashable one (e.g. an array) once and pass your own optax object to tune "
                         "instead, reusing that object across runs.") from None
    return _build(name, key)


def step_optimizer(optimizer: optax.GradientTransformation):
    """What `fojax.tuning.tune` passes to its jitted step: the `OptimizerSpec` of an object of
    `shared_optimizer` (float hyperparameters as data), else `optimizer` itself."""
    spec = _SPECS.get(id(optimizer))
    return optimizer if spec is None else spec


def transformation(optimizer) -> optax.GradientTransformation:
    """The optax transformation of what `step_optimizer` returned (inside the step)."""
    return optimizer.build() if isinstance(optimizer, OptimizerSpec) else optimizer
