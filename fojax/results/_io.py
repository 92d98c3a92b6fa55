r"""Saved designs and results folders that last.

**Design files.** `save_design` writes one ``.npz`` file (NumPy's zip of ``.npy``
arrays, no pickles) holding every matrix of a `fojax.design.FunctionalObserverDesign`
in float64 exactly as computed, plus one entry ``__metadata__`` with a JSON document:

- ``format`` = ``"fojax-design"``, ``format_version`` = 1, ``fojax_version``,
  ``created`` (UTC timestamp, ISO 8601);
- ``kind``, ``region`` (`AbstractRegion.to_dict`), the static fields of the
  structure (``q1``, ``psi``, ``solvability_residual``), the sizes ``n, m, p, q, q0``;
- ``report``: the `VerificationReport` (`to_dict`, eigenvalues kept in the arrays);
- ``solver``: the solver information (JSON-safe copy; non-JSON values as strings);
- ``user``: optional user metadata passed to `save_design`.

Array entries are named ``observer/N`` … ``observer/Wy``, ``structure/E``, ``A``,
``B``, ``C``, ``L``, ``R``, ``Eperp``, ``Z0``, ``PiZ`` (plant matrices, functional
and the parameterization), ``params/Z`` … ``params/G``, ``T``, ``K``, ``Z_eff``,
``X`` (LMI certificate) and ``report/eigenvalues``. `load_design` rebuilds the
design with bit-identical arrays (``np.array_equal`` on every entry), so the loaded
observer produces identical outputs.

**Atomic, never clobbering.** Every file is written to a temporary file in the
target directory and then moved into place (`os.replace`, or a hard link when
overwriting is not allowed, so that a concurrent writer cannot be clobbered either).
An existing file is never replaced unless ``overwrite=True``: `FileExistsError`
names it and says how to proceed.

**Results folders.** `new_results_folder` creates ``<root>/<prefix>-YYYYmmdd-HHMMSS``
(with a ``-2``, ``-3``, … suffix if that name is taken) and never reuses a folder;
with an explicit `name`, an existing folder is refused unless ``overwrite=True``.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import os
import pathlib
import tempfile
from typing import Any

import numpy as np


FORMAT = "fojax-design"
FORMAT_VERSION = 1

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


def _exists_message(path: pathlib.Path) -> str:
    return (
        f"{path} already exists; fojax never overwrites earlier results silently. "
        "Choose another path, delete the file, or pass overwrite=True (CLI: --overwrite)."
    )


def atomic_write_bytes(path, data: bytes, *, overwrite: bool = False) -> pathlib.Path:
    """Write `data` to `path` atomically (temporary file in the same directory, then rename).

    **Arguments:**

    - `path`: destination file; its directory must exist.
    - `data`: the bytes to write.
    - `overwrite`: replace an existing file. Otherwise an existing file raises
      `FileExistsError` (checked atomically: the temporary file is hard-linked into
      place, which fails if the name exists).

    **Returns:** the destination as a `pathlib.Path`.
    """
    path = pathlib.Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(_exists_message(path))
    directory = path.parent if str(path.parent) else pathlib.Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"directory {directory} does not exist; create it first.")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise FileExistsError(_exists_message(path)) from None
            except OSError:  # file systems without hard links: best effort
                if path.exists():
                    raise FileExistsError(_exists_message(path)) from None
                os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
    return path


def atomic_write_text(path, text: str, *, overwrite: bool = False) -> pathlib.Path:
    """`atomic_write_bytes` for UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def _json_safe(value: Any):
    """A JSON-serialisable copy (arrays to lists, numpy scalars to Python, others to str)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if np.isfinite(value) else str(value)
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    if isinstance(value, np.ndarray) or hasattr(value, "__array__"):
        arr = np.asarray(value)
        if np.iscomplexobj(arr):
            return {"real": _json_safe(arr.real.tolist()), "imag": _json_safe(arr.imag.tolist())}
        return _json_safe(arr.tolist())
    return str(value)


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
    """Save a functional-observer design to one ``.npz`` file (format in the module docstring).

    **Arguments:**

    - `design`: a `fojax.design.FunctionalObserverDesign`.
    - `path`: destination file (conventionally ``*.npz``); its directory must exist.
    - `overwrite`: replace an existing file (default: raise `FileExistsError`).
    - `metadata`: optional JSON-serialisable user metadata (e.g. the config file).

    **Returns:** the path written.
    """
    from ..design import FunctionalObserverDesign

    if not isinstance(design, FunctionalObserverDesign):
        raise TypeError(
            f"save_design expects a fojax.design.FunctionalObserverDesign, got "
            f"{type(design).__name__}."
        )
    obs, s = design.observer, design.structure
    arrays: dict[str, np.ndarray] = {}
    for k in _OBSERVER_FIELDS:
        arrays[f"observer/{k}"] = np.asarray(getattr(obs, k))
    for k in _STRUCTURE_FIELDS:
        arrays[f"structure/{k}"] = np.asarray(getattr(s, k))
    for k, v in design.params.items():
        arrays[f"params/{k}"] = np.asarray(v)
    for k in _TOP_FIELDS:
        arrays[k] = np.asarray(getattr(design, k))
    arrays["report/eigenvalues"] = np.asarray(design.report.eigenvalues)
    report = design.report.to_dict()
    report.pop("eigenvalues_real", None)
    report.pop("eigenvalues_imag", None)
    report["extra"] = _json_safe(dict(design.report.extra))
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "fojax_version": fojax_version(),
        "created": _timestamp(),
        "kind": design.kind,
        "observer_kind": obs.kind,
        "region": design.region.to_dict(),
        "region_description": design.region.describe(),
        "structure": {
            "q1": int(s.q1),
            "psi": s.psi,
            "solvability_residual": float(s.solvability_residual),
        },
        "sizes": {"n": int(s.n), "m": int(s.m), "p": int(s.p), "q": int(s.q), "q0": int(s.q0)},
        "params": sorted(design.params),
        "report": report,
        "solver": _json_safe(design.solver),
        "user": _json_safe(metadata or {}),
    }
    for k, v in arrays.items():
        if v.dtype == object:
            raise TypeError(f"design array {k!r} has dtype object; cannot be saved without pickle.")
    arrays["__metadata__"] = np.array(json.dumps(meta))
    return atomic_write_npz(path, arrays, overwrite=overwrite)


def read_design_metadata(path) -> dict:
    """The JSON metadata of a saved design (no arrays are rebuilt)."""
    with np.load(pathlib.Path(path), allow_pickle=False) as data:
        return _metadata(data, path)


def _metadata(data, path) -> dict:
    from .._errors import InputError

    if "__metadata__" not in data.files:
        raise InputError(f"{path} is not a fojax design file (no __metadata__ entry).")
    meta = json.loads(str(data["__metadata__"][()]))
    if meta.get("format") != FORMAT:
        raise InputError(f"{path} is not a fojax design file (format {meta.get('format')!r}).")
    if int(meta.get("format_version", 0)) > FORMAT_VERSION:
        raise InputError(
            f"{path} has design format version {meta['format_version']}, newer than this fojax "
            f"reads ({FORMAT_VERSION}); upgrade fojax."
        )
    return meta


def load_design(path):
    """Load a design written by `save_design`; arrays are bit-identical to the saved ones.

    **Arguments:**

    - `path`: a file written by `save_design`.

    **Returns:** a `fojax.design.FunctionalObserverDesign` (observer, structure, params,
    `T`, `K`, `Z_eff`, `X`, `report`, `solver`); the metadata (fojax version, creation
    time, user metadata) is in ``design.solver["saved"]``.
    """
    import jax.numpy as jnp

    from .._dtype import require_x64
    from ..design import FunctionalObserverDesign, FunctionalObserverStructure, region_from_dict
    from ..design._verify import VerificationReport
    from ..observer import GeneralizedFunctionalObserver

    require_x64("load_design")
    path = pathlib.Path(path)
    with np.load(path, allow_pickle=False) as data:
        meta = _metadata(data, path)
        arrays = {k: np.array(data[k]) for k in data.files if k != "__metadata__"}
    obs = GeneralizedFunctionalObserver(
        *(jnp.asarray(arrays[f"observer/{k}"]) for k in _OBSERVER_FIELDS), kind=meta["observer_kind"]
    )
    st = meta["structure"]
    structure = FunctionalObserverStructure(
        **{k: jnp.asarray(arrays[f"structure/{k}"]) for k in _STRUCTURE_FIELDS},
        solvability_residual=float(st["solvability_residual"]),
        q1=int(st["q1"]),
        psi=str(st["psi"]),
    )
    rep = meta["report"]
    report = VerificationReport(
        residuals=dict(rep["residuals"]),
        scale=rep["scale"],
        relative_residual=rep["relative_residual"],
        eigenvalues=arrays["report/eigenvalues"],
        region=rep["region"],
        region_margin=rep["region_margin"],
        lmi_max_eig=rep["lmi_max_eig"],
        certificate_min_eig=rep["certificate_min_eig"],
        passed=bool(rep["passed"]),
        failures=tuple(rep["failures"]),
        extra=dict(rep.get("extra", {})),
    )
    solver = dict(meta.get("solver") or {})
    solver["saved"] = {
        k: meta[k] for k in ("fojax_version", "created", "format_version", "user") if k in meta
    }
    return FunctionalObserverDesign(
        observer=obs,
        kind=meta["kind"],
        region=region_from_dict(meta["region"]),
        structure=structure,
        params={k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("params/")},
        T=arrays["T"],
        K=arrays["K"],
        Z_eff=arrays["Z_eff"],
        X=arrays["X"],
        report=report,
        solver=solver,
    )


# --------------------------------------------------------------------------- folders


def new_results_folder(
    root=".", *, prefix: str = "fojax", name: str | None = None, overwrite: bool = False
) -> pathlib.Path:
    """Create a new folder for the results of one run.

    **Arguments:**

    - `root`: parent directory (created if missing).
    - `prefix`: the folder is ``<root>/<prefix>-YYYYmmdd-HHMMSS`` (UTC), with ``-2``,
      ``-3``, … appended if that name exists already: an earlier run is never reused.
    - `name`: an explicit folder name instead of the timestamp. If it exists and is not
      empty, `FileExistsError` unless ``overwrite=True`` (then files in it may be
      replaced, nothing is deleted).

    **Returns:** the created folder.
    """
    root = pathlib.Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if name is not None:
        folder = root / name
        try:
            folder.mkdir()
        except FileExistsError:
            if not folder.is_dir():
                raise FileExistsError(f"{folder} exists and is not a folder.") from None
            if any(folder.iterdir()) and not overwrite:
                raise FileExistsError(
                    f"results folder {folder} already exists and is not empty; fojax never reuses "
                    "an earlier run's folder. Choose another name, or pass overwrite=True "
                    "(CLI: --overwrite) to write into it."
                ) from None
        return folder
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%d-%H%M%S")
    base = f"{prefix}-{stamp}"
    for i in range(1, 10_000):
        folder = root / (base if i == 1 else f"{base}-{i}")
        try:
            folder.mkdir()  # atomic: fails if it exists
            return folder
        except FileExistsError:
            continue
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
