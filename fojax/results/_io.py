r"""Saved designs and results folders that last.

**Design files.** `save_design` writes one ``.npz`` file (NumPy's zip of ``.npy``
arrays, no pickles) holding every matrix of a design object of `fojax.design` in
float64 exactly as computed, plus one entry ``__metadata__`` with a JSON document:

- ``format`` = ``"fojax-design"``, ``format_version`` = 2, ``fojax_version``,
  ``created`` (UTC timestamp, ISO 8601), ``design_class`` (one of `DESIGN_CLASSES`);
- ``kind``, ``region`` (`AbstractRegion.to_dict`), the static fields of the
  structure (``q1``, ``psi``, ``solvability_residual``), the sizes ``n, m, p, q, q0``;
- ``report``: the `VerificationReport` (`to_dict`, eigenvalues kept in the arrays);
- ``solver``: the solver information (JSON-safe copy; non-JSON values as strings);
- ``user``: optional user metadata passed to `save_design`.

Array entries of a `FunctionalObserverDesign` are named ``observer/N`` …
``observer/Wy``, ``structure/E``, ``A``, ``B``, ``C``, ``L``, ``R``, ``Eperp``, ``Z0``,
``PiZ`` (plant matrices, functional and the parameterization), ``params/Z`` …
``params/G``, ``T``, ``K``, ``Z_eff``, ``X`` (LMI certificate) and
``report/eigenvalues``. The other classes add to or nest this layout:

- `TakagiSugenoObserverDesign`: rule-stacked observer matrices, ``observer/T``, and the
  membership functions (``membership`` in the metadata: class and fields; arrays under
  ``observer/membership/…``). `load_design` rebuilds fojax's own membership classes;
  for other classes pass ``membership=``.
- `UnknownInputObserverDesign`: the observer matrices of eq. 3.110 (``observer/Delta``,
  ``observer/Phi``, ``observer/Lambda``, ``observer/W`` …) and ``D``.
- `FiniteTimeObserverDesign`: the two designs under ``designs/0/`` and ``designs/1/``
  (metadata ``designs``), ``observer/h``, ``observer/Gamma_now``,
  ``observer/Gamma_delay``, and ``h``, ``reconstruction_rcond``,
  ``reconstruction_residual`` as 0-d arrays.
- `FaultEstimatorDesign`: the design of the augmented system under ``design/``
  (metadata ``design``), ``augmented/E`` … ``augmented/C``, and ``q``, ``n_faults``,
  ``ramp`` in the metadata.

`load_design` rebuilds an object of the saved class with bit-identical arrays
(``np.array_equal`` on every entry), so the loaded observer produces identical
outputs. Files of format 1 (functional designs only, no ``design_class``) still load.

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
A path built from a results folder must resolve inside it (`fojax.UnsafePathError`
otherwise, nothing written), and every file written in it is recorded in its manifest
``fojax-manifest.json`` (relative path, SHA-256, size). ``overwrite=True`` first removes
the files the previous run recorded there (a file changed since it was written is
kept, and so is every file fojax did not write), so the folder then holds the new
run's files only, beside the user's own.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import io
import json
import pathlib
import zipfile
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
    results folder of `new_results_folder` must resolve inside it (`fojax.UnsafePathError`
    otherwise), and the file is recorded in the folder's manifest (module docstring).
    """
    return _atomic_write(path, bytes(data), overwrite=overwrite)


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

#: The design classes `save_design` writes (``design_class`` in the metadata).
DESIGN_CLASSES = (
    "FunctionalObserverDesign",
    "TakagiSugenoObserverDesign",
    "UnknownInputObserverDesign",
    "FiniteTimeObserverDesign",
    "FaultEstimatorDesign",
)
_TS_OBSERVER_FIELDS = _OBSERVER_FIELDS + ("T",)
_UIO_OBSERVER_FIELDS = (
    "N", "J", "F", "H", "Delta", "S", "G", "M", "Phi", "Lambda", "W", "P", "Q", "Wu", "Wy",
)  # fmt: skip
_SYSTEM_FIELDS = ("E", "A", "B", "C")


def _design_class_map() -> dict:
    from ..design import (
        FaultEstimatorDesign,
        FiniteTimeObserverDesign,
        FunctionalObserverDesign,
        TakagiSugenoObserverDesign,
        UnknownInputObserverDesign,
    )

    classes = (
        FunctionalObserverDesign,
        TakagiSugenoObserverDesign,
        UnknownInputObserverDesign,
        FiniteTimeObserverDesign,
        FaultEstimatorDesign,
    )
    return {c.__name__: c for c in classes}


