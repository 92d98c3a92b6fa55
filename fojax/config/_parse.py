"""`parse_config`: a parsed TOML document to a validated `Config` (format: `fojax.config._load`)."""


from __future__ import annotations

import pathlib

import numpy as np

from .._io import suggest_name
from ._observers import parse_observers
from ._spec import (
    _FAULTS,
    _INITIAL_STATE,
    _MAT_MATRICES,
    _MODEL,
    _MODEL_REQUIRED,
    _PROFILE,
    _STUDY,
    _TOP,
    _TS,
    _TUNING,
    _UNCERTAINTY,
    Config,
    NONLINEAR_PLANTS,
    PREMISES,
    PROFILE_KINDS,
    STEPPERS,
    StudySpec,
    TuningSpec,
)
from ._validate import check_model_header, join, missing, state_count, typename, V


def parse_config(data: dict, file: str = "<config>") -> Config:
    """Validate an already parsed TOML document (see the module docstring for the format).

    **Arguments:**

    - `data`: the dict `tomllib` returns.
    - `file`: the name used in error messages.

    **Returns:** a `Config`. **Raises:** `fojax.errors.ConfigError`.
    """
    v = V(file)
    check_model_header(v, data)
    v.table("", data, _TOP, required=("model",))
    # the model name names the results folders (design-<name>-<time>, study-<name>-<time>);
    # without one, the file name, made portable
    name = (v.file_name("name", data["name"], "my_model") if "name" in data
            else suggest_name(pathlib.Path(file).stem, "model"))
    description = v.string("description", data["description"]) if "description" in data else ""
    ts_raw = data.get("takagi_sugeno")
    model = v.table("model", data["model"], _MODEL)
    if "mat" in model:
        model = _with_mat(v, model, file)
    for k in _MODEL_REQUIRED:
        if k not in model:
            raise v.err(join("model", k), f"missing required key '{k}' in [model]"
                        + (f" (and no variable {k} in {model['mat']!r})." if "mat" in data["model"] else "."))

    E = v.array("model.E", model["E"], 2, "a square matrix")
    if ts_raw is None:
        A = v.array("model.A", model["A"], 2, "an n x n matrix")
        B = v.array("model.B", model["B"], 2, "an n x m matrix")
    else:
        A = v.array("model.A", model["A"], 3, "a list of n x n rule matrices (Takagi-Sugeno)")
        B = v.array("model.B", model["B"], (2, 3), "an n x m matrix or one per rule")
    C = v.array("model.C", model["C"], 2, "a p x n matrix")
    L = v.array("model.L", model["L"], 2, "a q x n matrix")
    # n: the number of states most of E, A, B, C, L agree on, so that the error names
    # the matrix that is wrong (not A when E has the wrong size)
    n, src = state_count(E=E, A=A, B=B, C=C, L=L)
    v.shape("model.E", E, (n, n), f"E must be square, n x n with n = {n} from {src('E')}")
    if ts_raw is None:
        v.shape("model.A", A, (n, n), f"n = {n} from {src('A')}")
    else:
        if A.shape[1:] != (n, n):
            raise v.err("model.A", f"has shape {A.shape}, expected (k, {n}, {n}) (one n x n matrix per rule, n = {n} from {src('A')}).")
        if B.ndim == 3 and B.shape[0] != A.shape[0]:
            raise v.err("model.B", f"has {B.shape[0]} rule matrices but model.A has {A.shape[0]}.")
    if B.shape[-2] != n:
        raise v.err("model.B", f"has shape {B.shape}, expected ({n}, m) (one row per state, n = {n} from {src('B')}).")
    m = B.shape[-1]
    if C.shape[1] != n:
        raise v.err("model.C", f"has shape {C.shape}, expected (p, {n}) (one column per state, n = {n} from {src('C')}).")
    p = C.shape[0]
    D = None
    if "D" in model:
        if ts_raw is not None:
            raise v.err("model.D", "a Takagi-Sugeno model has no feedthrough (y = C x); remove the key.")
        D = v.array("model.D", model["D"], 2, "a p x m matrix")
        v.shape("model.D", D, (p, m), f"y = C x + D u with p = {p} from C, m = {m} from B")
    dt = _sampling_period(v, model, ts_raw, data)
    if L.shape[1] != n:
        raise v.err("model.L", f"has shape {L.shape}, expected (q, {n}) (one column per state, n = {n} from {src('L')}).")
    feedback = None
    if "feedback" in model:
        feedback = v.array("model.feedback", model["feedback"], 2, "an m x n matrix")
        v.shape("model.feedback", feedback, (m, n), f"u = K x with m = {m} from B, n = {n} from E")
    x0 = None
    if "x0" in model:
        x0 = v.array("model.x0", model["x0"], 1, "a vector")
        v.shape("model.x0", x0, (n,), f"one entry per state, n = {n}")

    Fa = Fs = None
    ramp, estimate_faults = False, True
    if "faults" in data:
        f = v.table("faults", data["faults"], _FAULTS)
        if "Fa" not in f and "Fs" not in f:
            raise v.err("faults.Fa", "missing: [faults] needs Fa (n x nf), Fs (p x nf) or both.")
        if "Fa" in f:
            Fa = v.array("faults.Fa", f["Fa"], 2, "an n x nf matrix")
            if Fa.shape[0] != n:
                raise v.err("faults.Fa", f"has shape {Fa.shape}, expected ({n}, nf) (one row per state).")
        if "Fs" in f:
            Fs = v.array("faults.Fs", f["Fs"], 2, "a p x nf matrix")
            if Fs.shape[0] != p:
                raise v.err("faults.Fs", f"has shape {Fs.shape}, expected ({p}, nf) (one row per output, p = {p} from C).")
        if Fa is not None and Fs is not None and Fa.shape[1] != Fs.shape[1]:
            raise v.err("faults.Fs", f"has {Fs.shape[1]} columns but faults.Fa has {Fa.shape[1]}; both act on the same fault vector f.")
        ramp = v.boolean("faults.ramp", f["ramp"]) if "ramp" in f else False
        if "estimate_faults" in f:
            estimate_faults = v.boolean("faults.estimate_faults", f["estimate_faults"])
        if ts_raw is not None:  # T-S: faults of the simulated plant only (no augmented design)
            _ts_faults(v, f, ramp, estimate_faults)

    dA = profile = None
    parameter_spread = None
    if "uncertainty" in data:
        if ts_raw is not None:  # T-S: relative spreads of the nonlinear plant's parameters
            parameter_spread = _parameter_spread(v, data["uncertainty"], ts_raw)
        u = v.table("uncertainty", data["uncertainty"], _UNCERTAINTY,
                    required=("dA",) if ts_raw is None else ())
        if "parameters" in u and ts_raw is None:
            raise v.err("uncertainty.parameters", "is for Takagi-Sugeno models with [takagi_sugeno] plant "
                        "(relative spreads of the nonlinear plant's physical parameters); an LTI model's "
                        "uncertainty is given by dA and profile.")
    if "uncertainty" in data and "dA" in data["uncertainty"]:
        dA = v.array("uncertainty.dA", u["dA"], (2, 3), "a list of n x n matrices")
        if dA.ndim == 2:
            dA = dA[None]
        if dA.shape[1:] != (n, n):
            raise v.err("uncertainty.dA", f"has shape {dA.shape}, expected (k, {n}, {n}) (n x n directions, n = {n} from E).")
        k = dA.shape[0]
        if "profile" in u:
            pk = "uncertainty.profile"
            pr = u["profile"]
            if not isinstance(pr, dict):
                raise v.err(pk, f"expected a table {{ kind = ... }}, got {typename(pr)}.")
            kind = v.string(join(pk, "kind"), pr.get("kind", None) if "kind" in pr else missing(v, join(pk, "kind")), PROFILE_KINDS)
            v.table(pk, pr, _PROFILE[kind], required=[r for r in {"constant": ("value",), "uniform": ("bound",), "sine": ("amplitude", "omega")}[kind]])
            profile = {"kind": kind}
            for key in sorted(set(pr) - {"kind"}):
                val = pr[key]
                if isinstance(val, list):
                    arr = v.array(join(pk, key), val, 1, f"a list of {k} numbers")
                    v.shape(join(pk, key), arr, (k,), f"one per uncertainty direction, k = {k}")
                    profile[key] = arr.tolist()
                else:
                    profile[key] = v.number(join(pk, key), val, nonneg=key in ("bound", "omega"))

    ts = None
    if ts_raw is not None:
        t = v.table("takagi_sugeno", ts_raw, _TS, required=("premise", "index", "lower", "upper"))
        premise = v.string("takagi_sugeno.premise", t["premise"], PREMISES)
        index = v.number("takagi_sugeno.index", t["index"], integer=True, nonneg=True)
        if index >= p:
            raise v.err("takagi_sugeno.index", f"is {index}; expected an output index in 0..{p - 1} (p = {p} from C).")
        lo = v.number("takagi_sugeno.lower", t["lower"])
        hi = v.number("takagi_sugeno.upper", t["upper"])
        if not lo < hi:
            raise v.err("takagi_sugeno.upper", f"is {hi}; expected upper > lower = {lo}.")
        if A.shape[0] != 2:
            raise v.err("model.A", f"has {A.shape[0]} rule matrices; the sector membership of [takagi_sugeno] has 2 rules.")
        ts = {"premise": premise, "index": int(index), "lower": float(lo), "upper": float(hi)}
        if "plant" in t:
            ts["plant"] = v.string("takagi_sugeno.plant", t["plant"], NONLINEAR_PLANTS)
            _check_nonlinear_plant(v, ts, E, A, B, C)
    x0_spread = None
    if "initial_state" in data:
        x0_spread = _initial_state(v, data["initial_state"], n, ts_raw is not None)

    n_design = n
    if (Fa is not None or Fs is not None) and ts_raw is None:
        nf = (Fa if Fa is not None else Fs).shape[1]
        n_design = n + (2 * nf if ramp else nf)
    observers = parse_observers(v, data, n=n, n_design=n_design, p=p, ts=ts,
                                faults=Fa is not None or Fs is not None, dt=dt)

    study = None
    if "study" in data:
        study = StudySpec(**_read_table(v, "study", data["study"], _STUDY, _STUDY_READERS))
        if study.dt >= study.horizon:
            raise v.err("study.dt", f"is {study.dt}; expected a time step smaller than study.horizon = {study.horizon}.")
    tuning = None
    if "tuning" in data:
        tuning = TuningSpec(**_read_table(v, "tuning", data["tuning"], _TUNING, _TUNING_READERS))

    return Config(
        path=file, name=name, description=description, E=E, A=A, B=B, C=C, L=L,
        feedback=feedback, x0=x0, Fa=Fa, Fs=Fs, ramp=ramp, estimate_faults=estimate_faults,
        dA=dA, profile=profile, takagi_sugeno=ts, observers=observers, study=study,
        tuning=tuning, raw=data, parameter_spread=parameter_spread, x0_spread=x0_spread, D=D, dt=dt,
    )

