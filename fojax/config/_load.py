r"""TOML model and study files: format, validation and the objects they describe.

A config file describes one descriptor model, the observers to design for it and
(optionally) a Monte Carlo study and a tuning run. Matrices are nested lists of
numbers (rows). The full reference with examples is ``docs/config.md``; the thesis
examples ship as ``fojax/examples/*.toml`` (see `example_path`). Layout::

    name = "example_4_1_3"               # optional: a short name for result folders
    description = "..."                  # optional

    [model]                              # required
    E = [[1, 0], [0, 0]]                 # (n, n)            required
    A = [[-1, 1], [1, -2]]               # (n, n); (k, n, n) for a T-S model   required
    B = [[1], [0]]                       # (n, m); (k, n, m) allowed for T-S   required
    C = [[1, 0]]                         # (p, n)            required
    L = [[0, 1]]                         # (q, n) functional z = L x           required
    feedback = [[...]]                   # optional (m, n) K: the plant is (E, A + B K, B, C)
    x0 = [1, 0]                          # optional initial state (n,)

    [faults]                             # optional: E x' = A x + B u + Fa f, y = C x + Fs f
    Fa = [[...]]                         # (n, nf)   at least one of Fa, Fs
    Fs = [[...]]                         # (p, nf)
    ramp = false                         # Remark 9: ramp faults (f'' = 0)
    estimate_faults = true               # design for [L 0; 0 I] (estimate z and f)
    # a T-S model's faults act on the simulated plant only: its observers estimate z = L x
    # (no fault-augmented T-S design), so it needs estimate_faults = false (and no ramp)

    [uncertainty]                        # optional: A + sum_j delta_j(t) dA_j
    dA = [[[...]]]                       # list of (n, n) directions (or one matrix)
    profile = { kind = "uniform", bound = 0.3 }
        # kind = "constant" (value = [..]), "uniform" (bound: delta_j ~ U[-bound, bound]
        # per sample), or "sine" (amplitude, omega [, phase])

    [takagi_sugeno]                      # optional: [model] A (and B) hold one matrix per rule
    premise = "sinc"                     # rho = sin(y_i)/y_i ("sinc") or rho = y_i ("output")
    index = 1                            # output index i (0-based)
    lower = -0.217                       # rho range [lower, upper] of the sector membership
    upper = 1.0
    plant = "robot_arm"                  # optional: the nonlinear model `fojax study` simulates
                                         # (the rules are checked to be its sector form)
    # a T-S model's [uncertainty] is `parameters = { k = 0.2, ... }` (relative spreads of
    # that nonlinear plant's physical parameters), not dA/profile

    [initial_state]                      # optional, T-S models: x0 + U(-spread, spread)
    spread = [0.05, 0, 0.1, 0, 0]        # (n,) or one number

    [[observer]]                         # zero or more (default: one generalized observer)
    name = "FGDO"                        # optional
    kind = "generalized"                 # "generalized", "PI", "proportional", or (LTI, no
                                         # [faults]) "unknown-input" / "finite-time":
    D = [[...]]                          # unknown-input: (n, l) directions, E x' = ... + D d
    delay = 0.5                          # finite-time: h; and two separated disks
    regions = [{ center = -5.0, radius = 0.5 }, { center = -2.0, radius = 0.5 }]
    method = "auto"                      # finite-time: "auto", "lmi" or "place";
                                         # generalized / PI / proportional (LTI models): "lmi"
                                         # (default: the region LMI), "riccati" (a Riccati +
                                         # Stein route, no SDP, for one disk, half-plane or
                                         # sector; generalized and proportional; large models)
                                         # or "auto" (Riccati where it applies, else LMI)
    region = { disk = { center = -2.0, radius = 1.0 }, decay = 0.5, damping = 0.7 }
        # any non-empty subset; several parts are intersected. Default: disk(-2, 1).
    q0 = 2                               # optional observer order, or
    R = [[...]]                          # optional (q0, n) (of the designed, augmented system)
    q1 = 2                               # optional size of v
    objective = "hinf"                   # optional: "region" (default), "hinf" (minimise a
                                         # certified L2-gain bound from w, nu to zhat - z) or
                                         # "h2" (a certified H2-norm bound; no feedthrough) or
                                         # "centre" (eigenvalues as far inside a disk as the LMI allows)
    Bw = [[...]]                         # "hinf"/"h2": (n, mw) disturbance E x' = ... + Bw w
    Dv = [[...]]                         # "hinf"/"h2": (p, mv) noise y = C x + Dv nu
    balance = true                       # optional, generalized/PI/proportional/unknown-input on LTI
                                         # models: design unit-free (the design routine's balance;
                                         # default: its default)

    [study]                              # optional Monte Carlo settings
    samples = 64
    horizon = 10.0
    dt = 0.01
    seed = 0

    [tuning]                             # optional gradient tuning settings
    steps = 100
    learning_rate = 0.01
    loss = "ise"                         # training loss: "ise" (mean of the integral of e^2;
                                         # default) or "iae" (of |e|)
    robustness = { h2 = 0.1 }            # optional: H2Term / HinfTerm weights ("h2", "hinf") for
                                         # objective = "hinf"/"h2" observers (their channels)

Every problem raises `fojax.ConfigError` naming the file, the key (dotted path, e.g.
``observer[1].region.disk.radius``) and what was expected.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import pathlib
import tomllib
from typing import Any

import numpy as np

from .._errors import ConfigError, RegionError
from .._io import name_problem, NAME_RULE, suggest_name


KINDS = ("generalized", "PI", "proportional", "unknown-input", "finite-time")
#: Kinds designed by their own routine (`fojax.design.design_unknown_input_observer`,
#: `fojax.design.design_finite_time_observer`), for LTI models without [faults].
SPECIAL_KINDS = ("unknown-input", "finite-time")
FINITE_TIME_METHODS = ("auto", "lmi", "place")
#: ``method`` of the generalized / PI / proportional kinds: `fojax.design.design_functional_observer`'s.
DESIGN_METHODS = ("lmi", "riccati", "auto")
PROFILE_KINDS = ("constant", "uniform", "sine")
PREMISES = ("sinc", "output")

_TOP = {"name", "description", "model", "faults", "uncertainty", "initial_state", "takagi_sugeno", "observer",
        "study", "tuning"}
_MODEL = {"E", "A", "B", "C", "L", "feedback", "x0"}
_MODEL_REQUIRED = ("E", "A", "B", "C", "L")
_FAULTS = {"Fa", "Fs", "ramp", "estimate_faults"}
_UNCERTAINTY = {"dA", "profile", "parameters"}
_INITIAL_STATE = {"spread"}
_PROFILE = {
    "constant": {"kind", "value"},
    "uniform": {"kind", "bound"},
    "sine": {"kind", "amplitude", "omega", "phase"},
}
_TS = {"premise", "index", "lower", "upper", "plant"}
#: Nonlinear models a T-S file can name as its simulated plant (``[takagi_sugeno] plant``):
#: name -> (the `fojax.models` nonlinear example, its T-S form); see `Config.plant`.
NONLINEAR_PLANTS = ("robot_arm",)
_OBSERVER = {"name", "kind", "region", "R", "q0", "q1", "objective", "Bw", "Dv", "D", "delay", "regions",
             "method", "balance"}
OBJECTIVES = ("region", "hinf", "h2", "centre")
_REGION = {"disk", "decay", "damping"}
_DISK = {"center", "radius"}
_STUDY = {"samples", "horizon", "dt", "seed", "stepper"}
#: ``[study] stepper``: the stepper of the Monte Carlo run (`fojax.cli` builds the object).
STEPPERS = ("auto", "exact", "exponential", "diffrax")
_TUNING = {"steps", "learning_rate", "loss", "robustness"}


# --------------------------------------------------------------------------- results


@dataclasses.dataclass(frozen=True)
class ObserverSpec:
    """One ``[[observer]]`` entry: `kind`, `region` (an `AbstractRegion`), `R` or `q0`, `q1`."""

    name: str
    kind: str
    region: Any
    R: np.ndarray | None = None
    q0: int | None = None
    q1: int | None = None
    objective: str = "region"
    Bw: np.ndarray | None = None
    Dv: np.ndarray | None = None
    D: np.ndarray | None = None  # kind = "unknown-input": (n, l) unknown-input directions
    delay: float | None = None  # kind = "finite-time": the delay h
    regions: tuple | None = None  # kind = "finite-time": two disks
    # kind = "finite-time": "auto", "lmi" or "place"; generalized / PI / proportional:
    # "lmi", "riccati" or "auto" (None: the design routine's default, "lmi")
    method: str | None = None
    balance: bool | None = None  # the design routine's `balance` (None: its default)

    def design_kwargs(self) -> dict:
        """The ``objective``, ``method`` and ``balance`` keywords of
        `fojax.design.design_functional_observer` (empty for the defaults)."""
        kw = {} if self.objective == "region" else {"objective": self.objective, "Bw": self.Bw, "Dv": self.Dv}
        if self.method is not None and self.kind not in SPECIAL_KINDS:
            kw["method"] = self.method
        if self.balance is not None:
            kw["balance"] = self.balance
        return kw

    def route_words(self) -> str:
        """How the observer is designed, for progress messages."""
        if self.kind == "finite-time" or self.method in (None, "lmi"):
            return "by LMI"
        return "by the Riccati route" if self.method == "riccati" else "by the Riccati route where it applies, else LMI"


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """``[study]``: Monte Carlo `samples`, `horizon` [s], time step `dt` [s], `seed`, and
    the `stepper` of the Monte Carlo run (one of `STEPPERS`)."""

    samples: int = 64
    horizon: float = 10.0
    dt: float = 0.01
    seed: int = 0
    stepper: str = "auto"


@dataclasses.dataclass(frozen=True)
class TuningSpec:
    """``[tuning]``: optimisation `steps`, optax `learning_rate`, the training `loss` (``"ise"``,
    the default, or ``"iae"``: `fojax.tune`'s ``loss``), and `robustness`: the built-in terms
    ``(("h2" | "hinf", weight), ...)`` (`fojax.tuning.H2Term` / `HinfTerm`) added when an
    ``objective = "hinf"``/``"h2"`` design is tuned.

    *Why ISE by default* (`fojax study`, measured on its §3.3.7 benchmark, 60 steps, the
    tuned design evaluated on 512 samples of other seeds, one run each): trained on the
    mean IAE, the tuned observer's IAE changed by −1.7 % and its mean peak errors rose by
    +154 % (the fault estimates overshoot: IAE's gradient weighs an error's sign, not its
    size); trained on the mean ISE, IAE −9.8 % and peaks −30 %. `fojax.tune` itself keeps
    ``loss="iae"`` as its default."""

    steps: int = 100
    learning_rate: float = 0.01
    loss: str = "ise"
    robustness: tuple = ()


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated config file (all matrices float64 `numpy.ndarray`).

    **Fields:** `path`, `name`, `description`, `E`, `A` (``(n, n)`` or ``(k, n, n)``),
    `B`, `C`, `L`, `feedback` (or None), `x0` (or None), `Fa`, `Fs` (or None),
    `ramp`, `estimate_faults`, `dA` (``(k, n, n)`` or None), `profile` (dict or None),
    `takagi_sugeno` (dict or None), `observers` (tuple of `ObserverSpec`), `study`
    (`StudySpec` or None), `tuning` (`TuningSpec` or None), `raw` (the parsed TOML).
    """

    path: str
    name: str
    description: str
    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    L: np.ndarray
    feedback: np.ndarray | None
    x0: np.ndarray | None
    Fa: np.ndarray | None
    Fs: np.ndarray | None
    ramp: bool
    estimate_faults: bool
    dA: np.ndarray | None
    profile: dict | None
    takagi_sugeno: dict | None
    observers: tuple[ObserverSpec, ...]
    study: StudySpec | None
    tuning: TuningSpec | None
    raw: dict
    parameter_spread: dict | None = None
    x0_spread: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.E.shape[0]

    @property
    def is_takagi_sugeno(self) -> bool:
        return self.takagi_sugeno is not None

    @property
    def has_faults(self) -> bool:
        return self.Fa is not None or self.Fs is not None

    @property
    def augments_faults(self) -> bool:
        """Whether observers are designed for the fault-augmented system (eq. 3.196): LTI
        models with ``[faults]``. A Takagi–Sugeno model's faults act on the simulated plant
        only; its observers estimate ``z = L x`` of the nominal T–S model (the T–S design
        has no fault augmentation, so ``estimate_faults = true`` is refused at load)."""
        return self.has_faults and not self.is_takagi_sugeno

    def closed_loop_A(self) -> np.ndarray:
        """``A + B K`` with the `feedback` K (or `A`), per rule for T-S models."""
        if self.feedback is None:
            return self.A
        return self.A + self.B @ self.feedback

    def system(self):
        """The nominal (fault-free) `fojax.DescriptorSystem` ``(E, A + BK, B, C)``.

        For a Takagi–Sugeno model, the `fojax.TakagiSugenoSystem`.
        """
        from ..plant import DescriptorSystem, TakagiSugenoSystem
        from ..plant._takagi_sugeno import OutputPremise, SectorMembership, SincPremise

        if self.is_takagi_sugeno:
            ts = self.takagi_sugeno
            premise = (SincPremise if ts["premise"] == "sinc" else OutputPremise)(int(ts["index"]))
            membership = SectorMembership(premise, ts["lower"], ts["upper"])
            return TakagiSugenoSystem(self.E, self.closed_loop_A(), self.B, self.C, membership)
        return DescriptorSystem(self.E, self.closed_loop_A(), self.B, self.C)

    def rule_systems(self) -> list:
        """One `DescriptorSystem` per T-S rule (the nominal system alone otherwise)."""
        from ..plant import DescriptorSystem

        if not self.is_takagi_sugeno:
            return [self.system()]
        A = self.closed_loop_A()
        B = self.B if self.B.ndim == 3 else np.broadcast_to(self.B, (A.shape[0],) + self.B.shape)
        return [DescriptorSystem(self.E, A[i], B[i], self.C) for i in range(A.shape[0])]

    def design_system(self):
        """The system observers are designed for: fault-augmented (eq. 3.196) if
        ``[faults]`` is given (LTI models, `augments_faults`), else `system`."""
        from ..plant import augment_faults

        sys_ = self.system()
        if self.augments_faults:
            return augment_faults(sys_, self.Fa, self.Fs, ramp=self.ramp)
        return sys_

    def design_L(self) -> np.ndarray:
        """The functional of the designed system: `L`, or ``[L 0; 0 I]`` (``[L 0]`` when
        ``estimate_faults = false``) with faults (``[L 0 0; 0 I 0]`` for ramp faults);
        `L` for a Takagi–Sugeno model (see `augments_faults`)."""
        if not self.augments_faults:
            return self.L
        nf = (self.Fa if self.Fa is not None else self.Fs).shape[1]
        extra = 2 * nf if self.ramp else nf
        q, n = self.L.shape
        top = np.hstack([self.L, np.zeros((q, extra))])
        if not self.estimate_faults:
            return top
        bottom = np.hstack([np.zeros((nf, n)), np.eye(nf), np.zeros((nf, extra - nf))])
        return np.vstack([top, bottom])

    def nonlinear_model(self):
        """The `fojax.models` example named by ``[takagi_sugeno] plant`` (a `ThesisExample`
        whose `system` is the nonlinear model; its `theta` holds the physical parameters
        that ``[uncertainty] parameters`` perturbs), or None."""
        name = (self.takagi_sugeno or {}).get("plant")
        if name is None:
            return None
        from ..models import robot_arm

        return {"robot_arm": robot_arm}[name]()

    def plant(self):
        """The simulated plant. For a Takagi–Sugeno model with ``[takagi_sugeno] plant``,
        that nonlinear model (`nonlinear_model`; the file's rules are checked at load to be
        its exact sector form), else the `fojax.TakagiSugenoSystem`. Otherwise `system`, wrapped in a `fojax.UncertainDescriptorSystem`
        when ``[uncertainty]`` is given (constant profiles use ``value``, sine profiles
        the `fojax.Sine` signal, uniform profiles the nominal ``δ = 0``)."""
        if self.is_takagi_sugeno and self.takagi_sugeno.get("plant") is not None:
            return self.nonlinear_model().system
        sys_ = self.system()
        if self.dA is None:
            return sys_
        import jax.numpy as jnp

        from ..plant import Sine, UncertainDescriptorSystem

        k = self.dA.shape[0]
        prof = self.profile or {"kind": "constant", "value": [0.0] * k}
        if prof["kind"] == "sine":
            amp = np.broadcast_to(np.asarray(prof["amplitude"], float), (k,))
            delta = Sine(jnp.asarray(amp), float(prof["omega"]), float(prof.get("phase", 0.0)))
        elif prof["kind"] == "constant":
            delta = jnp.asarray(np.broadcast_to(np.asarray(prof["value"], float), (k,)))
        else:
            delta = jnp.zeros((k,))
        return UncertainDescriptorSystem(sys_, dA=jnp.asarray(self.dA), delta=delta)


# --------------------------------------------------------------------------- validation


class _V:
    """Validation helpers bound to one file name."""

    def __init__(self, file: str):
        self.file = file

    def err(self, key: str, message: str) -> ConfigError:
        return ConfigError(self.file, key, message)

    def table(self, key: str, value, allowed: set, required=()) -> dict:
        if not isinstance(value, dict):
            raise self.err(key, f"expected a table ([{key}] or {{...}}), got {_typename(value)}.")
        for k in value:
            if k not in allowed:
                close = difflib.get_close_matches(k, sorted(allowed), n=1, cutoff=0.5)
                hint = f" Did you mean '{close[0]}'?" if close else ""
                raise self.err(
                    _join(key, k),
                    f"unknown key '{k}'.{hint} Allowed keys in [{key or 'top level'}]: "
                    f"{', '.join(sorted(allowed))}.",
                )
        for k in required:
            if k not in value:
                raise self.err(_join(key, k), f"missing required key '{k}' in [{key or 'top level'}].")
        return value

    def number(self, key, value, *, positive=False, nonneg=False, integer=False) -> float | int:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        if integer and not (isinstance(value, int) and not isinstance(value, bool)):
            raise self.err(key, f"expected an integer, got {value!r} ({_typename(value)}).")
        if not ok:
            raise self.err(key, f"expected a number, got {value!r} ({_typename(value)}).")
        if not math.isfinite(value):
            raise self.err(key, f"expected a finite number, got {value!r}.")
        if positive and value <= 0:
            raise self.err(key, f"expected a positive number, got {value!r}.")
        if nonneg and value < 0:
            raise self.err(key, f"expected a number >= 0, got {value!r}.")
        return value

    def string(self, key, value, choices=None) -> str:
        if not isinstance(value, str):
            raise self.err(key, f"expected a string, got {value!r} ({_typename(value)}).")
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
            raise self.err(key, f"expected true or false, got {value!r} ({_typename(value)}).")
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
                    f"expected {what} of numbers; entry {key}{where} is {v!r} ({_typename(v)}).",
                )
            if not math.isfinite(v):
                where = "".join(f"[{i}]" for i in path)
                raise self.err(key, f"entry {key}{where} is {v!r}; every entry must be finite.")
            return float(v)

        if not isinstance(value, list):
            raise self.err(key, f"expected {what} (nested lists of numbers), got {_typename(value)}.")
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