def _report_meta(report, p: str, arrays: dict) -> dict:
    arrays[f"{p}report/eigenvalues"] = np.asarray(report.eigenvalues)
    rep = report.to_dict()
    rep.pop("eigenvalues_real", None)
    rep.pop("eigenvalues_imag", None)
    rep["extra"] = _json_safe(dict(report.extra))
    return rep


def _structure_design_meta(d, p: str, arrays: dict, observer_fields: tuple) -> dict:
    """Arrays and metadata of a design object holding a `FunctionalObserverStructure`
    (functional, Takagi–Sugeno and unknown-input designs), under the key prefix `p`."""
    obs, s = d.observer, d.structure
    for k in observer_fields:
        arrays[f"{p}observer/{k}"] = np.asarray(getattr(obs, k))
    for k in _STRUCTURE_FIELDS:
        arrays[f"{p}structure/{k}"] = np.asarray(getattr(s, k))
    for k, v in d.params.items():
        arrays[f"{p}params/{k}"] = np.asarray(v)
    for k in _TOP_FIELDS:
        arrays[p + k] = np.asarray(getattr(d, k))
    return {
        "region": d.region.to_dict(),
        "region_description": d.region.describe(),
        "structure": {
            "q1": int(s.q1),
            "psi": s.psi,
            "solvability_residual": float(s.solvability_residual),
        },
        "sizes": {"n": int(s.n), "m": int(s.m), "p": int(s.p), "q": int(s.q), "q0": int(s.q0)},
        "params": sorted(d.params),
        "report": _report_meta(d.report, p, arrays),
        "solver": _json_safe(d.solver),
    }


def _functional_meta(d, p: str, arrays: dict) -> dict:
    return {
        "kind": d.kind,
        "observer_kind": d.observer.kind,
        **_structure_design_meta(d, p, arrays, _OBSERVER_FIELDS),
        **({"hinf": d.hinf.to_dict()} if getattr(d, "hinf", None) is not None else {}),
        **({"h2": d.h2.to_dict()} if getattr(d, "h2", None) is not None else {}),
    }


class _NotStorable(Exception):
    pass


def _module_meta(obj, p: str, arrays: dict) -> dict:
    """A membership (any `equinox.Module` tree of arrays, numbers and strings): class
    name + fields in the metadata, arrays under ``p/<field>``. Raises `_NotStorable`."""
    import equinox as eqx
    import jax

    cls = type(obj)
    fields = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        key = f"{p}/{f.name}"
        if isinstance(v, eqx.Module):
            fields[f.name] = {"module": _module_meta(v, key, arrays)}
        elif v is None or isinstance(v, bool | int | str):
            fields[f.name] = {"value": v}
        elif isinstance(v, float):
            fields[f.name] = {"float": repr(v)}  # repr round-trips exactly (inf, nan too)
        elif isinstance(v, np.ndarray | np.generic | jax.Array):
            arr = np.asarray(v)
            if arr.dtype == object:
                raise _NotStorable(f"{cls.__qualname__}.{f.name} has dtype object")
            arrays[key] = arr
            fields[f.name] = {"array": key}
        else:
            raise _NotStorable(f"{cls.__qualname__}.{f.name} is a {type(v).__name__}")
    return {"class": f"{cls.__module__}:{cls.__qualname__}", "fields": fields}


def _membership_meta(membership, arrays: dict) -> dict:
    staged: dict = {}
    try:
        meta = _module_meta(membership, "observer/membership", staged)
    except _NotStorable as err:
        cls = type(membership)
        return {"class": f"{cls.__module__}:{cls.__qualname__}", "stored": False, "reason": str(err)}
    arrays.update(staged)
    return {**meta, "stored": True}


def _ts_meta(d, arrays: dict) -> dict:
    return {
        "kind": d.kind,
        "observer_kind": d.observer.kind,
        "num_rules": int(d.observer.num_rules),
        "membership": _membership_meta(d.observer.membership, arrays),
        **_structure_design_meta(d, "", arrays, _TS_OBSERVER_FIELDS),
    }


def _uio_meta(d, arrays: dict) -> dict:
    arrays["D"] = np.asarray(d.D)
    meta = _structure_design_meta(d, "", arrays, _UIO_OBSERVER_FIELDS)
    meta["sizes"]["l"] = int(np.shape(d.D)[1])
    return meta


