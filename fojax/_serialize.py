r"""One codec for fojax's host objects: a JSON skeleton plus named arrays (no pickles).

`encode` walks an object tree — dataclasses (frozen design results, reports,
certificates) and `equinox.Module`\ s (observers, regions, plants, memberships), dicts,
tuples, lists, numbers, strings — and returns ``(skeleton, arrays)``:

- every array (NumPy or JAX, any dtype but ``object``) and every NumPy scalar goes into
  `arrays` under a ``/``-joined key that names its place in the tree
  (``observer/N``, ``params/Z``, ``designs/0/X`` …); the skeleton records its key, shape,
  dtype and whether it was a JAX array;
- a dataclass or module becomes ``{"$": "object", "class": "module:qualname", "fields": …}``
  with *every* field (static or not, ``init`` or not), so `decode` can restore it without
  calling its ``__init__`` — the way `jax.tree_util` unflattens an equinox module — and no
  class needs code of its own to be saved;
- Python floats are stored by ``repr`` (exact, also ``inf``/``nan``); ints, bools,
  strings and ``None`` as JSON.

`decode` is the inverse; arrays come back bit for bit (``np.array_equal``, same dtype and
shape). It imports classes **only from fojax** (never code named in a file): a class from
elsewhere, or a value that is not storable (a Python callable), can only be restored
through `overrides` keyed by the field name (``membership=`` of `fojax.load_design`).

Inside a plain dict (free-form solver information) a value that is none of the above is
stored as its ``str`` — the one lossy case, recorded as ``{"$": "str"}``. Outside dicts an
unstorable value is an error at save time (`NotStorable`), except under a field named in
`encode`'s ``optional`` (the T-S membership), which is recorded as unstored.

A field a class gained after a file was written (e.g. a plant's feedthrough ``D``)
takes its default (``D = 0``) when that file is read.

Every problem found while decoding (a missing array, a wrong shape or dtype, an unknown
class) raises `fojax.errors.InputError` naming the entry, what was expected and what was found.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

import numpy as np

from ._errors import InputError


class NotStorable(Exception):
    """A value `encode` cannot store; the message says which and why."""


def _is_instance_dataclass(obj) -> bool:
    return dataclasses.is_dataclass(obj) and not isinstance(obj, type)


def class_path(obj_or_cls) -> str:
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    return f"{cls.__module__}:{cls.__qualname__}"


def encode(obj, arrays: dict, key: str = "", *, optional: tuple[str, ...] = (), _in_dict: bool = False):
    """The skeleton of `obj`; arrays are added to `arrays` (see the module docstring).

    `optional`: field names whose value may be unstorable; it is then recorded as
    ``{"$": "unstored", "class": …, "reason": …}`` instead of raising `NotStorable`.
    """
    import jax

    if obj is None or isinstance(obj, bool | int | str) and not isinstance(obj, np.generic):
        return obj
    if isinstance(obj, float) and not isinstance(obj, np.generic):
        return {"$": "float", "repr": repr(obj)}
    if isinstance(obj, complex):
        return {"$": "complex", "real": repr(obj.real), "imag": repr(obj.imag)}
    if isinstance(obj, np.ndarray | np.generic | jax.Array):
        arr = np.asarray(obj)
        if arr.dtype == object:
            raise NotStorable(f"{key or 'the value'} is an array of Python objects (dtype object)")
        k = key or "value"
        if k in arrays:  # pragma: no cover - keys are paths in a tree, hence unique
            raise NotStorable(f"two arrays at {k!r}")
        arrays[k] = arr
        kind = "scalar" if isinstance(obj, np.generic) else "jax" if isinstance(obj, jax.Array) else "numpy"
        return {"$": "array", "key": k, "kind": kind, "dtype": arr.dtype.str, "shape": list(arr.shape)}
    sub = (lambda name: f"{key}/{name}" if key else str(name))
    if isinstance(obj, dict):
        items = []
        for i, (k, v) in enumerate(obj.items()):
            name = k if isinstance(k, str) and "/" not in k else f"#{i}"
            try:
                items.append([encode(k, arrays, sub(name), _in_dict=True),
                              encode(v, arrays, sub(name), optional=optional, _in_dict=True)])
            except NotStorable:
                items.append([encode(k, arrays, sub(name), _in_dict=True), {"$": "str", "value": str(v)}])
        return {"$": "dict", "items": items}
    if isinstance(obj, tuple | list):
        items = [encode(v, arrays, sub(str(i)), optional=optional, _in_dict=_in_dict) for i, v in enumerate(obj)]
        return {"$": "tuple" if isinstance(obj, tuple) else "list", "items": items}
    if _is_instance_dataclass(obj):
        if _in_dict and not class_path(obj).startswith(("fojax:", "fojax.")):
            raise _Unstorable(type(obj).__name__)  # free-form info: stored as its str (never imported)
        fields = {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            try:
                fields[f.name] = encode(v, arrays, sub(f.name), optional=optional, _in_dict=_in_dict)
            except _Unstorable:
                reason = f"{type(obj).__qualname__}.{f.name} is a {type(v).__name__}"
                if f.name not in optional:
                    raise NotStorable(reason) from None
                fields[f.name] = {"$": "unstored", "class": class_path(v), "reason": reason}
            except NotStorable as err:
                if f.name not in optional:
                    raise
                fields[f.name] = {"$": "unstored", "class": class_path(v), "reason": str(err)}
        return {"$": "object", "class": class_path(obj), "fields": fields}
    raise _Unstorable(type(obj).__name__)


class _Unstorable(NotStorable):
    """A leaf of an unknown type (the enclosing dataclass field names it in the message)."""


def _fojax_class(path: str, where: str):
    """The fojax class named ``module:qualname``; `NotStorable` for anything else."""
    module, _, qualname = path.partition(":")
    if module != "fojax" and not module.startswith("fojax."):
        raise NotStorable(f"{path} is not a fojax class (fojax never imports code named in a file)")
    try:
        cls = importlib.import_module(module)
        for part in qualname.split("."):
            cls = getattr(cls, part)
    except (ImportError, AttributeError):
        raise NotStorable(f"{path} does not exist in this fojax version") from None
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise NotStorable(f"{path} is not a dataclass or equinox.Module")
    return cls


def decode(node, arrays: dict, *, source: str = "the file", overrides: dict | None = None, _key: str = "",
           used: set | None = None) -> Any:
    """Rebuild the object of skeleton `node` (inverse of `encode`).

    `overrides` maps a field name to the value to use for that field wherever it occurs
    (e.g. ``{"membership": plant.membership}``); `used` collects the names applied.
    """
    overrides = overrides or {}
    if node is None or isinstance(node, bool | int | str):
        return node
    if isinstance(node, list):  # pragma: no cover - lists are always tagged
        return [decode(v, arrays, source=source, overrides=overrides, used=used) for v in node]
    if not isinstance(node, dict) or "$" not in node:
        raise InputError(f"{source}: entry {_key or 'root'!r} of the design skeleton is not understood "
                         f"({str(node)[:80]}); the file was changed or damaged. Re-create it with "
                         "design.save(path) or `fojax design`.")
    tag = node["$"]
    if tag == "float":
        return float(node["repr"])
    if tag == "complex":
        return complex(float(node["real"]), float(node["imag"]))
    if tag == "str":
        return node["value"]
    if tag == "array":
        return _array(node, arrays, source)
    if tag in ("tuple", "list"):
        items = [decode(v, arrays, source=source, overrides=overrides, _key=f"{_key}/{i}", used=used)
                 for i, v in enumerate(node["items"])]
        return tuple(items) if tag == "tuple" else items
    if tag == "dict":
        return {decode(k, arrays, source=source, overrides=overrides, used=used):
                decode(v, arrays, source=source, overrides=overrides, _key=f"{_key}/{k}", used=used)
                for k, v in node["items"]}
    if tag == "object":
        cls = _fojax_class(node["class"], _key)
        obj = object.__new__(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        saved = set(node["fields"])
        added = {f.name: f for f in dataclasses.fields(cls) if f.name not in saved and _has_default(cls, f)}
        if names != saved | set(added) or not saved <= names:
            raise InputError(
                f"{source}: {node['class']} at {_key or 'the root'!r} has fields {sorted(saved)} in the file "
                f"but {sorted(names)} in this fojax version; load it with the fojax version that wrote it "
                "and re-create the design.")
        for name, f in node["fields"].items():
            if name in overrides:
                value = overrides[name]
                if used is not None:
                    used.add(name)
            elif isinstance(f, dict) and f.get("$") == "unstored":
                raise _Missing(name, f["class"], f"it was not stored ({f['reason']})")
            else:
                try:
                    value = decode(f, arrays, source=source, overrides=overrides, _key=f"{_key}/{name}", used=used)
                except NotStorable as err:
                    if isinstance(err, _Missing):
                        raise
                    raise _Missing(name, f.get("class", "?"), str(err)) from None
            object.__setattr__(obj, name, value)
        for name, f in added.items():  # a field added after the file was written: its default
            value = (getattr(cls, "_file_defaults", {}).get(name) or (lambda o, f=f: f.default))(obj)
            object.__setattr__(obj, name, value)
        return obj
    if tag == "unstored":
        raise _Missing(_key.rsplit("/", 1)[-1], node["class"], f"it was not stored ({node['reason']})")
    raise InputError(f"{source}: unknown entry type {tag!r} at {_key or 'the root'!r}; the file was "
                     "written by a newer fojax, or damaged. Upgrade fojax or re-create the design.")


def _has_default(cls, f) -> bool:
    """A field a file written before it existed may omit: it has a dataclass default, or
    the class names how to compute it (``_file_defaults``: name -> function of the object
    with the saved fields set)."""
    return f.default is not dataclasses.MISSING or f.name in getattr(cls, "_file_defaults", {})


class _Missing(NotStorable):
    """A field whose value cannot be rebuilt from the file (the caller names the fix)."""

    def __init__(self, field: str, cls: str, why: str):
        super().__init__(f"{cls} cannot be rebuilt: {why}")
        self.field, self.cls, self.why = field, cls, why


def _array(node: dict, arrays: dict, source: str):
    k = node["key"]
    if k not in arrays:
        raise InputError(f"{source} has no array {k!r}, which the design needs (its skeleton lists it); the "
                         "file was changed or truncated. Re-create it with design.save(path) or `fojax design`.")
    arr = arrays[k]
    shape, dtype = tuple(node["shape"]), np.dtype(node["dtype"])
    if arr.shape != shape or arr.dtype != dtype:
        raise InputError(
            f"{source}: array {k!r} has shape {arr.shape} and dtype {arr.dtype}, but the design "
            f"expects shape {shape} and dtype {dtype}; the file was changed or damaged. Re-create it "
            "with design.save(path) or `fojax design`.")
    if node["kind"] == "scalar":
        return arr[()]
    if node["kind"] == "jax":
        import jax.numpy as jnp

        return jnp.asarray(arr)
    return arr


def json_safe(value: Any):
    """A JSON-serialisable copy (arrays to lists, numpy scalars to Python, others to str)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if np.isfinite(value) else str(value)
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, np.ndarray) or hasattr(value, "__array__"):
        arr = np.asarray(value)
        if np.iscomplexobj(arr):
            return {"real": json_safe(arr.real.tolist()), "imag": json_safe(arr.imag.tolist())}
        return json_safe(arr.tolist())
    return str(value)