def _typename(v) -> str:
    return {dict: "table", list: "list", str: "string", bool: "boolean"}.get(type(v), type(v).__name__)


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _objective(v: _V, key: str, o: dict, n: int, n_design: int, p: int, takagi_sugeno: bool):
    """``objective``, ``Bw``, ``Dv`` of one ``[[observer]]``. `Bw` may have `n` rows (the
    model's states; zero rows are added for fault states) or `n_design` rows."""
    objective = v.string(_join(key, "objective"), o["objective"], OBJECTIVES) if "objective" in o else "region"
    if objective in ("region", "centre"):
        for ch in ("Bw", "Dv"):
            if ch in o:
                raise v.err(_join(key, ch), 'is only used with objective = "hinf" or "h2"; add that line or remove '
                            'the key.')
        if objective == "centre" and takagi_sugeno:
            raise v.err(_join(key, "objective"), 'is "centre", which is for linear models (not [takagi_sugeno]).')
        return objective, None, None
    if takagi_sugeno:
        raise v.err(_join(key, "objective"), f'is "{objective}", which is for linear models (not [takagi_sugeno]).')
    if "Bw" not in o and "Dv" not in o:
        raise v.err(_join(key, "objective"), f'is "{objective}" but neither Bw (n x mw disturbance) nor Dv '
                    "(p x mv measurement noise) is given: add at least one.")
    Bw = Dv = None
    if "Bw" in o:
        Bw = v.array(_join(key, "Bw"), o["Bw"], 2, "an n x mw matrix")
        if Bw.shape[0] == n and n_design != n:
            Bw = np.vstack([Bw, np.zeros((n_design - n, Bw.shape[1]))])
        if Bw.shape[0] != n_design:
            raise v.err(_join(key, "Bw"), f"has shape {Bw.shape}, expected ({n}, mw) (one row per state"
                        + (f", or {n_design} rows of the fault-augmented system)." if n_design != n else ")."))
    if "Dv" in o:
        Dv = v.array(_join(key, "Dv"), o["Dv"], 2, "a p x mv matrix")
        if Dv.shape[0] != p:
            raise v.err(_join(key, "Dv"), f"has shape {Dv.shape}, expected ({p}, mv) (one row per output, p = {p} from C).")
    return objective, Bw, Dv


