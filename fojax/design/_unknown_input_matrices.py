r"""The unknown-input observer's matrices as functions of its free parameters (conditions
a.–f. of `fojax.design.design_unknown_input_observer`, which derives them), its residuals,
its unit-free check and its design object `UnknownInputObserverDesign`.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..observer import UnknownInputObserver
from ._conditions import (
    unit_free_structure,
)
from ._functional import (
    AbstractStructureDesign,
    carried_extra,
    condition_scales,
    model_structure,
    unit_free_failure,
)
from ._parameterization import (
    FunctionalObserverStructure,
    observer_matrices,
    pieces,
)
from ._regions import AbstractRegion
from ._verify import relative_residual, RESIDUAL_RTOL, VerificationReport, verify


# ---------------------------------------------------------------------------- parameterization


class UnknownInputObserverMatrices(NamedTuple):
    """Matrices of the unknown-input observer (no rule axis)."""

    N: object
    J: object
    F: object
    H: object
    Delta: object
    S: object
    G: object
    M: object
    Phi: object
    Lambda: object
    W: object
    P: object
    Q: object
    T: object
    K: object
    Z_eff: object


def unknown_input_observer_matrices(
    s: FunctionalObserverStructure, D, Z, Y1, Y2, Y3, J, G, Y4, Lambda, *, xp=jnp
) -> UnknownInputObserverMatrices:
    r"""Free parameters → observer matrices (pure; traceable with ``xp=jax.numpy``).

    `s` must be built with ``Eperp`` = left null space of ``[E D]`` (see module
    docstring). Conditions a.–f. hold for every value of the parameters; $\Delta = TD$,
    $\Phi = -Y_4N_3$, $W = Y_4F_3$, $\Lambda$ free.
    """
    m = observer_matrices(s, Z, Y1, Y2, Y3, J, G, xp=xp)
    N3 = pieces(s, xp=xp).N3
    Y4 = xp.asarray(Y4)
    T = m.T
    Delta = T @ xp.asarray(D)
    Phi = -Y4 @ N3
    W = Y4 @ m.F3
    return UnknownInputObserverMatrices(
        m.N[0], m.J[0], m.F[0], m.H[0], Delta, m.S[0], m.G[0], m.M[0], Phi,
        xp.asarray(Lambda), W, m.P[0], m.Q[0], T, m.K, m.Z_eff,
    )  # fmt: skip


def unknown_input_error_dynamics(mats: UnknownInputObserverMatrices, xp=jnp):
    r"""$\mathbb A = [N\;J\;\Delta;\;S\;G\;0;\;\Phi\;\Lambda\;0]$."""
    q1, l = mats.G.shape[0], mats.Delta.shape[1]
    return xp.concatenate(
        [
            xp.concatenate([mats.N, mats.J, mats.Delta], axis=1),
            xp.concatenate([mats.S, mats.G, xp.zeros((q1, l))], axis=1),
            xp.concatenate([mats.Phi, mats.Lambda, xp.zeros((l, l))], axis=1),
        ],
        axis=0,
    )


def unknown_input_residuals(s: FunctionalObserverStructure, D, mats, xp=np) -> dict:
    """Residuals (spectral norm) of conditions a.–f. of Lemma 9 and the data scale
    ``max(1, ‖E‖, ‖A‖, ‖B‖, ‖C‖, ‖L‖, ‖D‖) · max(1, ‖T‖, ‖N‖, ‖F‖, …, ‖W‖)`` (traceable
    with ``xp=jax.numpy``)."""
    E, A, B, C, L, Ep = (xp.asarray(x) for x in (s.E, s.A, s.B, s.C, s.L, s.Eperp))
    D = xp.asarray(D)
    Psi = xp.concatenate([Ep @ A, C], axis=0)
    T = mats.T
    TE = T @ E
    res = {
        "a": mats.N @ TE + mats.F @ Psi - T @ A,
        "b": mats.H - T @ B,
        "c": mats.Delta - T @ D,
        "d": mats.S @ TE + mats.M @ Psi,
        "e": mats.Phi @ TE - mats.W @ Psi,
        "f": mats.P @ TE + mats.Q @ Psi - L,
    }

    def nrm(x):
        return xp.linalg.norm(x, ord=2) if x.size else xp.zeros(())

    out = {k: nrm(v) for k, v in res.items()}
    data = xp.max(xp.stack([nrm(x) for x in (E, A, B, C, L, D)] + [xp.ones(())]))
    names = ("T", "N", "F", "S", "M", "P", "Q", "Delta", "Phi", "W")
    gains = xp.max(xp.stack([nrm(xp.asarray(getattr(mats, k))) for k in names] + [xp.ones(())]))
    out["scale"] = data * gains
    return out


def unknown_input_condition_scales(s: FunctionalObserverStructure, D, mats) -> dict:
    """Per condition a.–f., the sum of the norms of its terms (host): the scale its residual
    is relative to in `verify`, as for the functional observer (`condition_scales`: a., b.,
    and its c., d. are d., f. here); c. ``‖Δ‖ + ‖T‖‖D‖``, e. ``‖Φ‖‖TE‖ + ‖W‖‖Ψ‖``."""

    def nrm(x):
        x = np.asarray(x, dtype=float)
        return float(np.linalg.norm(x, ord=2)) if x.size else 0.0

    fo = condition_scales(s, mats)
    T = np.asarray(mats.T)
    Psi = np.vstack([np.asarray(s.Eperp) @ np.asarray(s.A), np.asarray(s.C)])
    return {"a": fo["a"], "b": fo["b"], "c": nrm(mats.Delta) + nrm(T) * nrm(D), "d": fo["c"],
            "e": nrm(mats.Phi) * nrm(T @ np.asarray(s.E)) + nrm(mats.W) * nrm(Psi), "f": fo["d"]}


def _residuals(s, D, mats) -> tuple[dict, float, dict]:
    """``(residuals a.–f., data scale, per-condition scales)`` on the host."""
    res = {k: float(v) for k, v in unknown_input_residuals(s, D, mats).items()}
    scale = res.pop("scale")
    return res, scale, unknown_input_condition_scales(s, D, mats)


def unit_free_check(s: FunctionalObserverStructure, D, params) -> tuple | None:
    r"""``("unit-free relative residual", value, failure or None)``: conditions a.–f. of the
    observer of `params` re-checked in the unit-free frame (`fojax.analysis.unit_scaling`:
    $E_b = D_lED_r$, …, $D_b = D_lD$, $E^\perp_b = E^\perp D_l^{-1}$, $T_b = TD_l^{-1}$, the
    other observer matrices unchanged, so $\Delta = T_bD_b$), or ``None`` for models larger
    than `fojax.design._conditions.UNIT_FREE_CHECK_MAX` — the functional observer's
    `fojax.design._functional.unit_free_check` with the unknown input. Why: on badly scaled
    data (rows and states rescaled by 1e-6…1e6) a residual that is round-off relative to
    the large terms of the data as given can be O(0.1) in the unit-free frame."""
    uf = unit_free_structure(s)
    if uf is None:
        return None
    sb, dl, _ = uf
    mats = unknown_input_observer_matrices(s, D, **params, xp=np)
    mb = mats._replace(T=np.asarray(mats.T) / dl[None, :])
    rel = relative_residual(*_residuals(sb, dl[:, None] * np.asarray(D, float), mb))
    return ("unit-free relative residual", rel, unit_free_failure(rel, "a.-f."))


# ---------------------------------------------------------------------------- design object


@dataclasses.dataclass(frozen=True)
class UnknownInputObserverDesign(AbstractStructureDesign):
    """A verified unknown-input functional-observer design.

    Attributes (besides `structure`, `params`, `T`, `K`, `Z_eff`, `X`, `report` and `solver`,
    which every design on a `FunctionalObserverStructure` has):
        observer: the `UnknownInputObserver` (state ``[ζ; v; d̂]``).
        region: the pole region of 𝔸 = [N J Δ; S G 0; Φ Λ 0].
        D: the unknown-input matrix.

    Here `structure`'s E⊥ annihilates ``[E D]``; `params` are ``Z, Y1, Y2, Y3, J, G, Y4,
    Lambda``; `X` is the (full) LMI certificate of 𝔸; `report` has the residuals
    ``a``–``f``; `solver` holds ``step1`` (the choice of Z) and ``lmi``.
    """

    observer: UnknownInputObserver
    region: AbstractRegion
    D: np.ndarray

    @property
    def error_matrix(self) -> np.ndarray:
        return np.asarray(self.observer.error_matrix)

    def verify(self) -> VerificationReport:
        """Re-run the float64 verification (`fojax.design.AbstractDesign.verify`): conditions
        a.–f. at `params`, the eigenvalues of 𝔸 in `region` and the region LMI at `X`."""
        return verify_unknown_input_design(self.structure, self.D, self.params, self.region, self.X,
                                           extra=carried_extra(self.report),
                                           balance=self.solver.get("balance"))[1]

    def __str__(self) -> str:
        o = self.observer
        return (
            f"unknown-input functional observer: q0 = {o.q0}, q1 = {o.q1}, l = "
            f"{o.num_unknown_inputs} unknown inputs, estimates q = {o.output_size} functions; "
            f"error poles in {self.region.describe()}\n{self.report}"
        )


def verify_unknown_input_design(s, D, params, region, X, *, extra=None, balance=None):
    r"""The matrices of `params` (eq. 3.110) and their float64 verification by
    `fojax.design.verify`: residuals of a.–f. (each relative to the norms of its own terms,
    `unknown_input_condition_scales`, as for the functional observer), the eigenvalues of
    𝔸, the region LMI at `X`, ``E⊥[E D] = 0`` recorded (``extra["Eperp [E D] residual"]``)
    and a.–f. in the unit-free frame (`unit_free_check`).

    With `balance` (``{"row_factors": d_l, "state_factors": d_r}`` of a ``balance=True``
    design) `s` is the unit-free structure and `D` the model's: a.–f. are checked on the
    model as given ($E = D_l^{-1}E_bD_r^{-1}$, …, $E^\perp = E^\perp_bD_l$, $T = T_bD_l$,
    the other matrices unchanged; the report's residuals) and in the unit-free frame (a
    named check). Returns the unit-free frame's matrices then."""
    D = np.asarray(D, float)
    if balance is None:
        so, Do, checks = s, D, tuple(c for c in (unit_free_check(s, D, params),) if c)
        mats = mo = unknown_input_observer_matrices(s, D, **params, xp=np)
    else:
        dl, dr = (np.asarray(balance[k], float) for k in ("row_factors", "state_factors"))
        Db = dl[:, None] * D
        mats = unknown_input_observer_matrices(s, Db, **params, xp=np)
        rel = relative_residual(*_residuals(s, Db, mats))
        checks = (("unit-free relative residual", rel, None if rel <= RESIDUAL_RTOL else (
            f"conditions a.-f. in the unit-free frame have relative residual {rel:.2e} > {RESIDUAL_RTOL:.0e}")),)
        so = model_structure(s, dl, dr)
        Do, mo = D, mats._replace(T=np.asarray(mats.T) * dl[None, :])
    res, scale, scales = _residuals(so, Do, mo)
    Ep = np.asarray(so.Eperp)
    extra = {**(extra or {}),
             "Eperp [E D] residual": float(np.abs(Ep @ np.hstack([np.asarray(so.E), Do])).max())
             if Ep.size else 0.0}
    report = verify(res, scale, unknown_input_error_dynamics(mats, xp=np), region, X, extra=extra, scales=scales,
                    checks=checks)
    return mats, report
