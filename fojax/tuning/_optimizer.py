"""Optimizers shared between tuning runs, so that the jitted tuning step compiles once.

`fojax.tuning.tune` compiles its step (loss, gradient, optax update) once per optimizer
*object*: an optax transformation is a pair of closures, which JAX can only key by
identity. ``optax.adam(0.1)`` written twice is two objects, and the second run compiles
again (about 30 s on the §3.3.7 benchmark). `shared_optimizer` returns one object per
configuration, so runs that ask for the same configuration share one compilation.
"""

from __future__ import annotations

import functools

import optax

from .._errors import InputError


@functools.lru_cache(maxsize=64)
def _build(name: str, hyperparameters: tuple) -> optax.GradientTransformation:
    return getattr(optax, name)(**dict(hyperparameters))


def shared_optimizer(name: str = "adam", **hyperparameters) -> optax.GradientTransformation:
    r"""The optax transformation ``optax.<name>(**hyperparameters)``, one object per configuration.

    Two calls with the same `name` and hyperparameters return *the same* object, so
    `fojax.tuning.tune` reuses its compiled step across runs (it defaults to ``shared_optimizer("adam", learning_rate=1e-2)``).

    **Arguments:**

    - `name`: an optax optimizer, e.g. ``"adam"``, ``"sgd"``, ``"adamw"``.
    - `hyperparameters`: its keyword arguments; they must be hashable (numbers, strings,
      or a schedule *object* created once and reused).

    **Raises:** `fojax.InputError` for an unknown name or unhashable hyperparameters.
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