def _balance(v: _V, key: str, o: dict, kind: str, takagi_sugeno: bool) -> bool | None:
    """``balance`` of one ``[[observer]]`` (None when absent): a boolean, for the designs that
    have it (`fojax.design.design_functional_observer`, `fojax.design.design_unknown_input_observer`)."""
    if "balance" not in o:
        return None
    k = _join(key, "balance")
    value = v.boolean(k, o["balance"])
    if takagi_sugeno:
        raise v.err(k, "is for linear models (design_functional_observer), not [takagi_sugeno]: remove the key.")
    if kind == "finite-time":
        raise v.err(k, f"is for the generalized, PI, proportional and unknown-input kinds, not {kind!r}: remove "
                    "the key.")
    return value


def _region(v: _V, key: str, value):
    from ..design import Disk, HalfPlane, Intersection, Sector

    value = v.table(key, value, _REGION)
    if not value:
        raise v.err(key, "is empty; give at least one of disk = {center, radius}, decay, damping.")
    parts = []
    if "disk" in value:
        dkey = _join(key, "disk")
        d = v.table(dkey, value["disk"], _DISK, required=("center", "radius"))
        c = v.number(_join(dkey, "center"), d["center"])
        r = v.number(_join(dkey, "radius"), d["radius"], positive=True)
        if c + r >= 0:
            raise v.err(
                dkey,
                f"disk(center={c}, radius={r}) reaches into the closed right half-plane "
                f"(rightmost point {c + r}); expected center + radius < 0.",
            )
        parts.append(Disk(c, r))
    if "decay" in value:
        parts.append(HalfPlane(v.number(_join(key, "decay"), value["decay"], nonneg=True)))
    if "damping" in value:
        zeta = v.number(_join(key, "damping"), value["damping"])
        if not 0.0 < zeta < 1.0:
            raise v.err(_join(key, "damping"), f"expected a damping ratio in (0, 1), got {zeta!r}.")
        parts.append(Sector(zeta))
    try:
        return parts[0] if len(parts) == 1 else Intersection(tuple(parts))
    except RegionError as e:  # pragma: no cover - every parameter is checked above
        raise v.err(key, str(e)) from None


