"""The ``[[observer]]`` tables of a config file: kind, region, order, objective and the
keys of the special kinds (unknown-input, finite-time)."""


from __future__ import annotations

import numpy as np

from .._errors import RegionError
from ._spec import (
    _DISK,
    _OBSERVER,
    _REGION,
    DESIGN_METHODS,
    FINITE_TIME_METHODS,
    KINDS,
    OBJECTIVES,
    ObserverSpec,
    SPECIAL_KINDS,
)
from ._validate import check_observer_names, join, typename, V


def parse_observers(v: V, data: dict, *, n: int, n_design: int, p: int, ts: dict | None, faults: bool,
                    dt: float | None = None) -> tuple:
    """The ``[[observer]]`` entries as `ObserverSpec` s (``n_design``: the states of the
    designed, possibly fault-augmented, system; ``ts``: the parsed ``[takagi_sugeno]``; ``dt``:
    the sampling period of a discrete-time model, whose regions are z-plane disks inside the unit
    disk, default ``DiscreteDisk(0, 0.5)`` as in `fojax.design_functional_observer`)."""
    observers = []
    raw_obs = data.get("observer", [])
    if isinstance(raw_obs, dict):
        raw_obs = [raw_obs]
    if not isinstance(raw_obs, list):
        raise v.err("observer", f"expected [[observer]] tables, got {typename(raw_obs)}.")
    for i, o in enumerate(raw_obs):
        key = f"observer[{i}]"
        o = v.table(key, o, _OBSERVER)
        kind = v.string(join(key, "kind"), o["kind"], KINDS) if "kind" in o else "generalized"
        from ..design import DiscreteDisk, Disk

        if dt is not None:
            _discrete_kind(v, key, o, kind, dt)
            region = _discrete_region(v, join(key, "region"), o["region"]) if "region" in o else DiscreteDisk(0.0, 0.5)
        else:
            region = _region(v, join(key, "region"), o["region"]) if "region" in o else Disk(-2.0, 1.0)
        R = q0 = q1 = None
        if "R" in o and "q0" in o:
            raise v.err(join(key, "q0"), "give either R or q0, not both (q0 is the number of rows of R).")
        if "R" in o:
            R = v.array(join(key, "R"), o["R"], 2, "a q0 x n matrix")
            if R.shape[1] != n_design:
                raise v.err(join(key, "R"), f"has shape {R.shape}, expected (q0, {n_design}) (columns = states of the designed{' fault-augmented' if n_design != n else ''} system).")
        if "q0" in o:
            q0 = v.number(join(key, "q0"), o["q0"], integer=True, positive=True)
        if "q1" in o:
            q1 = v.number(join(key, "q1"), o["q1"], integer=True, nonneg=True)
            if kind == "proportional" and q1 != 0:
                raise v.err(join(key, "q1"), f"is {q1}; a proportional observer has q1 = 0.")
        objective, Bw, Dv = _objective(v, key, o, n, n_design, p, ts is not None)
        oname = v.file_name(join(key, "name"), o["name"], f"observer_{i + 1}") if "name" in o else f"{kind}-{i + 1}"
        special = _special_observer(v, key, o, kind, n, ts is not None, faults, region)
        if objective != "region" and kind in ("unknown-input", "finite-time"):
            raise v.err(join(key, "objective"), f"is {objective!r}; objective = {objective!r} is for the generalized, PI "
                        f"and proportional kinds, not {kind!r}: remove the key.")
        balance = _balance(v, key, o, kind, ts is not None)
        observers.append(ObserverSpec(oname, kind, region, R, q0, q1, objective, Bw, Dv, balance=balance, **special))
    check_observer_names(v, [o.name for o in observers])
    return tuple(observers)


