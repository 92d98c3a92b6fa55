r"""Saved designs and results folders that last.

**Design files.** `save_design` (= ``design.save(path)``) writes one ``.npz`` file
(NumPy's zip of ``.npy`` arrays, no pickles) holding every array of a design result of
`fojax.design` in float64 exactly as computed, plus one entry ``__metadata__`` with a
JSON document: ``format`` = ``"fojax-design"``, ``format_version`` = 3,
``fojax_version``, ``created``, ``design_class``, ``user`` (the caller's metadata), a
readable ``summary`` (``kind``, ``region``, ``sizes``, ``report``) and the ``tree``: the
skeleton of the design's dataclass, every field, each array named by its path
(``observer/N``, ``structure/E``, ``params/Z``, ``designs/0/X`` …) with its shape and dtype.
No design class has code of its own for this: `fojax.design.AbstractDesign` and
`fojax._serialize` (format, damage checks, the classes a file may name: fojax's only).

`load_design` rebuilds an object of the saved class with bit-identical arrays
(``np.array_equal`` on every entry), so the loaded observer produces identical
outputs, and re-runs its float64 verification (``verify=False`` skips that). Files of
format 2 (hand-written layouts per class) and format 1 (functional designs only) still
load (`fojax.design._legacy_io`; tested on files written by that code,
``tests/data/designs_v2``).

**Atomic, never clobbering.** Every file is written to a temporary file in the
target directory, flushed to disk and then moved into place (`os.replace`, or a hard
link when overwriting is not allowed, so that a concurrent writer cannot be clobbered
either), with the mode the user's umask gives (``0o666 & ~umask``). An existing file is
never replaced unless ``overwrite=True``: `FileExistsError` names it and says how to
proceed. (The one writer is `fojax._io.atomic_write`.)

**Results folders.** `new_results_folder` creates ``<root>/<prefix>-YYYYmmdd-HHMMSS``
(with a ``-2``, ``-3``, … suffix if that name is taken) and never reuses a folder;
with an explicit `name`, an existing non-empty folder is refused unless
``overwrite=True``. Names are single portable file-name components (`NAME_RULE`).
A path built from a results folder must resolve inside it (`fojax.errors.UnsafePathError`
otherwise, nothing written), and every file written in it is recorded in its manifest
``fojax-manifest.json`` (relative path, SHA-256, size). ``overwrite=True`` first removes
the files the previous run recorded there (a file changed since it was written is
kept, and so is every file fojax did not write), so the folder then holds the new
run's files only, beside the user's own.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import pathlib
from typing import Any

import numpy as np

from .._io import (
    atomic_write as _atomic_write,
    MANIFEST as MANIFEST,
    name_problem,
    NAME_RULE,
    register_results_folder,
    suggest_name,
)
from .._serialize import json_safe as _json_safe  # the one JSON-safe copy


FORMAT = "fojax-design"
#: 2: every design class (``design_class`` entry); 1: `FunctionalObserverDesign` only.
FORMAT_VERSION = 2

_OBSERVER_FIELDS = ("N", "J", "F", "H", "S", "G", "M", "P", "Q", "Wu", "Wy")
_STRUCTURE_FIELDS = ("E", "A", "B", "C", "L", "R", "Eperp", "Z0", "PiZ")
_TOP_FIELDS = ("T", "K", "Z_eff", "X")


def fojax_version() -> str:
    """The installed fojax version (``"unknown"`` when not installed as a distribution)."""
    import importlib.metadata

    try:
        return importlib.metadata.version("fojax")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        return "unknown"


def _timestamp() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- atomic writes


def atomic_write_bytes(path, data: bytes, *, overwrite: bool = False) -> pathlib.Path:
    """Write `data` to `path` atomically (temporary file in the same directory, fsync, rename).

    **Arguments:**

    - `path`: destination file; its directory must exist.
    - `data`: the bytes to write.
    - `overwrite`: replace an existing file. Otherwise an existing file raises
      `FileExistsError` (checked atomically: the temporary file is hard-linked into
      place, which fails if the name exists).

    **Returns:** the destination as a `pathlib.Path`.

    The file gets the mode the umask gives (``0o666 & ~umask``). A path built from a
    results folder of `new_results_folder` must resolve inside it (`fojax.errors.UnsafePathError`
    otherwise), and the file is recorded in the folder's manifest (module docstring).
    """
    return _atomic_write(path, bytes(data), overwrite=overwrite)


def atomic_write_text(path, text: str, *, overwrite: bool = False) -> pathlib.Path:
    """`atomic_write_bytes` for UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def atomic_write_json(path, obj: Any, *, overwrite: bool = False) -> pathlib.Path:
    """Write `obj` as indented JSON, atomically (non-JSON values are converted)."""
    return atomic_write_text(path, json.dumps(_json_safe(obj), indent=2) + "\n", overwrite=overwrite)


