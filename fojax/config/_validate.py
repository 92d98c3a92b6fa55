"""Validation helpers of the config files: typed values, arrays and shapes (`V`), and the
checks across tables (model header, state count, observer file names). Every problem is a
`fojax.errors.ConfigError` naming the file, the dotted key and what was expected."""


from __future__ import annotations

import difflib
import math
from typing import Any

import numpy as np

from .._errors import ConfigError
from .._io import name_problem, NAME_RULE, suggest_name
from ._spec import _MODEL


class V:
    """Validation helpers bound to one file name."""

    def __init__(self, file: str):
        self.file = file

    def err(self, key: str, message: str) -> ConfigError:
        return ConfigError(self.file, key, message)

    def table(self, key: str, value, allowed: set, required=()) -> dict:
        if not isinstance(value, dict):
            raise self.err(key, f"expected a table ([{key}] or {{...}}), got {typename(value)}.")
        for k in value:
            if k not in allowed:
                close = difflib.get_close_matches(k, sorted(allowed), n=1, cutoff=0.5)
                hint = f" Did you mean '{close[0]}'?" if close else ""
                raise self.err(
                    join(key, k),
                    f"unknown key '{k}'.{hint} Allowed keys in [{key or 'top level'}]: "
                    f"{', '.join(sorted(allowed))}.",
                )
        for k in required:
            if k not in value:
                raise self.err(join(key, k), f"missing required key '{k}' in [{key or 'top level'}].")
        return value

    def number(self, key, value, *, positive=False, nonneg=False, integer=False) -> float | int:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        if integer and not (isinstance(value, int) and not isinstance(value, bool)):
            raise self.err(key, f"expected an integer, got {value!r} ({typename(value)}).")
        if not ok:
            raise self.err(key, f"expected a number, got {value!r} ({typename(value)}).")
        if not math.isfinite(value):
            raise self.err(key, f"expected a finite number, got {value!r}.")
        if positive and value <= 0:
            raise self.err(key, f"expected a positive number, got {value!r}.")
        if nonneg and value < 0:
            raise self.err(key, f"expected a number >= 0, got {value!r}.")
        return value

    def string(self, key, value, choices=None) -> str:
        if not isinstance(value, str):
            raise self.err(key, f"expected a string, got {value!r} ({typename(value)}).")
        if choices is not None and value not in choices:
            # the hint ignores case: "IAE" -> "iae"
            lower = {c.lower(): c for c in choices}
            close = difflib.get_close_matches(value.lower(), list(lower), n=1, cutoff=0.5)
            hint = f" Did you mean '{lower[close[0]]}'?" if close else ""
            raise self.err(key, f"expected one of {', '.join(map(repr, choices))}, got {value!r}.{hint}")
        return value

    def file_name(self, key, value, fallback: str) -> str:
        """A string that becomes a file or folder name (`fojax._io.NAME_RULE`)."""
        value = self.string(key, value)
        problem = name_problem(value)
        if problem is not None:
            raise self.err(
                key, f"{value!r} cannot be used: {problem}. The {NAME_RULE}; e.g. "
                f"{suggest_name(value, fallback)!r}."
            )
        return value

    def boolean(self, key, value) -> bool:
        if not isinstance(value, bool):
            raise self.err(key, f"expected true or false, got {value!r} ({typename(value)}).")
        return value

    def array(self, key, value, ndim: int | tuple[int, ...], what: str) -> np.ndarray:
        """A rectangular float64 array of `ndim` dimensions from nested lists of numbers."""
        ndims = (ndim,) if isinstance(ndim, int) else ndim

        def walk(v, path, depth):
            if isinstance(v, list):
                return [walk(x, path + [i], depth + 1) for i, x in enumerate(v)]
            if isinstance(v, bool) or not isinstance(v, int | float):
                where = "".join(f"[{i}]" for i in path)
                raise self.err(
                    key,
                    f"expected {what} of numbers; entry {key}{where} is {v!r} ({typename(v)}).",
                )
            if not math.isfinite(v):
                where = "".join(f"[{i}]" for i in path)
                raise self.err(key, f"entry {key}{where} is {v!r}; every entry must be finite.")
            return float(v)

        if not isinstance(value, list):
            raise self.err(key, f"expected {what} (nested lists of numbers), got {typename(value)}.")
        walk(value, [], 0)
        try:
            arr = np.array(value, dtype=np.float64)
        except ValueError:
            raise self.err(
                key, f"expected {what}, but the rows have different lengths (ragged nested lists)."
            ) from None
        if arr.ndim not in ndims or 0 in arr.shape:
            raise self.err(
                key,
                f"expected {what} ({' or '.join(f'{d}-D' for d in ndims)} nested lists), got an "
                f"array of shape {arr.shape}.",
            )
        return arr

    def shape(self, key, arr, expected: tuple, meaning: str):
        if tuple(arr.shape) != tuple(expected):
            raise self.err(key, f"has shape {tuple(arr.shape)}, expected {tuple(expected)} ({meaning}).")