def _objective(v: V, key: str, o: dict, n: int, n_design: int, p: int, takagi_sugeno: bool):
    """``objective``, ``Bw``, ``Dv`` of one ``[[observer]]``. `Bw` may have `n` rows (the
    model's states; zero rows are added for fault states) or `n_design` rows."""
    objective = v.string(join(key, "objective"), o["objective"], OBJECTIVES) if "objective" in o else "region"
    if objective in ("region", "centre"):
        for ch in ("Bw", "Dv"):
            if ch in o:
                raise v.err(join(key, ch), 'is only used with objective = "hinf" or "h2"; add that line or remove '
                            'the key.')
        if objective == "centre" and takagi_sugeno:
            raise v.err(join(key, "objective"), 'is "centre", which is for linear models (not [takagi_sugeno]).')
        return objective, None, None
    if takagi_sugeno:
        raise v.err(join(key, "objective"), f'is "{objective}", which is for linear models (not [takagi_sugeno]).')
    if "Bw" not in o and "Dv" not in o:
        raise v.err(join(key, "objective"), f'is "{objective}" but neither Bw (n x mw disturbance) nor Dv '
                    "(p x mv measurement noise) is given: add at least one.")
    Bw = Dv = None
    if "Bw" in o:
        Bw = v.array(join(key, "Bw"), o["Bw"], 2, "an n x mw matrix")
        if Bw.shape[0] == n and n_design != n:
            Bw = np.vstack([Bw, np.zeros((n_design - n, Bw.shape[1]))])
        if Bw.shape[0] != n_design:
            raise v.err(join(key, "Bw"), f"has shape {Bw.shape}, expected ({n}, mw) (one row per state"
                        + (f", or {n_design} rows of the fault-augmented system)." if n_design != n else ")."))
    if "Dv" in o:
        Dv = v.array(join(key, "Dv"), o["Dv"], 2, "a p x mv matrix")
        if Dv.shape[0] != p:
            raise v.err(join(key, "Dv"), f"has shape {Dv.shape}, expected ({p}, mv) (one row per output, p = {p} from C).")
    return objective, Bw, Dv


def _balance(v: V, key: str, o: dict, kind: str, takagi_sugeno: bool) -> bool | None:
    """``balance`` of one ``[[observer]]`` (None when absent): a boolean, for the designs that
    have it (`fojax.design.design_functional_observer`, `fojax.design.design_unknown_input_observer`)."""
    if "balance" not in o:
        return None
    k = join(key, "balance")
    value = v.boolean(k, o["balance"])
    if takagi_sugeno:
        raise v.err(k, "is for linear models (design_functional_observer), not [takagi_sugeno]: remove the key.")
    if kind == "finite-time":
        raise v.err(k, f"is for the generalized, PI, proportional and unknown-input kinds, not {kind!r}: remove "
                    "the key.")
    return value


def _discrete_kind(v: V, key: str, o: dict, kind: str, dt: float) -> None:
    """The observers a discrete-time model (``[model] dt``) can have: generalized, PI and
    proportional, with ``objective = "region"`` or ``"centre"``."""
    if kind in SPECIAL_KINDS:
        raise v.err(join(key, "kind"), f"is '{kind}', which is designed for continuous-time models only; this "
                    f"model is discrete-time (model.dt = {dt:g}): use 'generalized', 'PI' or 'proportional'.")
    objective = o.get("objective")
    if objective in ("hinf", "h2"):
        raise v.err(join(key, "objective"), f"is '{objective}', a continuous-time norm; this model is "
                    f"discrete-time (model.dt = {dt:g}): use objective = 'region' or 'centre'.")