def _read_table(v: V, name: str, value, allowed: set, readers: dict) -> dict:
    """The table ``[name]`` (keys in `allowed`) as keyword arguments: every given key checked
    and converted by its reader ``(v, dotted key, value) -> value``, in the order of `readers`."""
    table = v.table(name, value, allowed)
    return {k: read(v, f"{name}.{k}", table[k]) for k, read in readers.items() if k in table}


def _count(v: V, key: str, value) -> int:
    return v.number(key, value, integer=True, positive=True)


def _positive(v: V, key: str, value) -> float:
    return float(v.number(key, value, positive=True))


def _seed(v: V, key: str, value) -> int:
    return v.number(key, value, integer=True, nonneg=True)


def _robustness(v: V, key: str, value) -> tuple:
    r = v.table(key, value, {"h2", "hinf"})
    return tuple((k, float(v.number(f"{key}.{k}", r[k], nonneg=True))) for k in sorted(r))


_STUDY_READERS = {
    "samples": _count,
    "horizon": _positive,
    "dt": _positive,
    "seed": _seed,
    "stepper": lambda v, key, value: v.string(key, value, STEPPERS),
}
_TUNING_READERS = {
    "steps": _count,
    "learning_rate": _positive,
    "loss": lambda v, key, value: v.string(key, value, ("ise", "iae")),
    "robustness": _robustness,
}