def _finite_time_meta(d, arrays: dict) -> dict:
    o = d.observer
    arrays["observer/h"] = np.asarray(o.h)
    arrays["observer/Gamma_now"] = np.asarray(o.Gamma_now)
    arrays["observer/Gamma_delay"] = np.asarray(o.Gamma_delay)
    scalars = ("h", "reconstruction_rcond", "reconstruction_residual")
    for k in scalars:
        arrays[k] = np.asarray(getattr(d, k), dtype=np.float64)
    return {
        "kind": d.designs[0].kind,
        "designs": [_functional_meta(di, f"designs/{i}/", arrays) for i, di in enumerate(d.designs)],
        **{k: float(getattr(d, k)) for k in scalars},
    }


def _fault_meta(d, arrays: dict) -> dict:
    for k in _SYSTEM_FIELDS:
        arrays[f"augmented/{k}"] = np.asarray(getattr(d.augmented, k))
    return {
        "kind": d.design.kind,
        "design": _functional_meta(d.design, "design/", arrays),
        "q": int(d.q),
        "n_faults": int(d.n_faults),
        "ramp": bool(d.ramp),
    }


_SAVERS = {
    "FunctionalObserverDesign": lambda d, arrays: _functional_meta(d, "", arrays),
    "TakagiSugenoObserverDesign": _ts_meta,
    "UnknownInputObserverDesign": _uio_meta,
    "FiniteTimeObserverDesign": _finite_time_meta,
    "FaultEstimatorDesign": _fault_meta,
}


def save_design(design, path, *, overwrite: bool = False, metadata: dict | None = None) -> pathlib.Path:
    """Save a verified design to one ``.npz`` file (format in the module docstring).

    **Arguments:**

    - `design`: a design object of `fojax.design`: `FunctionalObserverDesign`,
      `TakagiSugenoObserverDesign`, `UnknownInputObserverDesign`,
      `FiniteTimeObserverDesign` or `FaultEstimatorDesign`.
    - `path`: destination file (conventionally ``*.npz``); its directory must exist.
    - `overwrite`: replace an existing file (default: raise `FileExistsError`).
    - `metadata`: optional JSON-serialisable user metadata (e.g. the config file).

    **Returns:** the path written.
    """
    classes = _design_class_map()
    name = next((n for n, c in classes.items() if type(design) is c), None)
    if name is None:
        raise TypeError(
            f"save_design expects a design object of fojax.design ({', '.join(DESIGN_CLASSES)}), "
            f"got {type(design).__name__}."
        )
    arrays: dict[str, np.ndarray] = {}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "fojax_version": fojax_version(),
        "created": _timestamp(),
        "design_class": name,
        **_SAVERS[name](design, arrays),
        "user": _json_safe(metadata or {}),
    }
    for k, v in arrays.items():
        if v.dtype == object:
            raise TypeError(f"design array {k!r} has dtype object; cannot be saved without pickle.")
    arrays["__metadata__"] = np.array(json.dumps(meta))
    return atomic_write_npz(path, arrays, overwrite=overwrite)


def read_design_metadata(path) -> dict:
    """The JSON metadata of a saved design (no arrays are rebuilt)."""
    with _open_design_file(path) as data:
        return _metadata(data, path)