def _discrete_region(v: V, key: str, value):
    """``region`` of an observer of a discrete-time model: ``disk = { center, radius }`` is a
    `fojax.design.DiscreteDisk`, a disk of the z-plane inside the unit disk
    (``|center| + radius < 1``); ``decay`` and ``damping`` (s-plane regions) are refused."""
    from ..design import DiscreteDisk

    value = v.table(key, value, _REGION)
    for part in ("decay", "damping"):
        if part in value:
            raise v.err(join(key, part), "is an s-plane region (continuous time); a discrete-time model "
                        "(model.dt) takes region = { disk = { center = c, radius = r } } with |c| + r < 1.")
    if "disk" not in value:
        raise v.err(key, "is empty; give disk = { center = c, radius = r } with |c| + r < 1.")
    dkey = join(key, "disk")
    d = v.table(dkey, value["disk"], _DISK, required=("center", "radius"))
    c = v.number(join(dkey, "center"), d["center"])
    r = v.number(join(dkey, "radius"), d["radius"], positive=True)
    if abs(c) + r >= 1:
        raise v.err(dkey, f"disk(center={c}, radius={r}) is not inside the open unit disk (|center| + radius = "
                    f"{abs(c) + r:g}); the error e[k+1] = N e[k] of a discrete-time model decays only for "
                    "eigenvalues inside it. Expected |center| + radius < 1.")
    return DiscreteDisk(c, r)


def _region(v: V, key: str, value):
    from ..design import Disk, HalfPlane, Intersection, Sector

    value = v.table(key, value, _REGION)
    if not value:
        raise v.err(key, "is empty; give at least one of disk = {center, radius}, decay, damping.")
    parts = []
    if "disk" in value:
        dkey = join(key, "disk")
        d = v.table(dkey, value["disk"], _DISK, required=("center", "radius"))
        c = v.number(join(dkey, "center"), d["center"])
        r = v.number(join(dkey, "radius"), d["radius"], positive=True)
        if c + r >= 0:
            raise v.err(
                dkey,
                f"disk(center={c}, radius={r}) reaches into the closed right half-plane "
                f"(rightmost point {c + r}); expected center + radius < 0.",
            )
        parts.append(Disk(c, r))
    if "decay" in value:
        parts.append(HalfPlane(v.number(join(key, "decay"), value["decay"], nonneg=True)))
    if "damping" in value:
        zeta = v.number(join(key, "damping"), value["damping"])
        if not 0.0 < zeta < 1.0:
            raise v.err(join(key, "damping"), f"expected a damping ratio in (0, 1), got {zeta!r}.")
        parts.append(Sector(zeta))
    try:
        return parts[0] if len(parts) == 1 else Intersection(tuple(parts))
    except RegionError as e:  # pragma: no cover - every parameter is checked above
        raise v.err(key, str(e)) from None