def _sampling_period(v: V, model: dict, ts_raw, data: dict) -> float | None:
    """``[model] dt``: the sampling period ``h > 0`` of a discrete-time model
    ``E x[k+1] = A x[k] + B u[k]`` (`fojax.DescriptorSystem`'s ``dt``), or None. Refused with
    the parts of a file that describe continuous-time models only: ``[takagi_sugeno]`` and
    ``[uncertainty]`` (their plants and designs have no sampling period)."""
    if "dt" not in model:
        return None
    dt = float(v.number("model.dt", model["dt"], positive=True))
    for table, what in (("takagi_sugeno", "a Takagi-Sugeno model"), ("uncertainty", "an uncertain model")):
        if table in data and (table != "takagi_sugeno" or ts_raw is not None):
            raise v.err("model.dt", f"is {dt}: {what} ([{table}]) is continuous-time in fojax; remove dt, "
                        f"or remove [{table}] for a discrete-time model.")
    return dt


def _ts_faults(v: V, f: dict, ramp: bool, estimate_faults: bool) -> None:
    """``[faults]`` of a Takagi–Sugeno model: the faults act on the simulated plant (through
    `fojax.FaultyPlant`), the observers estimate ``z = L x`` only, since the T–S
    design (`fojax.design.design_ts_observer`) has no fault-augmented form. So
    ``estimate_faults`` must be given as ``false`` (its default ``true`` would ask for fault
    estimates) and ``ramp`` (the fault model of the augmented design) cannot be ``true``."""
    if estimate_faults:
        raise v.err("faults.estimate_faults", ("is true" if "estimate_faults" in f else "is missing (default true)")
                    + ": Takagi-Sugeno observers estimate z = L x only (the T-S design has no "
                    "fault-augmented form), so a T-S model's faults act on the simulated plant only. "
                    "Set estimate_faults = false in [faults].")
    if ramp:
        raise v.err("faults.ramp", "is true: ramp is the fault model of the fault-augmented design "
                    "(Remark 9), which Takagi-Sugeno observers do not use; remove it (the study's "
                    "faults are steps at a random onset).")