def atomic_write_npz(path, arrays: dict, *, overwrite: bool = False) -> pathlib.Path:
    """Write a dict of arrays as an uncompressed ``.npz`` file, atomically."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    return atomic_write_bytes(path, buf.getvalue(), overwrite=overwrite)


# --------------------------------------------------------------------------- designs

def save_design(design, path, *, overwrite: bool = False, metadata: dict | None = None) -> pathlib.Path:
    """Save a verified design to one ``.npz`` file (``design.save(path)``; format 3 of
    `fojax.design.AbstractDesign`).

    **Arguments:**

    - `design`: a design result of `fojax.design` (any `fojax.design.AbstractDesign`:
      `FunctionalObserverDesign`, `TakagiSugenoObserverDesign`,
      `UnknownInputObserverDesign`, `FiniteTimeObserverDesign`, `FaultEstimatorDesign`).
    - `path`: destination file (conventionally ``*.npz``); its directory must exist.
    - `overwrite`: replace an existing file (default: raise `FileExistsError`).
    - `metadata`: optional JSON-serialisable user metadata (e.g. the config file).

    **Returns:** the path written.
    """
    from ..design._base import save

    return save(design, path, overwrite=overwrite, metadata=metadata)


def read_design_metadata(path) -> dict:
    """The JSON metadata of a saved design (no arrays are rebuilt)."""
    from ..design._base import read_metadata

    return read_metadata(path)


def load_design(path, *, membership=None, verify: bool = True):
    """Load a design written by `save_design` (any format version); arrays are
    bit-identical to the saved ones.

    **Arguments:**

    - `path`: a file written by `save_design`, ``design.save`` or `fojax design`.
    - `membership`: only for Takagi–Sugeno designs whose membership functions are not
      fojax classes (fojax rebuilds `fojax.plant.SectorMembership` and the other fojax
      memberships from the file, but never imports code named in a file): the
      plant's `fojax.plant.AbstractMembership`.
    - `verify`: re-run the design's float64 verification (``design.verify()``) on the
      loaded numbers (default ``True``).

    **Returns:** an object of the saved class whose arrays equal the saved ones bit for
    bit, so its observer produces identical outputs. The metadata (fojax version,
    creation time, user metadata) is in ``design.solver["saved"]`` (for finite-time and
    fault-estimator designs: in the `solver` of each inner `FunctionalObserverDesign`).

    **Raises:** `fojax.errors.InputError` for a file that is not a fojax design (a config file,
    any other file or archive), has a newer format, holds a design class this version
    does not know, or was damaged (a missing array, an array of the wrong shape or dtype,
    each named); `fojax.errors.DesignVerificationError` when the loaded numbers fail verification.
    """
    from ..design._base import load

    return load(path, membership=membership, verify=verify)


# --------------------------------------------------------------------------- folders


def _check_name(what: str, value) -> None:
    from .._errors import InputError

    problem = name_problem(value)
    if problem is not None:
        raise InputError(
            f"{what} {value!r} cannot be used: {problem}. The {NAME_RULE}; e.g. "
            f"{suggest_name(value, 'run1')!r}."
        )


def new_results_folder(
    root=".", *, prefix: str = "fojax", name: str | None = None, overwrite: bool = False
) -> pathlib.Path:
    """Create a new folder for the results of one run.

    **Arguments:**

    - `root`: parent directory (any path; created if missing).
    - `prefix`: the folder is ``<root>/<prefix>-YYYYmmdd-HHMMSS`` (UTC), with ``-2``,
      ``-3``, … appended if that name exists already: an earlier run is never reused.
    - `name`: an explicit folder name instead of the timestamp. If it exists and is not
      empty, `FileExistsError` unless ``overwrite=True``.
    - `overwrite`: reuse an existing `name` folder for a new run. The files the previous
      fojax run wrote there (listed in its manifest ``fojax-manifest.json``) are removed
      first, except those changed since they were written; files fojax did not write stay.
      A folder without a manifest (written by fojax < this version) keeps every file;
      files of the new run replace those of the same name.

    `prefix` and `name` must be single portable file-name components (`NAME_RULE`;
    `fojax.errors.InputError` otherwise), so the folder is always inside `root`.

    **Returns:** the created folder. Files written into it through paths built from it are
    confined to it and recorded in its manifest (module docstring).
    """
    _check_name("results folder prefix", prefix)
    if name is not None:
        _check_name("results folder name (--name)", name)
    root = pathlib.Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if name is not None:
        folder = root / name
        reuse = False
        try:
            folder.mkdir()
        except FileExistsError:
            if not folder.is_dir():
                raise FileExistsError(f"{folder} exists and is not a folder.") from None
            reuse = any(folder.iterdir())
            if reuse and not overwrite:
                raise FileExistsError(
                    f"results folder {folder} already exists and is not empty; fojax never reuses "
                    "an earlier run's folder. Choose another name, or pass overwrite=True "
                    "(CLI: --overwrite) to replace the previous run in it."
                ) from None
        register_results_folder(folder, replace_previous_run=reuse)
        return folder
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%d-%H%M%S")
    base = f"{prefix}-{stamp}"
    for i in range(1, 10_000):
        folder = root / (base if i == 1 else f"{base}-{i}")
        try:
            folder.mkdir()  # atomic: fails if it exists
        except FileExistsError:
            continue
        register_results_folder(folder)
        return folder
    raise FileExistsError(f"could not create a new results folder under {root}")  # pragma: no cover


# --------------------------------------------------------------------------- metrics


def _flatten(d, prefix=""):
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            yield from _flatten(v, key + "/")
        else:
            yield key, v


def write_metrics(
    folder, metrics: dict, *, name: str = "metrics", overwrite: bool = False, max_json_size: int = 10_000
) -> tuple[pathlib.Path, pathlib.Path]:
    """Write metrics as ``<name>.json`` (readable) and ``<name>.npz`` (exact arrays), atomically.

    **Arguments:**

    - `folder`: the results folder.
    - `metrics`: a (nested) dict of numbers, strings and arrays, e.g.
      ``{"PO": {"IAE": iae_per_sample, "mean_IAE": 1.2}, "samples": 64}``.
    - `name`: the file stem.
    - `overwrite`: replace existing files (default: `FileExistsError`).
    - `max_json_size`: arrays with more entries are written to the NPZ only (the JSON
      records their shape and the NPZ key).

    **Returns:** ``(json_path, npz_path)``. Every array and number is in the NPZ under its
    ``/``-joined key (bit-exact float64); the JSON holds the same tree.
    """
    folder = pathlib.Path(folder)
    arrays = {}
    for key, v in _flatten(metrics):
        if isinstance(v, str):
            continue
        arr = np.asarray(v)
        if arr.dtype == object:
            raise TypeError(f"metric {key!r} is not numeric (dtype object); cannot be written.")
        arrays[key] = arr

    def tree(d, prefix=""):
        out = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict):
                out[k] = tree(v, key + "/")
            elif isinstance(v, str):
                out[k] = v
            else:
                arr = np.asarray(v)
                if arr.size > max_json_size:
                    out[k] = {"shape": list(arr.shape), "npz_key": key}
                else:
                    out[k] = _json_safe(arr.item() if arr.ndim == 0 else arr)
        return out

    npz = atomic_write_npz(folder / f"{name}.npz", arrays, overwrite=overwrite)
    js = atomic_write_json(folder / f"{name}.json", tree(metrics), overwrite=overwrite)
    return js, npz