_EXPECTED = (
    "load_design reads the .npz files written by fojax.results.save_design or `fojax design` "
    "(<observer>.npz in its results folder)"
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


def _open_design_file(path):
    """`np.load` of a design file (no pickles), with a clear `InputError` for anything
    that is not a ``.npz`` archive."""
    from .._errors import InputError

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


def _metadata(data, path) -> dict:
    from .._errors import InputError

    if "__metadata__" not in data.files:
        raise InputError(f"{path} is not a fojax design file (no __metadata__ entry); {_EXPECTED}.")
    meta = json.loads(str(data["__metadata__"][()]))
    if meta.get("format") != FORMAT:
        raise InputError(f"{path} is not a fojax design file (format {meta.get('format')!r}).")
    if int(meta.get("format_version", 0)) > FORMAT_VERSION:
        raise InputError(
            f"{path} has design format version {meta['format_version']}, newer than this fojax "
            f"reads ({FORMAT_VERSION}); upgrade fojax."
        )
    return meta


def _report_from(rep: dict, arrays: dict, p: str):
    from ..design._verify import VerificationReport

    return VerificationReport(
        residuals=dict(rep["residuals"]),
        scale=rep["scale"],
        relative_residual=rep["relative_residual"],
        eigenvalues=arrays[f"{p}report/eigenvalues"],
        region=rep["region"],
        region_margin=rep["region_margin"],
        lmi_max_eig=rep["lmi_max_eig"],
        certificate_min_eig=rep["certificate_min_eig"],
        passed=bool(rep["passed"]),
        failures=tuple(rep["failures"]),
        extra=dict(rep.get("extra", {})),
    )


def _structure_design_kwargs(m: dict, arrays: dict, p: str, saved: dict) -> dict:
    """Constructor arguments shared by the structure-based design classes."""
    import jax.numpy as jnp

    from ..design import FunctionalObserverStructure, region_from_dict

    st = m["structure"]
    structure = FunctionalObserverStructure(
        **{k: jnp.asarray(arrays[f"{p}structure/{k}"]) for k in _STRUCTURE_FIELDS},
        solvability_residual=float(st["solvability_residual"]),
        q1=int(st["q1"]),
        psi=str(st["psi"]),
    )
    solver = dict(m.get("solver") or {})
    solver["saved"] = saved
    prefix = f"{p}params/"
    return dict(
        region=region_from_dict(m["region"]),
        structure=structure,
        params={k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)},
        T=arrays[p + "T"],
        K=arrays[p + "K"],
        Z_eff=arrays[p + "Z_eff"],
        X=arrays[p + "X"],
        report=_report_from(m["report"], arrays, p),
        solver=solver,
    )


def _observer_arrays(arrays: dict, p: str, fields: tuple) -> list:
    import jax.numpy as jnp

    return [jnp.asarray(arrays[f"{p}observer/{k}"]) for k in fields]


def _load_functional(m: dict, arrays: dict, p: str, saved: dict):
    from ..design import FunctionalObserverDesign
    from ..observer import GeneralizedFunctionalObserver

    obs = GeneralizedFunctionalObserver(*_observer_arrays(arrays, p, _OBSERVER_FIELDS), kind=m["observer_kind"])
    hinf = None
    if m.get("hinf"):
        from ..design import HinfCertificate

        hinf = HinfCertificate.from_dict(m["hinf"])
    h2 = None
    if m.get("h2"):
        from ..design import H2Certificate

        h2 = H2Certificate.from_dict(m["h2"])
    return FunctionalObserverDesign(observer=obs, kind=m["kind"], hinf=hinf, h2=h2,
                                    **_structure_design_kwargs(m, arrays, p, saved))


def _module_from(m: dict, arrays: dict):
    import importlib

    import equinox as eqx
    import jax.numpy as jnp

    module, _, qualname = m["class"].partition(":")
    if module != "fojax" and not module.startswith("fojax."):
        raise _NotStorable(f"{m['class']} is not a fojax class (fojax never imports code named in a file)")
    try:
        cls = importlib.import_module(module)
        for part in qualname.split("."):
            cls = getattr(cls, part)
    except (ImportError, AttributeError):
        raise _NotStorable(f"{m['class']} does not exist in this fojax version") from None
    if not (isinstance(cls, type) and issubclass(cls, eqx.Module)):
        raise _NotStorable(f"{m['class']} is not an equinox.Module")
    kwargs = {}
    for name, f in m["fields"].items():
        if "module" in f:
            kwargs[name] = _module_from(f["module"], arrays)
        elif "array" in f:
            kwargs[name] = jnp.asarray(arrays[f["array"]])
        elif "float" in f:
            kwargs[name] = float(f["float"])
        else:
            kwargs[name] = f["value"]
    return cls(**kwargs)


def _load_ts(m: dict, arrays: dict, saved: dict, membership=None, path=None):
    from .._errors import InputError
    from ..design import TakagiSugenoObserverDesign
    from ..observer import TakagiSugenoObserver

    mm = m["membership"]
    if membership is None:
        try:
            if not mm.get("stored", True):
                raise _NotStorable(f"it was not stored ({mm.get('reason', 'not a tree of arrays')})")
            membership = _module_from(mm, arrays)
        except _NotStorable as err:
            raise InputError(
                f"{path}: the membership functions of this Takagi–Sugeno design ({mm['class']}) "
                f"cannot be rebuilt: {err}. Pass the plant's membership: "
                "load_design(path, membership=plant.membership)."
            ) from None
    *mats, T = _observer_arrays(arrays, "", _TS_OBSERVER_FIELDS)
    obs = TakagiSugenoObserver(*mats, T, membership, kind=m["observer_kind"])
    return TakagiSugenoObserverDesign(observer=obs, kind=m["kind"], **_structure_design_kwargs(m, arrays, "", saved))


