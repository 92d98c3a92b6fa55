r"""`AbstractDesign`: what every design result of `fojax.design` is and can do.

A design result is a frozen dataclass on the host (NumPy data, JAX observer modules)
holding

- `observer`: the observer module (or the pair of a finite-time observer);
- `region`: where the error eigenvalues were placed;
- `certificate`: the matrix that proves it (the Lyapunov matrix $X$ of the region LMI);
- `report`: the float64 `fojax.design.VerificationReport` made when it was designed;

and offering

- `verify()`: the checks re-run on the stored numbers, through the one verification
  routine `fojax.design.verify` (residuals of the design conditions relative to their
  own terms, eigenvalues in the region, the region LMI at the certificate, plus the
  checks of the class: the common Lyapunov inequality of a Takagi–Sugeno design, the
  H∞ bound, the exactness of a finite-time reconstruction); raises
  `fojax.errors.DesignVerificationError` with the report when a check fails;
- `summary()`: the human-readable description (also ``str(design)``);
- `save(path)` / `load(path)`: one ``.npz`` file written atomically (`fojax._io`) with
  no code per class (format below).

**File format 3.** NumPy's ``.npz`` (no pickles): the arrays of the design under keys
that name their place (``observer/N``, ``structure/E``, ``params/Z``, ``designs/0/X``,
``report/eigenvalues`` …) and one entry ``__metadata__``, a JSON document with
``format = "fojax-design"``, ``format_version = 3``, ``fojax_version``, ``created``
(UTC, ISO 8601), ``design_class``, ``user`` (the caller's metadata), a ``summary``
(``kind``, ``region``, ``report`` of the class, for reading without fojax) and the
``tree``: the skeleton of the dataclass written by `fojax._serialize.encode` (every field,
with each array's key, shape and dtype). Loading rebuilds the object of the saved class
with bit-identical arrays, checks every array's shape and dtype against the skeleton, and
(by default) re-runs `verify()`: a damaged or edited file is refused with
`fojax.errors.InputError` (a missing or mis-shaped entry) or `fojax.errors.DesignVerificationError`
(numbers that no longer verify). Files of format 1 and 2 (fojax before this format)
still load (`fojax.design._legacy_io`).
"""

from __future__ import annotations

import abc
import dataclasses
import datetime as _dt
import io
import json
import pathlib
import zipfile
from typing import Any

import numpy as np

from .. import _serialize
from .._errors import InputError


FORMAT = "fojax-design"
#: 3: the generic skeleton (``tree``); 2: hand-written layouts per class; 1: functional only.
FORMAT_VERSION = 3
#: Fields whose value may be a user object that cannot be stored (then ``load(..., membership=)``).
OPTIONAL_FIELDS = ("membership",)


class AbstractDesign(abc.ABC):
    """Base of every design result (module docstring).

    Concrete classes are frozen dataclasses with (at least) the fields or properties
    `observer`, `region`, `certificate` and `report` (not defined here: a property of the
    base would become the default value of a dataclass field of the same name).
    """

    @abc.abstractmethod
    def verify(self):
        """Re-run the float64 verification on the stored numbers; returns the
        `VerificationReport`, raises `fojax.errors.DesignVerificationError` on a failed check."""

    def summary(self) -> str:
        """What was designed, and its verification report (``str(design)``)."""
        return str(self)

    def _summary_dict(self) -> dict:
        """A few fields for people reading a file's metadata without fojax."""
        out: dict[str, Any] = {}
        kind = getattr(self, "kind", None)
        if isinstance(kind, str):
            out["kind"] = kind
        region = getattr(self, "region", None)
        if hasattr(region, "to_dict"):
            out["region"] = region.to_dict()
        s = getattr(self, "structure", None)
        if s is not None:
            out["sizes"] = {k: int(getattr(s, k)) for k in ("n", "m", "p", "q", "q0")}
        report = getattr(self, "report", None)
        if hasattr(report, "to_dict"):
            out["report"] = report.to_dict()
        return out

    def save(self, path, *, overwrite: bool = False, metadata: dict | None = None) -> pathlib.Path:
        """Write this design to one ``.npz`` file, atomically (module docstring).

        **Arguments:**

        - `path`: the file (conventionally ``*.npz``); its directory must exist. Inside a
          results folder the path must stay inside it (`fojax.errors.UnsafePathError`).
        - `overwrite`: replace an existing file (default: `FileExistsError`).
        - `metadata`: JSON-serialisable user metadata (e.g. the config file's name).

        **Returns:** the path written.
        """
        return save(self, path, overwrite=overwrite, metadata=metadata)

    @classmethod
    def load(cls, path, *, membership=None, verify: bool = True):
        """Read a design file (any format version) and, by default, re-verify it.

        **Arguments:**

        - `path`: a file written by `save` / `fojax.save_design` / `fojax design`.
        - `membership`: for a Takagi–Sugeno design whose membership functions are not a
          fojax class (a file never makes fojax import code): the plant's membership.
        - `verify`: re-run `verify()` on the loaded numbers (default ``True``).

        **Returns:** the design, of the saved class (which must be `cls` or a subclass).
        """
        design = load(path, membership=membership, verify=verify)
        if not isinstance(design, cls):
            raise InputError(f"{path} holds a {type(design).__name__}, not a {cls.__name__}; "
                             f"load it with fojax.load_design(path) or {type(design).__name__}.load(path).")
        return design