def _special_observer(v: V, key: str, o: dict, kind: str, n: int, ts: bool, faults: bool, region) -> dict:
    """The keys of ``kind = "unknown-input"`` (``D``) and ``kind = "finite-time"``
    (``delay``, ``regions``, ``method``), refused for the other kinds; and the ``method``
    of the generalized / PI / proportional kinds (`_design_method`)."""
    own = {"unknown-input": ("D",), "finite-time": ("delay", "regions")}
    for k in ("D", "delay", "regions"):
        if k in o and k not in own.get(kind, ()):
            owner = next(kk for kk, keys in own.items() if k in keys)
            raise v.err(join(key, k), f"is a key of kind = '{owner}' observers; this observer has kind = '{kind}'.")
    if kind not in SPECIAL_KINDS:
        return _design_method(v, key, o, kind, ts, region)
    if kind == "unknown-input" and "method" in o:
        raise v.err(join(key, "method"), "is not a key of kind = 'unknown-input' observers (their design "
                    "has one route, the LMI); remove it.")
    if ts or faults:
        raise v.err(join(key, "kind"), f"'{kind}' observers are designed for LTI models without "
                    f"[{'takagi_sugeno' if ts else 'faults'}]; use 'generalized', 'PI' or 'proportional'.")
    if "region" in o and kind == "finite-time":
        raise v.err(join(key, "region"), "a finite-time observer has two regions: give regions = "
                    "[{ center = c1, radius = r1 }, { center = c2, radius = r2 }] instead.")
    if kind == "unknown-input":
        if "D" not in o:
            raise v.err(join(key, "D"), "missing: an unknown-input observer needs D, the (n, l) matrix "
                        "of unknown-input directions (E x' = A x + B u + D d).")
        D = v.array(join(key, "D"), o["D"], 2, "an n x l matrix")
        if D.shape[0] != n:
            raise v.err(join(key, "D"), f"has shape {D.shape}, expected ({n}, l) (one row per state, n = {n}).")
        return {"D": D}
    if "delay" not in o:
        raise v.err(join(key, "delay"), "missing: a finite-time observer needs its delay h > 0 "
                    "(the estimate is exact for t >= h).")
    h = float(v.number(join(key, "delay"), o["delay"], positive=True))
    from ..design import Disk

    regions = (Disk(-5.0, 0.5), Disk(-2.0, 0.5))
    if "regions" in o:
        rk = join(key, "regions")
        r = o["regions"]
        if not isinstance(r, list) or len(r) != 2:
            raise v.err(rk, f"expected two disks [{{ center = c1, radius = r1 }}, {{ center = c2, radius = r2 }}], got {r!r}.")
        disks = []
        for j, d in enumerate(r):
            dk = f"{rk}[{j}]"
            d = v.table(dk, d, _DISK, required=("center", "radius"))
            c = v.number(join(dk, "center"), d["center"])
            rad = v.number(join(dk, "radius"), d["radius"], positive=True)
            if c + rad >= 0:
                raise v.err(dk, f"disk(center={c}, radius={rad}) reaches into the closed right half-plane; "
                            "expected center + radius < 0.")
            disks.append(Disk(c, rad))
        (c1, r1), (c2, r2) = ((float(d.center), float(d.radius)) for d in disks)
        if not (c1 + r1 < c2 - r2 or c2 + r2 < c1 - r1):
            raise v.err(rk, f"the disks ({c1}, {r1}) and ({c2}, {r2}) overlap along the real axis; the two "
                        "observers' eigenvalues must be separated (Lemma 6).")
        regions = tuple(disks)
    method = v.string(join(key, "method"), o["method"], FINITE_TIME_METHODS) if "method" in o else "auto"
    return {"delay": h, "regions": regions, "method": method}


def _design_method(v: V, key: str, o: dict, kind: str, ts: bool, region) -> dict:
    """``method`` of a generalized / PI / proportional observer (`DESIGN_METHODS`), checked
    against what the Riccati route can do (`fojax.design._riccati.riccati_applies`): one
    LTI model (not a Takagi–Sugeno family, which needs a common certificate), kind
    generalized or proportional (PI fixes S = 0), one disk, half-plane or sector, and not
    ``objective = "centre"`` (a search over the region LMI)."""
    if "method" not in o:
        return {}
    mk = join(key, "method")
    method = v.string(mk, o["method"], DESIGN_METHODS)
    if method == "lmi":
        return {"method": method}
    if ts:
        raise v.err(mk, f"is {method!r}; Takagi-Sugeno observers need one certificate common to all rules, "
                    "which only the LMI route gives: use method = 'lmi' or remove the key.")
    if method == "riccati":
        if kind == "PI":
            raise v.err(mk, "is 'riccati'; the Riccati route gives generalized and proportional observers (a PI "
                        "observer's S = 0 constrains the gain): use method = 'lmi' or 'auto', or kind = 'generalized'.")
        if o.get("objective") == "centre":
            raise v.err(mk, "is 'riccati'; objective = 'centre' searches the region LMI: use method = 'lmi' or 'auto'.")
        from ..design import Disk, HalfPlane, Sector

        if not isinstance(region, Disk | HalfPlane | Sector):
            raise v.err(mk, f"is 'riccati', which needs one disk, half-plane or sector; region is "
                        f"{region.describe()}: use method = 'lmi' or 'auto', or give one region part.")
    return {"method": method}