def _load_uio(m: dict, arrays: dict, saved: dict):
    from ..design import UnknownInputObserverDesign
    from ..observer import UnknownInputObserver

    obs = UnknownInputObserver(*_observer_arrays(arrays, "", _UIO_OBSERVER_FIELDS))
    return UnknownInputObserverDesign(observer=obs, D=arrays["D"], **_structure_design_kwargs(m, arrays, "", saved))


def _load_finite_time(m: dict, arrays: dict, saved: dict):
    import jax.numpy as jnp

    from ..design import FiniteTimeObserverDesign
    from ..observer import FiniteTimeObserver

    designs = tuple(_load_functional(mi, arrays, f"designs/{i}/", saved) for i, mi in enumerate(m["designs"]))
    obs = FiniteTimeObserver(
        designs[0].observer,
        designs[1].observer,
        *(jnp.asarray(arrays[f"observer/{k}"]) for k in ("h", "Gamma_now", "Gamma_delay")),
    )
    return FiniteTimeObserverDesign(
        obs, designs, *(float(arrays[k]) for k in ("h", "reconstruction_rcond", "reconstruction_residual"))
    )


def _load_fault(m: dict, arrays: dict, saved: dict):
    import jax.numpy as jnp

    from ..design import FaultEstimatorDesign
    from ..plant import DescriptorSystem

    aug = DescriptorSystem(*(jnp.asarray(arrays[f"augmented/{k}"]) for k in _SYSTEM_FIELDS))
    design = _load_functional(m["design"], arrays, "design/", saved)
    return FaultEstimatorDesign(design, aug, int(m["q"]), int(m["n_faults"]), bool(m["ramp"]))


def load_design(path, *, membership=None):
    """Load a design written by `save_design`; arrays are bit-identical to the saved ones.

    **Arguments:**

    - `path`: a file written by `save_design`.
    - `membership`: only for Takagi–Sugeno designs whose membership functions are not
      fojax classes (fojax rebuilds `fojax.SectorMembership` and the other fojax
      memberships from the file, but never imports code named in a file): the
      plant's `fojax.AbstractMembership`.

    **Returns:** an object of the saved class (`FunctionalObserverDesign`,
    `TakagiSugenoObserverDesign`, `UnknownInputObserverDesign`,
    `FiniteTimeObserverDesign` or `FaultEstimatorDesign`) whose arrays equal the saved
    ones bit for bit, so its observer produces identical outputs. The metadata (fojax
    version, creation time, user metadata) is in ``design.solver["saved"]`` (for
    finite-time and fault-estimator designs: in the `solver` of each inner
    `FunctionalObserverDesign`).

    **Raises:** `fojax.InputError` for a file that is not a fojax design (a config file,
    any other file or archive), has a newer format, or holds a design class this version
    does not know.
    """
    from .._dtype import require_x64
    from .._errors import InputError

    require_x64("load_design")
    path = pathlib.Path(path)
    with _open_design_file(path) as data:
        meta = _metadata(data, path)
        arrays = {k: np.array(data[k]) for k in data.files if k != "__metadata__"}
    name = meta.get("design_class", "FunctionalObserverDesign")  # format 1: functional only
    saved = {k: meta[k] for k in ("fojax_version", "created", "format_version", "user") if k in meta}
    if membership is not None and name != "TakagiSugenoObserverDesign":
        raise InputError(f"membership= applies to Takagi–Sugeno designs only; {path} holds a {name}.")
    if name == "FunctionalObserverDesign":
        return _load_functional(meta, arrays, "", saved)
    if name == "TakagiSugenoObserverDesign":
        return _load_ts(meta, arrays, saved, membership=membership, path=path)
    if name == "UnknownInputObserverDesign":
        return _load_uio(meta, arrays, saved)
    if name == "FiniteTimeObserverDesign":
        return _load_finite_time(meta, arrays, saved)
    if name == "FaultEstimatorDesign":
        return _load_fault(meta, arrays, saved)
    raise InputError(
        f"{path} holds a design of class {name!r}, which this fojax version cannot load "
        f"(known: {', '.join(DESIGN_CLASSES)}); upgrade fojax."
    )


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
    `fojax.InputError` otherwise), so the folder is always inside `root`.

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