# --------------------------------------------------------------------------- files


def _version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("fojax")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        return "unknown"


def save(design, path, *, overwrite: bool = False, metadata: dict | None = None) -> pathlib.Path:
    """`AbstractDesign.save` (format 3, module docstring)."""
    from .._io import atomic_write
    from .._serialize import json_safe as _json_safe

    if not isinstance(design, AbstractDesign):
        raise TypeError(f"save_design expects a design result of fojax.design (a fojax.design.AbstractDesign: "
                        f"FunctionalObserverDesign, TakagiSugenoObserverDesign, ...), got {type(design).__name__}.")
    arrays: dict[str, np.ndarray] = {}
    try:
        tree = _serialize.encode(design, arrays, optional=OPTIONAL_FIELDS)
    except _serialize.NotStorable as err:
        raise TypeError(f"{type(design).__name__} cannot be saved: {err}.") from None
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "fojax_version": _version(),
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "design_class": type(design).__name__,
        "summary": _json_safe(design._summary_dict()),
        "user": _json_safe(metadata or {}),
        "tree": tree,
    }
    if "__metadata__" in arrays:  # pragma: no cover - keys are field paths
        raise TypeError("a design field is named __metadata__")
    arrays["__metadata__"] = np.array(json.dumps(meta))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write(path, buf.getvalue(), overwrite=overwrite)


_EXPECTED = (
    "load_design reads the .npz files written by fojax.results.save_design or `fojax design` "
    "(<observer>.npz in its results folder) or design.save"
)


def _what_file(head: bytes, path: pathlib.Path) -> str:
    if head.startswith(b"\x93NUMPY"):
        return "a single NumPy array (.npy), not a design archive"
    if not head:
        return "empty"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return "a binary file that is not a .npz archive"
    if path.suffix.lower() == ".toml" or head.lstrip().startswith((b"[", b"name", b"#")):
        return "a text file (a TOML config?), not a .npz archive"
    return "a text file, not a .npz archive"


def open_design_file(path):
    """`np.load` of a design file (no pickles), with a clear `InputError` for anything
    that is not a ``.npz`` archive."""
    path = pathlib.Path(path)
    if path.is_dir():
        raise InputError(f"{path} is a folder; {_EXPECTED}.")
    with open(path, "rb") as f:  # FileNotFoundError names the missing file
        head = f.read(64)
    if not head.startswith(b"PK"):
        raise InputError(f"{path} is not a fojax design file: it is {_what_file(head, path)}; {_EXPECTED}.")
    try:
        with zipfile.ZipFile(path) as z:  # np.load leaks its file on a damaged archive
            z.namelist()
    except (ValueError, OSError, zipfile.BadZipFile) as err:
        raise InputError(
            f"{path} is not a readable fojax design file ({type(err).__name__}: {err}; a damaged or "
            f"truncated archive?); {_EXPECTED}."
        ) from None
    return np.load(path, allow_pickle=False)