def parse_config(data: dict, file: str = "<config>") -> Config:
    """Validate an already parsed TOML document (see the module docstring for the format).

    **Arguments:**

    - `data`: the dict `tomllib` returns.
    - `file`: the name used in error messages.

    **Returns:** a `Config`. **Raises:** `fojax.ConfigError`.
    """
    v = _V(file)
    _check_model_header(v, data)
    v.table("", data, _TOP, required=("model",))
    # the model name names the results folders (design-<name>-<time>, study-<name>-<time>);
    # without one, the file name, made portable
    name = (v.file_name("name", data["name"], "my_model") if "name" in data
            else suggest_name(pathlib.Path(file).stem, "model"))
    description = v.string("description", data["description"]) if "description" in data else ""
    ts_raw = data.get("takagi_sugeno")
    model = v.table("model", data["model"], _MODEL, required=_MODEL_REQUIRED)

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
    n, src = _state_count(E=E, A=A, B=B, C=C, L=L)
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
                raise v.err(pk, f"expected a table {{ kind = ... }}, got {_typename(pr)}.")
            kind = v.string(_join(pk, "kind"), pr.get("kind", None) if "kind" in pr else _missing(v, _join(pk, "kind")), PROFILE_KINDS)
            v.table(pk, pr, _PROFILE[kind], required=[r for r in {"constant": ("value",), "uniform": ("bound",), "sine": ("amplitude", "omega")}[kind]])
            profile = {"kind": kind}
            for key in sorted(set(pr) - {"kind"}):
                val = pr[key]
                if isinstance(val, list):
                    arr = v.array(_join(pk, key), val, 1, f"a list of {k} numbers")
                    v.shape(_join(pk, key), arr, (k,), f"one per uncertainty direction, k = {k}")
                    profile[key] = arr.tolist()
                else:
                    profile[key] = v.number(_join(pk, key), val, nonneg=key in ("bound", "omega"))

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
    observers = []
    raw_obs = data.get("observer", [])
    if isinstance(raw_obs, dict):
        raw_obs = [raw_obs]
    if not isinstance(raw_obs, list):
        raise v.err("observer", f"expected [[observer]] tables, got {_typename(raw_obs)}.")
    for i, o in enumerate(raw_obs):
        key = f"observer[{i}]"
        o = v.table(key, o, _OBSERVER)
        kind = v.string(_join(key, "kind"), o["kind"], KINDS) if "kind" in o else "generalized"
        from ..design import Disk

        region = _region(v, _join(key, "region"), o["region"]) if "region" in o else Disk(-2.0, 1.0)
        R = q0 = q1 = None
        if "R" in o and "q0" in o:
            raise v.err(_join(key, "q0"), "give either R or q0, not both (q0 is the number of rows of R).")
        if "R" in o:
            R = v.array(_join(key, "R"), o["R"], 2, "a q0 x n matrix")
            if R.shape[1] != n_design:
                raise v.err(_join(key, "R"), f"has shape {R.shape}, expected (q0, {n_design}) (columns = states of the designed{' fault-augmented' if n_design != n else ''} system).")
        if "q0" in o:
            q0 = v.number(_join(key, "q0"), o["q0"], integer=True, positive=True)
        if "q1" in o:
            q1 = v.number(_join(key, "q1"), o["q1"], integer=True, nonneg=True)
            if kind == "proportional" and q1 != 0:
                raise v.err(_join(key, "q1"), f"is {q1}; a proportional observer has q1 = 0.")
        objective, Bw, Dv = _objective(v, key, o, n, n_design, p, ts is not None)
        oname = v.file_name(_join(key, "name"), o["name"], f"observer_{i + 1}") if "name" in o else f"{kind}-{i + 1}"
        special = _special_observer(v, key, o, kind, n, ts_raw is not None, Fa is not None or Fs is not None, region)
        if objective != "region" and kind in ("unknown-input", "finite-time"):
            raise v.err(_join(key, "objective"), f"is {objective!r}; objective = {objective!r} is for the generalized, PI "
                        f"and proportional kinds, not {kind!r}: remove the key.")
        balance = _balance(v, key, o, kind, ts is not None)
        observers.append(ObserverSpec(oname, kind, region, R, q0, q1, objective, Bw, Dv, balance=balance, **special))
    _check_observer_names(v, [o.name for o in observers])

    study = None
    if "study" in data:
        s = v.table("study", data["study"], _STUDY)
        kw = {}
        if "samples" in s:
            kw["samples"] = v.number("study.samples", s["samples"], integer=True, positive=True)
        if "horizon" in s:
            kw["horizon"] = float(v.number("study.horizon", s["horizon"], positive=True))
        if "dt" in s:
            kw["dt"] = float(v.number("study.dt", s["dt"], positive=True))
        if "seed" in s:
            kw["seed"] = v.number("study.seed", s["seed"], integer=True, nonneg=True)
        if "stepper" in s:
            kw["stepper"] = v.string("study.stepper", s["stepper"], STEPPERS)
        study = StudySpec(**kw)
        if study.dt >= study.horizon:
            raise v.err("study.dt", f"is {study.dt}; expected a time step smaller than study.horizon = {study.horizon}.")
    tuning = None
    if "tuning" in data:
        t = v.table("tuning", data["tuning"], _TUNING)
        kw = {}
        if "steps" in t:
            kw["steps"] = v.number("tuning.steps", t["steps"], integer=True, positive=True)
        if "learning_rate" in t:
            kw["learning_rate"] = float(v.number("tuning.learning_rate", t["learning_rate"], positive=True))
        if "loss" in t:
            kw["loss"] = v.string("tuning.loss", t["loss"], ("ise", "iae"))
        if "robustness" in t:
            r = v.table("tuning.robustness", t["robustness"], {"h2", "hinf"})
            kw["robustness"] = tuple((k, float(v.number(f"tuning.robustness.{k}", r[k], nonneg=True)))
                                     for k in sorted(r))
        tuning = TuningSpec(**kw)

    return Config(
        path=file, name=name, description=description, E=E, A=A, B=B, C=C, L=L,
        feedback=feedback, x0=x0, Fa=Fa, Fs=Fs, ramp=ramp, estimate_faults=estimate_faults,
        dA=dA, profile=profile, takagi_sugeno=ts, observers=tuple(observers), study=study,
        tuning=tuning, raw=data, parameter_spread=parameter_spread, x0_spread=x0_spread,
    )


