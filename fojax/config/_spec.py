"""The objects a config file describes (`Config`, `ObserverSpec`, `StudySpec`,
`TuningSpec`) and the file's vocabulary (table keys, kinds, methods)."""


from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


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
_MODEL = {"E", "A", "B", "C", "D", "L", "feedback", "x0", "mat", "dt"}
#: The matrices a ``mat = "file.mat"`` reference may hold (`fojax.interop.load_mat`).
_MAT_MATRICES = ("E", "A", "B", "C", "D", "L")
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

    ISE is the default of config files because IAE's gradient weighs an error's sign, not
    its size: trained on IAE, a tuned observer may trade a lower mean for larger peaks (fault
    estimates that overshoot), while ISE penalises large errors most. `fojax.tune` itself
    keeps ``loss="iae"`` as its default."""

    steps: int = 100
    learning_rate: float = 0.01
    loss: str = "ise"
    robustness: tuple = ()


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated config file (all matrices float64 `numpy.ndarray`).

    **Fields:** `path`, `name`, `description`, `E`, `A` (``(n, n)`` or ``(k, n, n)``),
    `B`, `C`, `L`, `D` (the ``(p, m)`` feedthrough, or None), `dt` (the sampling period of a
    discrete-time model, or None), `feedback` (or None), `x0` (or None), `Fa`, `Fs` (or None),
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
    D: np.ndarray | None = None
    dt: float | None = None

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
        has no fault augmentation, so ``estimate_faults = true`` is refused when the file is read)."""
        return self.has_faults and not self.is_takagi_sugeno

    def closed_loop_A(self) -> np.ndarray:
        """``A + B K`` with the `feedback` K (or `A`), per rule for T-S models."""
        if self.feedback is None:
            return self.A
        return self.A + self.B @ self.feedback

    def system(self):
        """The nominal (fault-free) `fojax.DescriptorSystem` ``(E, A + BK, B, C + DK, D)``,
        discrete-time with the file's `dt` when it has one.

        For a Takagi–Sugeno model, the `fojax.TakagiSugenoSystem`.
        """
        from ..plant import (
            DescriptorSystem,
            OutputPremise,
            SectorMembership,
            SincPremise,
            TakagiSugenoSystem,
        )

        if self.is_takagi_sugeno:
            ts = self.takagi_sugeno
            premise = (SincPremise if ts["premise"] == "sinc" else OutputPremise)(int(ts["index"]))
            membership = SectorMembership(premise, ts["lower"], ts["upper"])
            return TakagiSugenoSystem(self.E, self.closed_loop_A(), self.B, self.C, membership)
        return DescriptorSystem(self.E, self.closed_loop_A(), self.B, self.closed_loop_C(), self.D, dt=self.dt)

    def closed_loop_C(self) -> np.ndarray:
        """``C + D K`` with the `feedback` K and a feedthrough `D` (``y = Cx + D(Kx + u)``), else `C`."""
        if self.feedback is None or self.D is None:
            return self.C
        return self.C + self.D @ self.feedback

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
        that nonlinear model (`nonlinear_model`; the file's rules are checked when it is read to be
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