def metadata(data, path) -> dict:
    """The checked JSON metadata of an open design file."""
    if "__metadata__" not in data.files:
        raise InputError(f"{path} is not a fojax design file (no __metadata__ entry); {_EXPECTED}.")
    try:
        meta = json.loads(str(data["__metadata__"][()]))
    except (ValueError, TypeError) as err:
        raise InputError(f"{path}: the __metadata__ entry is not valid JSON ({err}); the file was changed "
                         "or damaged. Re-create it with design.save(path) or `fojax design`.") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{path} is not a fojax design file (format "
                         f"{meta.get('format') if isinstance(meta, dict) else meta!r}).")
    if int(meta.get("format_version", 0)) > FORMAT_VERSION:
        raise InputError(
            f"{path} has design format version {meta['format_version']}, newer than this fojax "
            f"reads ({FORMAT_VERSION}); upgrade fojax."
        )
    return meta


def read_metadata(path) -> dict:
    """The JSON metadata of a saved design (no arrays are rebuilt)."""
    with open_design_file(path) as data:
        return metadata(data, path)


def _mark_saved(obj, saved: dict | None) -> None:
    """Put the file's metadata in ``solver["saved"]`` of every design in the tree (the
    nested designs of a finite-time design included); ``saved=None`` removes it."""
    if isinstance(obj, AbstractDesign):
        solver = getattr(obj, "solver", None)
        if isinstance(solver, dict):
            if saved is None:
                solver.pop("saved", None)
            else:
                solver["saved"] = saved
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            for item in v if isinstance(v, tuple | list) else (v,):
                if isinstance(item, AbstractDesign):
                    _mark_saved(item, saved)


def load(path, *, membership=None, verify: bool = True):
    """`AbstractDesign.load` for any saved class (`fojax.load_design`)."""
    from .._dtype import require_x64

    require_x64("load_design")
    path = pathlib.Path(path)
    with open_design_file(path) as data:
        meta = metadata(data, path)
        arrays = {k: np.array(data[k]) for k in data.files if k != "__metadata__"}
    saved = {k: meta[k] for k in ("fojax_version", "created", "format_version", "user") if k in meta}
    name = meta.get("design_class", "FunctionalObserverDesign")
    if int(meta.get("format_version", 0)) < 3:
        from ._legacy_io import load_legacy

        design = load_legacy(meta, arrays, saved, path, membership=membership)
    else:
        if "tree" not in meta:
            raise InputError(f"{path} has no design skeleton ('tree' in __metadata__); the file was changed or "
                             "damaged. Re-create it with design.save(path) or `fojax design`.")
        used: set = set()
        overrides = {} if membership is None else {"membership": membership}
        try:
            design = _serialize.decode(meta["tree"], arrays, source=str(path), overrides=overrides, used=used)
        except _serialize.NotStorable as err:
            fld = getattr(err, "field", None)
            fix = (" Pass the plant's membership: load_design(path, membership=plant.membership)."
                   if fld == "membership" else " Load it with the fojax version that wrote it.")
            raise InputError(f"{path}: the {fld or 'design'} of this {name} cannot be rebuilt: "
                             f"{getattr(err, 'why', err)}.{fix}") from None
        if membership is not None and "membership" not in used:
            raise InputError(f"membership= applies to Takagi–Sugeno designs only; {path} holds a {name}.")
        if not isinstance(design, AbstractDesign):
            raise InputError(f"{path} holds a {type(design).__name__}, not a design result of fojax.design.")
        _mark_saved(design, saved)
    if verify:
        design.verify()
    return design


def with_feedthrough(design, D):
    r"""The design for a plant with feedthrough $y = Cx + Du$ (the one rule of every
    ``design_*`` entry point): its observer(s) take $y - Du$
    (`fojax.observer._base.fold_feedthrough`: $W_u \leftarrow W_u - W_y D$) and its
    structure records ``D``, so an observer rebuilt from the parameters (tuning) folds it
    too. The conditions, certificate and error dynamics do not depend on ``D``. A zero
    ``D`` returns `design` itself."""
    D = np.asarray(D, dtype=float)
    if not np.any(D):
        return design
    from ..observer._base import AbstractObserver, fold_feedthrough
    from ._parameterization import FunctionalObserverStructure

    def fold(v):
        if isinstance(v, AbstractObserver):
            return fold_feedthrough(v, D)
        if isinstance(v, FunctionalObserverStructure):
            return dataclasses.replace(v, D=D)
        if isinstance(v, AbstractDesign):
            return with_feedthrough(v, D)
        if isinstance(v, tuple):
            return tuple(fold(x) for x in v)
        return v

    return dataclasses.replace(design, **{f.name: fold(getattr(design, f.name)) for f in dataclasses.fields(design)
                                          if f.init})
