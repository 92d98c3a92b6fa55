"""cvxpy on the host: building and solving region LMIs, strictly.

Only solver status ``optimal`` is accepted. Status ``infeasible`` (a certificate of
infeasibility) raises `fojax.errors.LMIInfeasibleError`; every other status (``optimal_inaccurate``,
an iteration limit, a solver error) raises `fojax.errors.SolverStoppedShortError`, both with the
status and solver statistics.
Every solution is re-verified in float64 by the caller, independently of the solver.

**Solvers.** ``solver="auto"`` (default) tries Clarabel and, when its status is not
``optimal``, SCS; ``"CLARABEL"`` or ``"SCS"`` use one solver. Both are installed with
cvxpy. Clarabel (an interior-point method) goes first because observer LMIs
are small but often need ill-conditioned certificates, which a first-order method such as
SCS reaches only after very many iterations (if at all: on the thesis example 4.1.3 with
disk(-2, 1) it stops at ``optimal_inaccurate`` with eps = 1e-7, and a bound X ⪯ 100·I makes
the problem infeasible), while Clarabel reaches ``optimal`` in about 20 iterations. SCS is run
with eps_abs = eps_rel = 1e-7 (SCS's own default, 1e-4, is too loose for
verification at 1e-8) and retried once with more iterations. Neither solver wins
everywhere: on §3.1.3's structure Clarabel stopped at ``optimal_inaccurate`` where SCS
reached ``optimal`` — hence "auto".

**Retries.** Clarabel runs with tolerances 1e-9; when it stops at ``optimal_inaccurate``
it is retried once with its own documented defaults (1e-8), as SCS is retried with more
iterations. Whether the tighter run meets 1e-9 depends on the last digits of the BLAS
kernel (on the minimum-gain LMI ``A_REP`` of ``tests/test_design.py`` Clarabel's primal
residual can stall just above 1e-9 under relative perturbations of 1e-15 of the data,
never at 1e-8). A solver error (numerical breakdown) is retried the same way. 1e-8 is ample: the
LMIs are strict by ``margin`` (1e-3) and every solution is re-verified in float64
(`fojax.design.verify`), so the solver's tolerance never decides what is returned. The
settings that produced a solution are in ``info["settings"]``, the refused attempts in
``info["retried_after"]``.

**Ctrl-C during an SCS solve.** SCS installs its own SIGINT handler while it runs and
then stops with status "interrupted", which cvxpy reports as a solver failure: the
interruption would become a `SolverStoppedShortError` (or the next attempt), and Python
(the ``fojax`` command, a notebook) would never see it. `solve` therefore runs SCS
through `_scs_solver`, which re-raises the SIGINT in Python (`signal.raise_signal`)
when SCS was interrupted: Ctrl-C ends the design as it does everywhere else.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np

from .._errors import LMI_FAILURES, LMIInfeasibleError, solver_failure, SolverStoppedShortError
from ._regions import AbstractRegion


if TYPE_CHECKING:  # cvxpy is imported where a problem is built: its import is slow
    import cvxpy as cp


#: SCS settings: tighter than SCS's defaults (1e-4), see the module docstring.
SCS_SETTINGS = dict(eps_abs=1e-7, eps_rel=1e-7, max_iters=20_000)
CLARABEL_SETTINGS = dict(tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9, max_iter=500)
#: Clarabel's retry after ``optimal_inaccurate``: its documented default tolerances (1e-8).
CLARABEL_RETRY = dict(tol_gap_abs=1e-8, tol_gap_rel=1e-8, tol_feas=1e-8, max_iter=500)
SCS_RETRY = dict(eps_abs=1e-6, eps_rel=1e-6, max_iters=40_000, acceleration_lookback=0)


def sym(M):
    return 0.5 * (M + M.T)


def region_lmi(region: AbstractRegion, X, Phi):
    """Chilali–Gahinet matrix ``L⊗X + M⊗Φᵀ + Mᵀ⊗Φ`` with ``Φ = X𝔸`` (cvxpy expression)."""
    import cvxpy as cp
    L, M = region.characteristic()
    out = cp.kron(L, X) + cp.kron(M, Phi.T) + cp.kron(M.T, Phi)
    return sym(out)


SOLVERS = ("AUTO", "CLARABEL", "SCS")
DEFAULT_SOLVER = "auto"


def check_solver(solver: str) -> str:
    s = str(solver).upper()
    if s not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    return s


_SCS_SOLVER = None


def _scs_solver():
    """cvxpy's SCS interface, except that a solve SCS stopped on SIGINT re-raises the
    signal in Python (see the module docstring). One instance, made on first use."""
    global _SCS_SOLVER
    if _SCS_SOLVER is None:
        import signal

        from cvxpy.reductions.solvers.conic_solvers.scs_conif import SCS

        class _SCS(SCS):
            def name(self):
                return "SCS (fojax)"  # cvxpy requires custom solvers to have their own name

            def solve_via_data(self, *args, **kwargs):
                results = super().solve_via_data(*args, **kwargs)
                if results["info"].get("status_val") == -5:  # SCS_SIGINT: interrupted by SIGINT
                    signal.raise_signal(signal.SIGINT)  # KeyboardInterrupt, unless ignored
                return results

        _SCS_SOLVER = _SCS()
    return _SCS_SOLVER


def solve(problem: cp.Problem, name: str, hint: str = "", solver: str = DEFAULT_SOLVER) -> dict:
    """Solve; unless the status is ``optimal``, raise `LMIInfeasibleError` (infeasibility
    shown) or `SolverStoppedShortError` (`fojax._errors.solver_failure`).

    Each solver gets a second run with looser settings after ``optimal_inaccurate``
    (`CLARABEL_RETRY`, `SCS_RETRY`; module docstring)."""
    import cvxpy as cp
    solver = check_solver(solver)
    if solver == "AUTO":
        try:
            return solve(problem, name, hint, "CLARABEL")
        except LMI_FAILURES as first:
            try:
                info = solve(problem, name, hint, "SCS")
            except LMI_FAILURES as second:
                both = {"clarabel": first.info, "scs": second.info}
                shown = [e for e in (first, second) if isinstance(e, LMIInfeasibleError)]
                if shown:  # one solver's certificate of infeasibility decides
                    raise LMIInfeasibleError(name, f"{first.status} (Clarabel), {second.status} (SCS)",
                                             both, hint) from None
                raise SolverStoppedShortError(
                    name, f"{first.status} (Clarabel), {second.status} (SCS)", both) from None
            info["fallback_from"] = {"solver": "CLARABEL", "status": first.status}
            return info
    info: dict = {"solver": solver}
    status = None
    attempts = (SCS_SETTINGS, SCS_RETRY) if solver == "SCS" else (CLARABEL_SETTINGS, CLARABEL_RETRY)
    refused = []
    for settings in attempts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                problem.solve(solver=_scs_solver() if solver == "SCS" else solver, **settings)
        except Exception as e:  # noqa: BLE001 - every solver failure becomes a typed error
            # a numerical breakdown (Clarabel's NumericalError/InsufficientProgress, a
            # cvxpy SolverError) is retried like optimal_inaccurate; so is any other
            # exception of the solver interface (SCS raises ValueError("ScsWork allocation
            # error!") on data it cannot hold), which must never reach the user untyped
            status = "solver_error"
            info.update(status=status, message=f"{type(e).__name__}: {e}", settings=dict(settings))
            refused.append({"status": status, "settings": dict(settings)})
            continue
        status = problem.status
        info.pop("message", None)
        stats = problem.solver_stats
        info.update(
            status=status,
            iterations=getattr(stats, "num_iters", None),
            solve_time=getattr(stats, "solve_time", None),
            settings=dict(settings),
        )
        if status == cp.OPTIMAL:
            if refused:
                info["retried_after"] = refused
            return info
        if status != cp.OPTIMAL_INACCURATE:
            break
        refused.append({"status": status, "settings": dict(settings)})
    if status == "solver_error":
        info.update(problem_size(problem))
    raise solver_failure(name, str(status), info, hint)


def problem_size(problem) -> dict:
    """Scalar variables, constraints and the largest absolute constant of a cvxpy problem
    (what a solver failure report needs: was the problem large, or its data extreme?)."""
    out: dict = {}
    try:
        m = problem.size_metrics
        out["variables"] = int(m.num_scalar_variables)
        out["constraints"] = int(m.num_scalar_eq_constr + m.num_scalar_leq_constr)
    except Exception:  # noqa: BLE001 - best effort, for the message only
        out["variables"] = out["constraints"] = -1
    big = 0.0
    for c in problem.constants():
        v = np.abs(np.asarray(c.value if not hasattr(c.value, "toarray") else c.value.toarray(), dtype=float))
        if v.size:
            big = max(big, float(np.nanmax(v)))
    out["data_magnitude"] = big
    return out


def describe_route(info: dict, objective: str | None = None) -> str:
    """One line on how an LMI solution was obtained, e.g. ``"min-gain problem, CLARABEL,
    status optimal at tol 1e-08 (retry after optimal_inaccurate at 1e-09)"``."""

    def tol(settings: dict) -> str:
        t = settings.get("tol_feas", settings.get("eps_abs"))
        return "?" if t is None else f"{t:.0e}"

    out = f"{objective} problem, " if objective else ""
    out += f"{info.get('solver')}, status {info.get('status')} at tol {tol(info.get('settings', {}))}"
    if info.get("retried_after"):
        out += " (retry after " + ", ".join(
            f"{r['status']} at {tol(r['settings'])}" for r in info["retried_after"]) + ")"
    if info.get("fallback_from"):
        out += f" (after {info['fallback_from']['status']} with {info['fallback_from']['solver']})"
    return out


def value(x) -> np.ndarray:
    v = x.value
    if v is None:
        raise SolverStoppedShortError("value", "no_solution", {})
    return np.asarray(v, dtype=float)
