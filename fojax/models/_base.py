"""The container returned by every thesis example."""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..plant import AbstractPlant, augment_faults, DescriptorSystem


def _freeze(value):
    """Read-only float64 copy of array-like printed data; other values unchanged."""
    if isinstance(value, np.ndarray):
        arr = np.array(value, dtype=np.complex128 if np.iscomplexobj(value) else np.float64)
        arr.flags.writeable = False
        return arr
    if isinstance(value, dict):
        return types.MappingProxyType({k: _freeze(v) for k, v in value.items()})
    return value


def _array(rows) -> np.ndarray:
    """A read-only float64 matrix from nested lists (the printed numbers)."""
    arr = np.array(rows, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def physical_parameters(model: str, defaults: Mapping[str, float], given: Mapping[str, Any],
                        positive: tuple[str, ...], what: str) -> dict[str, float]:
    """The parameters of a model that is not from the thesis: `defaults` overridden by
    `given` (as floats). Raises `TypeError` naming unknown names and `ValueError` naming the
    first of `positive` that is not > 0 (`what` says what those are, for the message)."""
    unknown = set(given) - set(defaults)
    if unknown:
        raise TypeError(f"{model} got unknown parameters {sorted(unknown)}; known: {sorted(defaults)}")
    p = {**defaults, **{k: float(v) for k, v in given.items()}}
    for k in positive:
        if not p[k] > 0:
            raise ValueError(f"{model}: {k} must be positive ({what}); got {p[k]}.")
    return p


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class ThesisExample:
    r"""One numerical example of the thesis, with every printed quantity.

    The plant is in `system`; everything else the thesis prints (functional and
    feedback matrices, observer gains, eigenvalues, disks, delays, initial
    conditions, fault matrices, ...) is reachable as an attribute named after the
    thesis's symbol, e.g. ``ex.L``, ``ex.N``, ``ex.eig_EA``. The attributes that an
    example carries are listed in the docstring of the function that builds it and
    by `keys`.

    Printed matrices are read-only `numpy.ndarray`s of dtype float64 (printed
    eigenvalues: complex128), exactly as printed except where a typo was resolved;
    every resolution is recorded in `notes` (and the printed version is kept under a
    ``*_printed`` name).

    **Fields:**

    - `name`: short identifier, e.g. ``"example_4_1_3"``.
    - `section`: the thesis section, e.g. ``"4.1.3"``.
    - `system`: the plant (a `fojax.DescriptorSystem`, `fojax.TakagiSugenoSystem`
      or `fojax.NonlinearDescriptorSystem`).
    - `notes`: typo resolutions and findings, one string each.
    - `quantities`: read-only mapping of every other attribute.
    """

    name: str
    section: str
    system: AbstractPlant
    notes: tuple[str, ...]
    quantities: Mapping[str, Any]

    def __post_init__(self):
        frozen = {k: _freeze(v) for k, v in dict(self.quantities).items()}
        clash = set(frozen) & {f.name for f in dataclasses.fields(self)}
        if clash:
            raise ValueError(f"quantities may not shadow the fields {sorted(clash)}")
        object.__setattr__(self, "quantities", types.MappingProxyType(frozen))
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))

    def __getattr__(self, key: str):
        # Only called when normal lookup fails; guard the fields themselves so that
        # copying/unpickling (which builds the object without __init__) terminates.
        if key.startswith("__") or key in ("quantities", "name", "section", "system", "notes"):
            raise AttributeError(key)
        try:
            return self.quantities[key]
        except KeyError:
            raise AttributeError(
                f"{self.name} has no quantity {key!r}; available: {', '.join(self.keys())}"
            ) from None

    def __dir__(self):
        return sorted(set(super().__dir__()) | set(self.quantities))

    def keys(self) -> tuple[str, ...]:
        """Names of the printed quantities (besides `system` and `notes`)."""
        return tuple(self.quantities)

    def __repr__(self) -> str:
        s = self.system
        return (
            f"ThesisExample({self.name}, §{self.section}, "
            f"{type(s).__name__}(n={s.n}, m={s.m}, p={s.p}), "
            f"quantities={list(self.quantities)}, {len(self.notes)} notes)"
        )


def linear_example(name: str, section: str, notes: tuple[str, ...], E, A, B, C, *,
                   system: AbstractPlant | None = None, faults: Mapping[str, Any] | None = None,
                   **quantities) -> ThesisExample:
    """The `ThesisExample` of a linear model $(E, A, B, C)$: `system` is
    ``DescriptorSystem(E, A, B, C)`` unless given, and the quantities are `E`, `A`, `B`, `C`,
    then `quantities` in their order, then, with `faults` (the fault directions, keywords of
    `fojax.plant.augment_faults`), ``augmented``: the system with its faults as states."""
    system = DescriptorSystem(E, A, B, C) if system is None else system
    quantities = dict(E=E, A=A, B=B, C=C, **quantities)
    if faults is not None:
        quantities["augmented"] = augment_faults(system, **faults)
    return ThesisExample(name=name, section=section, system=system, notes=notes,
                         quantities=quantities)