def _parameter_spread(v: V, u, ts_raw) -> dict:
    """``[uncertainty]`` of a T-S model: ``parameters = { name = spread, ... }``."""
    u = v.table("uncertainty", u, _UNCERTAINTY)
    if "dA" in u or "profile" in u:
        key = "uncertainty.dA" if "dA" in u else "uncertainty.profile"
        raise v.err(key, "is for LTI models; the uncertainty of a Takagi-Sugeno model is given as "
                    "relative spreads of its nonlinear plant's parameters: [takagi_sugeno] plant = "
                    "'robot_arm' and [uncertainty] parameters = { k = 0.2, m = 0.2, J_l = 0.2 }.")
    if "parameters" not in u:
        raise v.err("uncertainty.parameters", "missing: the uncertainty of a Takagi-Sugeno model is "
                    "parameters = { name = relative spread, ... } (e.g. { k = 0.2 }).")
    if not isinstance(ts_raw, dict) or "plant" not in ts_raw:
        raise v.err("uncertainty.parameters", "needs [takagi_sugeno] plant (the nonlinear model whose "
                    f"parameters are uncertain; one of {', '.join(map(repr, NONLINEAR_PLANTS))}).")
    pk = "uncertainty.parameters"
    table = u["parameters"]
    if not isinstance(table, dict) or not table:
        raise v.err(pk, f"expected a non-empty table {{ name = spread, ... }}, got {table!r}.")
    plant = v.string("takagi_sugeno.plant", ts_raw["plant"], NONLINEAR_PLANTS)
    names = set(_nonlinear_parameters(plant))
    v.table(pk, table, names)
    out = {}
    for name, val in table.items():
        s = v.number(join(pk, name), val, nonneg=True)
        if s >= 1:
            raise v.err(join(pk, name), f"is {s}; expected a relative spread in [0, 1) (the parameter is "
                        "nominal * (1 + spread * U(-1, 1)) and must keep its sign).")
        out[name] = float(s)
    return out


