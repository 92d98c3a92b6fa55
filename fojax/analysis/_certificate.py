r"""LMI certificate of admissibility (thesis Theorem 2.1.3, Xu & Lam form)."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from .._errors import (
    DesignVerificationError,
    InputError,
    LMIInfeasibleError,
    SolverStoppedShortError,
)
from .._linalg import left_null_space
from ._common import as_pencil


@dataclass(frozen=True)
class AdmissibilityCertificate:
    r"""A verified certificate $P$ of admissibility of $(E, A)$.

    $E^TP = P^TE \succeq 0$ and $A^TP + P^TA \prec 0$, with $P = XE + S\Phi$ (see
    `admissibility_certificate`). All margins were recomputed in float64 from `P` and the
    original (un-normalised) $E$, $A$.

    **Fields:**

    - `P`: ``(n, n)`` certificate; `X` (``(n, n)``, $\succ 0$), `Phi`
      (``(n - rank E, n)``) and `S` (``(n, n - rank E)``, orthonormal basis of
      $\ker E^T$) are its parts.
    - `lyapunov_margin`: $-\lambda_{\max}(\mathrm{sym}(A^TP + P^TA)) / (\|A\|\|P\|)$,
      relative, $> 0$.
    - `lyapunov_max_eig`: $\lambda_{\max}(\mathrm{sym}(A^TP + P^TA))$, absolute.
    - `psd_min_eig`: $\lambda_{\min}(\mathrm{sym}(E^TP)) / (\|E\|\|P\|)$ (relative,
      $\ge -$ tolerance; it is $\approx 0$ whenever $E$ is singular).
    - `symmetry_residual`: $\|E^TP - P^TE\|_2 / (\|E\|\|P\|)$.
    - `x_min_eig`: $\lambda_{\min}(X)$.
    - `status`: the solver status (always ``"optimal"``, or ``"trivial"`` for
      ``n = 0``); `solver`: ``"SCS"``; `info`: iterations, solve time, solver warnings.
    """

    P: np.ndarray
    X: np.ndarray
    Phi: np.ndarray
    S: np.ndarray
    lyapunov_margin: float
    lyapunov_max_eig: float
    psd_min_eig: float
    symmetry_residual: float
    x_min_eig: float
    status: str
    solver: str = "SCS"
    info: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        return (
            f"AdmissibilityCertificate(status={self.status!r}, "
            f"lyapunov_margin={self.lyapunov_margin:.3e}, psd_min_eig={self.psd_min_eig:.1e}, "
            f"symmetry_residual={self.symmetry_residual:.1e}, n={self.P.shape[0]})"
        )


def _sym(M):
    return 0.5 * (M + M.T)


def admissibility_certificate(
    sys,
    A=None,
    *,
    verify_rtol: float = 1e-9,
    eps: float = 1e-8,
    max_iters: int = 200_000,
    tol: float | None = None,
    balance: bool = True,
) -> AdmissibilityCertificate:
    r"""Solve and verify the strict LMI certificate of admissibility (Theorem 2.1.3).

    Theorem 2.1.3 (Xu & Lam 2006, Thm 2.1 / Lemma 2.2): $(E, A)$ is regular, impulse-free
    and stable iff there is $P$ with

    $$E^TP = P^TE \succeq 0,\qquad A^TP + P^TA \prec 0.$$

    (The thesis prints the first condition as $EP_c^T = P_c^TE$, mixing the two dual
    forms (2.20)/(2.21); the statement above is the correct one.) The equality
    constraint is eliminated by the strict-LMI parameterisation
    $P = XE + S\Phi$ with $X = X^T \succ 0$, $\Phi$ free and $S$ an orthonormal basis of
    $\ker E^T$ (so $E^TP = E^TXE$). Because the LMI is homogeneous it is normalised as

    $$X \succeq I,\qquad \mathrm{sym}(A^TP + P^TA) \preceq -I,$$

    minimising $\mathrm{tr}X + \|\Phi\|_F^2$ (to keep the certificate well scaled), on the
    normalised pencil $(E/\|E\|, A/\|A\|)$ — a certificate for that pencil certifies
    $(E, A)$ too. Solved with cvxpy + SCS on the host (never inside ``jit``).

    **Acceptance.** Only solver status ``"optimal"`` is accepted; anything else
    raises with the status: ``"infeasible"`` `fojax.errors.LMIInfeasibleError`, any other
    (``"optimal_inaccurate"``, an iteration limit, a solver error)
    `fojax.errors.SolverStoppedShortError`. The solution is then re-checked in float64 against the
    original $E$, $A$: ``symmetry_residual <= verify_rtol``,
    ``psd_min_eig >= -verify_rtol``, ``lyapunov_margin >= verify_rtol`` and
    $\lambda_{\min}(X) > 0$ (definitions in `AdmissibilityCertificate`); a failure
    raises `fojax.errors.DesignVerificationError` with the numbers.

    Host-only (cvxpy/SCS).

    **Arguments:**

    - `sys`: a `fojax.DescriptorSystem`, or ``E`` with `A` given.
    - `verify_rtol`: relative verification tolerance (default ``1e-9``, far above float64
      rounding of the products, far below the normalised LMI margin of 1).
    - `eps`: SCS ``eps_abs = eps_rel`` (default ``1e-8``); `max_iters`: SCS iteration cap.
    - `tol`: rank threshold for $\ker E^T$ (fojax tolerance by default).

    **Returns:** an `AdmissibilityCertificate`. For ``n = 0`` a trivial certificate
    (empty matrices, status ``"trivial"``) is returned without calling the solver.

    **Raises:** `fojax.errors.LMIInfeasibleError`, `fojax.errors.SolverStoppedShortError`,
    `fojax.errors.DesignVerificationError`.
    """
    import cvxpy as cp

    p = as_pencil(sys, A, fname="admissibility_certificate", balance=balance)
    if p.dt is not None:
        raise InputError(
            f"admissibility_certificate certifies continuous-time admissibility (Theorem 2.1.3); this system is "
            f"discrete-time (dt = {p.dt:g}). Use fojax.analysis.is_admissible (regular, causal, |λ| < 1) for its verdict."
        )
    n = p.n
    if n == 0:
        z = np.zeros((0, 0))
        return AdmissibilityCertificate(z, z, z, z, np.inf, -np.inf, 0.0, 0.0, np.inf, "trivial")
    En, An = p.En, p.An
    S = left_null_space(En, tol).T  # (n, n - r), E^T S = 0
    k = S.shape[1]

    X = cp.Variable((n, n), symmetric=True)
    if k:
        Phi = cp.Variable((k, n))
        Pexpr = X @ En + S @ Phi
        obj = cp.trace(X) + cp.sum_squares(Phi)
    else:
        Phi = None
        Pexpr = X @ En
        obj = cp.trace(X)
    M = An.T @ Pexpr
    Msym = 0.5 * (M + M.T)
    I = np.eye(n)
    prob = cp.Problem(cp.Minimize(obj), [X - I >> 0, -Msym - I >> 0])
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            prob.solve(solver=cp.SCS, eps_abs=eps, eps_rel=eps, max_iters=max_iters)
        except cp.error.SolverError as err:
            raise SolverStoppedShortError(
                "admissibility (Xu-Lam)", "solver_error", {"solver": "SCS", "message": str(err)}
            ) from err
    info = {
        "solve_time": time.perf_counter() - t0,
        "warnings": [str(w.message) for w in caught],
    }
    stats = getattr(prob, "solver_stats", None)
    if stats is not None:
        info["iterations"] = getattr(stats, "num_iters", None)
    status = str(prob.status)
    if status != "optimal":
        info.update(solver="SCS", settings={"eps_abs": eps})
        if status == "infeasible":
            raise LMIInfeasibleError("admissibility (Xu-Lam)", status, info, hint=(
                "No certificate E^T P = P^T E >= 0, A^T P + P^T A < 0 exists: the pair (E, A) "
                "is not admissible (irregular, impulsive or unstable). "
                "Check fojax.structure_report(sys)."))
        raise SolverStoppedShortError("admissibility (Xu-Lam)", status, info, hint=(
            f"Here: raise max_iters (now {max_iters}), loosen eps (now {eps:.0e}), or rescale the "
            "model. If the pair is only marginally admissible, check fojax.structure_report(sys)."))
    Xv = np.asarray(X.value, dtype=float)
    Xv = _sym(Xv)
    Phiv = np.asarray(Phi.value, dtype=float) if Phi is not None else np.zeros((0, n))
    # Back from the balanced, normalised pencil (Dl E Dr / e, Dl A Dr / a) to (E, A):
    # P = Dl Pb Dr^-1 gives E^T P = e Dr^-1 (Eb^T Pb) Dr^-1 (a congruence, so the
    # conditions carry over), and P = X E + S Phi with X = Dl Xb Dl / e, S Phi = Dl Sb Phi_b Dr^-1.
    dl, dr = p.scaling.left, p.scaling.right
    e = float(np.linalg.norm(dl[:, None] * p.E * dr[None, :], 2)) or 1.0
    Xv = _sym(dl[:, None] * Xv * dl[None, :] / e)
    if k:
        S, R = np.linalg.qr(dl[:, None] * S)
        Phiv = (R @ Phiv) / dr[None, :]
    P = Xv @ p.E + S @ Phiv

    # float64 re-check on the ORIGINAL matrices.
    E, A_ = p.E, p.A
    nE = float(np.linalg.norm(E, 2))
    nA = float(np.linalg.norm(A_, 2))
    nP = float(np.linalg.norm(P, 2))
    EtP = E.T @ P
    sym_res = float(np.linalg.norm(EtP - EtP.T, 2)) / max(nE * nP, 1e-300)
    psd = float(np.linalg.eigvalsh(_sym(EtP))[0]) / max(nE * nP, 1e-300) if nE > 0 else 0.0
    lmax = float(np.linalg.eigvalsh(_sym(A_.T @ P + P.T @ A_))[-1])
    lmargin = -lmax / max(nA * nP, 1e-300)
    xmin = float(np.linalg.eigvalsh(Xv)[0])
    cert = AdmissibilityCertificate(
        P=P,
        X=Xv,
        Phi=Phiv,
        S=S,
        lyapunov_margin=lmargin,
        lyapunov_max_eig=lmax,
        psd_min_eig=psd,
        symmetry_residual=sym_res,
        x_min_eig=xmin,
        status=status,
        info=info,
    )
    failures = []
    if not sym_res <= verify_rtol:
        failures.append(
            f"symmetry residual ‖EᵀP − PᵀE‖/(‖E‖‖P‖) = {sym_res:.3e} > {verify_rtol:.1e}"
        )
    if not psd >= -verify_rtol:
        failures.append(f"λ_min(sym(EᵀP))/(‖E‖‖P‖) = {psd:.3e} < −{verify_rtol:.1e}")
    if not lmargin >= verify_rtol:
        failures.append(
            f"Lyapunov margin −λ_max(AᵀP + PᵀA)/(‖A‖‖P‖) = {lmargin:.3e} < {verify_rtol:.1e} "
            f"(λ_max = {lmax:.3e})"
        )
    if not xmin > 0:
        failures.append(f"λ_min(X) = {xmin:.3e} <= 0")
    if failures:
        raise DesignVerificationError(
            "admissibility certificate failed its float64 verification although SCS reported "
            "'optimal': " + "; ".join(failures) + ". The pair is at best marginally "
            "admissible at this scale; tighten eps= or rescale the model.",
            report=cert,
        )
    return cert