def typename(v) -> str:
    return {dict: "table", list: "list", str: "string", bool: "boolean"}.get(type(v), type(v).__name__)


def join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


#: Files `fojax study` writes beside the observers' ``<name>.npz`` (an observer of that name
#: would share the file).
_STUDY_STEMS = ("study", "metrics")


def check_observer_names(v: V, names: list[str]) -> None:
    """Every observer gets its own files: ``<name>.npz`` and ``poles-<name>.png``
    (`fojax design`), ``<name>-tuned.npz`` and ``tuning-<name>.npz/.json/.png``
    (`fojax study`). Refuse names whose files coincide, also on case-insensitive file
    systems (macOS, Windows), where ``PO.npz`` and ``po.npz`` are one file."""
    owner: dict[str, tuple[int, str]] = {}  # file stem (lower case) -> (observer, which file)
    for i, nm in enumerate(names):
        key = f"observer[{i}].name"
        if nm in names[:i]:
            raise v.err(key, f"'{nm}' is the name of observer[{names.index(nm)}] too; names must be "
                        f"unique (each observer is saved as <name>.npz).")
        if nm.lower() in _STUDY_STEMS:
            raise v.err(key, f"'{nm}' is reserved: `fojax study` writes {nm.lower()}.npz itself. "
                        f"Choose another name, e.g. '{nm}_obs'.")
        files = ((nm, f"its design {nm}.npz"), (f"{nm}-tuned", f"its tuned design {nm}-tuned.npz"),
                 (f"tuning-{nm}", f"its tuning checkpoint tuning-{nm}.npz"))
        for stem, what in files:
            if stem.lower() in owner:
                j, other = owner[stem.lower()]
                raise v.err(
                    key, f"'{nm}' clashes with observer[{j}] '{names[j]}': {what} would be the same "
                    f"file as {other} of '{names[j]}' (file names compare ignoring case on macOS and "
                    "Windows). Rename one of them."
                )
        for stem, what in files:
            owner[stem.lower()] = (i, what)


def check_model_header(v: V, data) -> None:
    """Model keys (E, A, ...) at the top level: the ``[model]`` header is missing or
    placed after them (TOML puts every key before the first header at the top level)."""
    if not isinstance(data, dict):
        return
    stray = [k for k in data if k in _MODEL]
    if not stray:
        return
    keys = ", ".join(stray)
    if "model" in data:
        raise v.err(
            stray[0],
            f"{keys} {'is' if len(stray) == 1 else 'are'} at the top level of the file, outside the "
            "[model] table: TOML puts every key above the first [table] header at the top level. "
            "Move them below the [model] header.",
        )
    raise v.err(
        "model",
        f"missing [model] table: {keys} {'is' if len(stray) == 1 else 'are'} at the top level. Put "
        "them under a [model] table (a line `[model]` above E).",
    )


def state_count(**mats) -> tuple[int, Any]:
    """``(n, source)``: the state count most model matrices agree on (E rows and columns,
    A rows and columns, B rows, C and L columns; E wins a tie), and ``source(name)``, the
    names of the other matrices that give it (for error messages)."""
    votes = {
        "E": (mats["E"].shape[0], mats["E"].shape[1]),
        "A": tuple(mats["A"].shape[-2:]),
        "B": (mats["B"].shape[-2],),
        "C": (mats["C"].shape[1],),
        "L": (mats["L"].shape[1],),
    }
    count: dict[int, int] = {}
    for vals in votes.values():
        for x in vals:
            count[x] = count.get(x, 0) + 1
    best = max(count.values())
    n = votes["E"][0] if count[votes["E"][0]] == best else max(count, key=count.get)

    def source(name: str) -> str:
        others = [k for k, vals in votes.items() if k != name and n in vals]
        if not others:
            return "the other model matrices"
        return (", ".join(others[:-1]) + " and " + others[-1]) if len(others) > 1 else others[0]

    return n, source


def missing(v: V, key: str):
    raise v.err(key, f"missing required key '{key.rsplit('.', 1)[-1]}'.")