def _special_observer(v: _V, key: str, o: dict, kind: str, n: int, ts: bool, faults: bool, region) -> dict:
    """The keys of ``kind = "unknown-input"`` (``D``) and ``kind = "finite-time"``
    (``delay``, ``regions``, ``method``), refused for the other kinds; and the ``method``
    of the generalized / PI / proportional kinds (`_design_method`)."""
    own = {"unknown-input": ("D",), "finite-time": ("delay", "regions")}
    for k in ("D", "delay", "regions"):
        if k in o and k not in own.get(kind, ()):
            owner = next(kk for kk, keys in own.items() if k in keys)
            raise v.err(_join(key, k), f"is a key of kind = '{owner}' observers; this observer has kind = '{kind}'.")
    if kind not in SPECIAL_KINDS:
        return _design_method(v, key, o, kind, ts, region)
    if kind == "unknown-input" and "method" in o:
        raise v.err(_join(key, "method"), "is not a key of kind = 'unknown-input' observers (their design "
                    "has one route, the LMI); remove it.")
    if ts or faults:
        raise v.err(_join(key, "kind"), f"'{kind}' observers are designed for LTI models without "
                    f"[{'takagi_sugeno' if ts else 'faults'}]; use 'generalized', 'PI' or 'proportional'.")
    if "region" in o and kind == "finite-time":
        raise v.err(_join(key, "region"), "a finite-time observer has two regions: give regions = "
                    "[{ center = c1, radius = r1 }, { center = c2, radius = r2 }] instead.")
    if kind == "unknown-input":
        if "D" not in o:
            raise v.err(_join(key, "D"), "missing: an unknown-input observer needs D, the (n, l) matrix "
                        "of unknown-input directions (E x' = A x + B u + D d).")
        D = v.array(_join(key, "D"), o["D"], 2, "an n x l matrix")
        if D.shape[0] != n:
            raise v.err(_join(key, "D"), f"has shape {D.shape}, expected ({n}, l) (one row per state, n = {n}).")
        return {"D": D}
    if "delay" not in o:
        raise v.err(_join(key, "delay"), "missing: a finite-time observer needs its delay h > 0 "
                    "(the estimate is exact for t >= h).")
    h = float(v.number(_join(key, "delay"), o["delay"], positive=True))
    from ..design import Disk

    regions = (Disk(-5.0, 0.5), Disk(-2.0, 0.5))
    if "regions" in o:
        rk = _join(key, "regions")
        r = o["regions"]
        if not isinstance(r, list) or len(r) != 2:
            raise v.err(rk, f"expected two disks [{{ center = c1, radius = r1 }}, {{ center = c2, radius = r2 }}], got {r!r}.")
        disks = []
        for j, d in enumerate(r):
            dk = f"{rk}[{j}]"
            d = v.table(dk, d, _DISK, required=("center", "radius"))
            c = v.number(_join(dk, "center"), d["center"])
            rad = v.number(_join(dk, "radius"), d["radius"], positive=True)
            if c + rad >= 0:
                raise v.err(dk, f"disk(center={c}, radius={rad}) reaches into the closed right half-plane; "
                            "expected center + radius < 0.")
            disks.append(Disk(c, rad))
        (c1, r1), (c2, r2) = ((float(d.center), float(d.radius)) for d in disks)
        if not (c1 + r1 < c2 - r2 or c2 + r2 < c1 - r1):
            raise v.err(rk, f"the disks ({c1}, {r1}) and ({c2}, {r2}) overlap along the real axis; the two "
                        "observers' eigenvalues must be separated (Lemma 6).")
        regions = tuple(disks)
    method = v.string(_join(key, "method"), o["method"], FINITE_TIME_METHODS) if "method" in o else "auto"
    return {"delay": h, "regions": regions, "method": method}