def _initial_state(v: V, value, n: int, takagi_sugeno: bool) -> np.ndarray:
    """``[initial_state] spread``: ``(n,)`` half-widths (or one number for every state)."""
    t = v.table("initial_state", value, _INITIAL_STATE, required=("spread",))
    if not takagi_sugeno:
        raise v.err("initial_state", "is only available for Takagi-Sugeno models so far (LTI studies "
                    "draw delta and faults, not x0); remove it.")
    key = "initial_state.spread"
    if isinstance(t["spread"], list):
        sp = v.array(key, t["spread"], 1, "a vector")
        v.shape(key, sp, (n,), f"one half-width per state, n = {n}")
    else:
        sp = np.full((n,), float(v.number(key, t["spread"])))
    if (sp < 0).any():
        raise v.err(key, f"has a negative entry {sp.min()}; expected half-widths >= 0.")
    return sp


def _nonlinear_parameters(name: str) -> tuple:
    from ..models import _robot_arm

    return {"robot_arm": _robot_arm.PARAMETERS}[name]


def _check_nonlinear_plant(v: V, ts: dict, E, A, B, C) -> None:
    """``[takagi_sugeno] plant``: the file's rule matrices and membership must be the sector
    form of that nonlinear model (so the T-S observers are designed for the plant simulated)."""
    from ..models import _robot_arm

    m = {"robot_arm": _robot_arm.ts_matrices}[ts["plant"]]()
    B_ref = m["B"] if B.ndim == 2 else np.broadcast_to(m["B"], B.shape)
    if ts["premise"] != "sinc" or ts["index"] != 1:
        raise v.err("takagi_sugeno.premise", f"is {ts['premise']!r} on output {ts['index']}; the sector form "
                    f"of '{ts['plant']}' has premise = 'sinc', index = 1 (rho = sin(y[1])/y[1]).")
    ref = {"model.E": (E, m["E"]), "model.A": (A, m["A"]), "model.B": (B, B_ref), "model.C": (C, m["C"]),
           "takagi_sugeno.lower": (np.array(ts["lower"]), np.array(m["rho_min"])),
           "takagi_sugeno.upper": (np.array(ts["upper"]), np.array(m["rho_max"]))}
    for key, (mine, theirs) in ref.items():
        theirs = np.asarray(theirs, dtype=float)
        if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-9, atol=1e-12):
            raise v.err(key, f"differs from the Takagi-Sugeno form of the nonlinear plant "
                        f"'{ts['plant']}' (fojax.models.{ts['plant']}_ts(): {np.array2string(theirs, precision=6)}); "
                        "the observers would be designed for another plant than the one simulated. "
                        "Use that model's matrices or remove [takagi_sugeno] plant.")


def _with_mat(v: V, model: dict, file: str) -> dict:
    """``[model] mat = "plant.mat"``: the matrices E, A, B, C, D, L (any case) read from a
    MATLAB file (`fojax.interop.load_mat`; a relative path is taken from the config file's
    folder), merged with the inline keys. A matrix given both ways is refused."""
    from .._errors import InputError
    from ..interop._mat import _variables

    ref = v.string("model.mat", model["mat"])
    path = pathlib.Path(ref)
    if not path.is_absolute() and file not in ("<config>", ""):
        path = pathlib.Path(file).parent / path
    try:
        found = _variables(path)
    except InputError as e:
        raise v.err("model.mat", str(e)) from None
    out = {k: val for k, val in model.items() if k != "mat"}
    for k in _MAT_MATRICES:
        if k in found:
            if k in model:
                raise v.err(join("model", k), f"is given inline and as variable {found[k][0]!r} of {ref}; keep one.")
            out[k] = np.atleast_2d(np.asarray(found[k][1], dtype=float)).tolist()
    if "E" not in out and "A" in out:  # a state-space model in the file: E = I
        out["E"] = np.eye(len(out["A"])).tolist()
    return out
