r"""Readers of the design files fojax wrote before format 3 (`fojax.design._base`).

**Format 2** (fojax 2026-11, `design_class` in the metadata) and **format 1** (functional
designs only): one ``.npz`` with hand-written layouts per class — ``observer/N`` …
``observer/Wy``, ``structure/E`` … ``structure/PiZ``, ``params/…``, ``T``, ``K``,
``Z_eff``, ``X``, ``report/eigenvalues``; Takagi–Sugeno designs add ``observer/T`` and the
membership (class and fields in the metadata); unknown-input designs the observer of eq.
3.110 and ``D``; finite-time designs their two designs under ``designs/0/``,
``designs/1/``; fault estimators theirs under ``design/`` and ``augmented/…``. These
readers are kept so that old files still load (tests: ``tests/data/designs_v2``, files
written by that code); nothing writes this format any more.
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError


class _NotStorable(Exception):
    pass


_OBSERVER_FIELDS = ("N", "J", "F", "H", "S", "G", "M", "P", "Q", "Wu", "Wy")
_STRUCTURE_FIELDS = ("E", "A", "B", "C", "L", "R", "Eperp", "Z0", "PiZ")
_TS_OBSERVER_FIELDS = _OBSERVER_FIELDS + ("T",)
_UIO_OBSERVER_FIELDS = (
    "N", "J", "F", "H", "Delta", "S", "G", "M", "Phi", "Lambda", "W", "P", "Q", "Wu", "Wy",
)  # fmt: skip
_SYSTEM_FIELDS = ("E", "A", "B", "C")
#: The classes format 2 knew.
DESIGN_CLASSES = (
    "FunctionalObserverDesign",
    "TakagiSugenoObserverDesign",
    "UnknownInputObserverDesign",
    "FiniteTimeObserverDesign",
    "FaultEstimatorDesign",
)


def _need(arrays: dict, key: str, path):
    if key not in arrays:
        raise InputError(f"{path} has no array {key!r}, which a format-2 design needs; the file was changed "
                         "or truncated. Re-create it with design.save(path) or `fojax design`.")
    return arrays[key]


def _report_from(rep: dict, arrays: dict, p: str):
    from ._verify import VerificationReport

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

    from . import FunctionalObserverStructure, region_from_dict

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


def _rows(rows: list) -> np.ndarray:
    """A JSON list of rows as an ``(r, c)`` array, also when ``c = 0``."""
    return np.asarray(rows, dtype=float).reshape(len(rows), len(rows[0]) if rows else 0)


def _load_functional(m: dict, arrays: dict, p: str, saved: dict):
    from ..observer import GeneralizedFunctionalObserver
    from . import FunctionalObserverDesign

    obs = GeneralizedFunctionalObserver(*_observer_arrays(arrays, p, _OBSERVER_FIELDS), kind=m["observer_kind"])
    hinf = None
    if m.get("hinf"):
        from . import HinfCertificate

        h = m["hinf"]  # the format-1/2 JSON dict (floats; Bw, Dv as lists of rows)
        hinf = HinfCertificate(**{k: float(h[k]) for k in ("gamma", "norm", "peak_frequency", "tightness",
                                                            "region_only_norm", "brl_max_eig")},
                               Bw=_rows(h["Bw"]), Dv=_rows(h["Dv"]))
    return FunctionalObserverDesign(observer=obs, kind=m["kind"], hinf=hinf,
                                    **_structure_design_kwargs(m, arrays, p, saved))


def _module_from(m: dict, arrays: dict):
    import equinox as eqx
    import jax.numpy as jnp

    from .._serialize import _fojax_class, NotStorable

    try:
        cls = _fojax_class(m["class"], "membership")  # fojax classes only, as in format 3
    except NotStorable as err:
        raise _NotStorable(str(err)) from None
    if not issubclass(cls, eqx.Module):
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
    from ..observer import TakagiSugenoObserver
    from . import TakagiSugenoObserverDesign

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
    from ..observer import UnknownInputObserver
    from . import UnknownInputObserverDesign

    obs = UnknownInputObserver(*_observer_arrays(arrays, "", _UIO_OBSERVER_FIELDS))
    return UnknownInputObserverDesign(observer=obs, D=arrays["D"], **_structure_design_kwargs(m, arrays, "", saved))


def _load_finite_time(m: dict, arrays: dict, saved: dict):
    import jax.numpy as jnp

    from ..observer import FiniteTimeObserver
    from . import FiniteTimeObserverDesign

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

    from ..plant import DescriptorSystem
    from . import FaultEstimatorDesign

    aug = DescriptorSystem(*(jnp.asarray(arrays[f"augmented/{k}"]) for k in _SYSTEM_FIELDS))
    design = _load_functional(m["design"], arrays, "design/", saved)
    return FaultEstimatorDesign(design, aug, int(m["q"]), int(m["n_faults"]), bool(m["ramp"]))


def load_legacy(meta: dict, arrays: dict, saved: dict, path, *, membership=None):
    """The design of a format-1/2 file (`meta`: its metadata, `arrays`: its entries)."""
    name = meta.get("design_class", "FunctionalObserverDesign")  # format 1: functional only
    if membership is not None and name != "TakagiSugenoObserverDesign":
        raise InputError(f"membership= applies to Takagi–Sugeno designs only; {path} holds a {name}.")
    arrays = _Checked(arrays, path)
    try:
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
    except KeyError as err:
        raise InputError(f"{path}: the metadata of this format-{meta.get('format_version', 1)} design has no "
                         f"entry {err}; the file was changed or damaged. Re-create it with design.save(path) "
                         "or `fojax design`.") from None
    raise InputError(
        f"{path} holds a design of class {name!r}, which this fojax version cannot load "
        f"(known: {', '.join(DESIGN_CLASSES)}); upgrade fojax."
    )


class _Checked(dict):
    """The file's arrays; a missing one raises `InputError` naming it (not `KeyError`)."""

    def __init__(self, arrays: dict, path):
        super().__init__(arrays)
        self.path = path

    def __missing__(self, key):
        return _need({}, key, self.path)