def _design_method(v: _V, key: str, o: dict, kind: str, ts: bool, region) -> dict:
    """``method`` of a generalized / PI / proportional observer (`DESIGN_METHODS`), checked
    against what the Riccati route can do (`fojax.design._riccati.riccati_applies`): one
    LTI model (not a Takagi–Sugeno family, which needs a common certificate), kind
    generalized or proportional (PI fixes S = 0), one disk, half-plane or sector, and not
    ``objective = "centre"`` (a search over the region LMI)."""
    if "method" not in o:
        return {}
    mk = _join(key, "method")
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


def _ts_faults(v: _V, f: dict, ramp: bool, estimate_faults: bool) -> None:
    """``[faults]`` of a Takagi–Sugeno model: the faults act on the simulated plant (through
    `fojax.studies.FaultyPlant`), the observers estimate ``z = L x`` only, since the T–S
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


def _parameter_spread(v: _V, u, ts_raw) -> dict:
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
        s = v.number(_join(pk, name), val, nonneg=True)
        if s >= 1:
            raise v.err(_join(pk, name), f"is {s}; expected a relative spread in [0, 1) (the parameter is "
                        "nominal * (1 + spread * U(-1, 1)) and must keep its sign).")
        out[name] = float(s)
    return out


def _initial_state(v: _V, value, n: int, takagi_sugeno: bool) -> np.ndarray:
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


def _check_nonlinear_plant(v: _V, ts: dict, E, A, B, C) -> None:
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


#: Files `fojax study` writes beside the observers' ``<name>.npz`` (an observer of that name
#: would share the file).
_STUDY_STEMS = ("study", "metrics")


def _check_observer_names(v: _V, names: list[str]) -> None:
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


def _check_model_header(v: _V, data) -> None:
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


def _state_count(**mats) -> tuple[int, Any]:
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


def _missing(v: _V, key: str):
    raise v.err(key, f"missing required key '{key.rsplit('.', 1)[-1]}'.")


def load_config(path) -> Config:
    """Read and validate a TOML model/study file.

    **Arguments:**

    - `path`: the ``.toml`` file (format: module docstring and ``docs/config.md``).

    **Returns:** a `Config`.

    **Raises:** `fojax.ConfigError` naming the file, the key and what was expected
    (missing file, TOML syntax, unknown or missing keys, non-numeric entries, wrong
    shapes, inconsistent dimensions, bad region parameters).
    """
    path = pathlib.Path(path)
    file = str(path)
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(file, "(file)", "does not exist; pass the path of a .toml config file.") from None
    except OSError as e:
        raise ConfigError(file, "(file)", f"cannot be read: {e.strerror}.") from None
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(file, "(file)", "is not UTF-8 text; a TOML file is expected.") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(file, "(syntax)", f"is not valid TOML: {e}.") from None
    return parse_config(data, file)


def example_names() -> list[str]:
    """Names of the example configs shipped in ``fojax/examples`` (without ``.toml``)."""
    import importlib.resources

    root = importlib.resources.files("fojax").joinpath("examples")
    return sorted(p.name[: -len(".toml")] for p in root.iterdir() if p.name.endswith(".toml"))


def example_path(name: str) -> pathlib.Path:
    """Path of a shipped example config, e.g. ``example_path("example_3_3_7")``."""
    import importlib.resources

    names = example_names()
    if name.endswith(".toml"):
        name = name[:-5]
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise ConfigError(None, "example", f"no example named {name!r}.{hint} Available: {', '.join(names)}.")
    return pathlib.Path(str(importlib.resources.files("fojax").joinpath("examples", f"{name}.toml")))
