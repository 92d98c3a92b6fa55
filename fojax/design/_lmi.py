r"""cvxpy on the host: building and solving region LMIs, strictly.

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

**Conic programs built directly.** `ConicLMI` holds an LMI program
$\min c^\top x + \|x_{\mathcal N}\|_2$ subject to $F_{0j} + \sum_i x_iF_{ij} \succeq 0$ for
every block $j$, with the affine map's coefficients $F_{ij}$ computed with NumPy (a
symmetric matrix variable $X$ enters through the orthonormal basis of `sym_basis`, so that
its coordinates are $\operatorname{svec}X$). `solve_conic` hands it to Clarabel without
cvxpy: each block is one PSD-triangle cone, $s_j = \operatorname{svec}(F_{0j}) - A_jx$ with
$A_j = -[\operatorname{svec}F_{1j}, \dots]$ (`svec`: the upper triangle by columns,
off-diagonal entries scaled by $\sqrt2$ — Clarabel's convention, under which
$\langle S, T\rangle = \operatorname{svec}S\cdot\operatorname{svec}T$), the norm term
one second-order cone. The statuses, the retry with `CLARABEL_RETRY` and the errors are
those of `solve`; `ConicLMI.to_cvxpy` gives the same program to cvxpy (for SCS).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple, TYPE_CHECKING

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

    def run(settings):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            problem.solve(solver=_scs_solver() if solver == "SCS" else solver, **settings)
        stats = problem.solver_stats
        return problem.status, getattr(stats, "num_iters", None), getattr(stats, "solve_time", None)

    attempts = (SCS_SETTINGS, SCS_RETRY) if solver == "SCS" else (CLARABEL_SETTINGS, CLARABEL_RETRY)
    return _attempts(run, attempts, name, hint, info, lambda: problem_size(problem))


def _attempts(run, attempts, name: str, hint: str, info: dict, size) -> dict:
    """Run ``run(settings) -> (status, iterations, solve_time)`` with each settings of
    `attempts` until the status is ``optimal`` (returns `info`) or not ``optimal_inaccurate``
    (raises, `fojax._errors.solver_failure`); a raised exception counts as ``solver_error``
    and is retried. ``size()`` describes the problem after a solver error."""
    status = None
    refused = []
    for settings in attempts:
        try:
            status, iterations, solve_time = run(settings)
        except Exception as e:  # noqa: BLE001 - every solver failure becomes a typed error
            # a numerical breakdown (Clarabel's NumericalError/InsufficientProgress, a
            # cvxpy SolverError) is retried like optimal_inaccurate; so is any other
            # exception of the solver interface (SCS raises ValueError("ScsWork allocation
            # error!") on data it cannot hold), which must never reach the user untyped
            status = "solver_error"
            info.update(status=status, message=f"{type(e).__name__}: {e}", settings=dict(settings))
            refused.append({"status": status, "settings": dict(settings)})
            continue
        info.pop("message", None)
        info.update(status=status, iterations=iterations, solve_time=solve_time, settings=dict(settings))
        if status == "optimal":
            if refused:
                info["retried_after"] = refused
            return info
        if status != "optimal_inaccurate":
            break
        refused.append({"status": status, "settings": dict(settings)})
    if status == "solver_error":
        info.update(size())
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


# --------------------------------------------------------------------------- direct conic programs


def svec(S: np.ndarray) -> np.ndarray:
    """``(..., m, m)`` → ``(..., m(m+1)/2)``: the upper triangle by columns, off-diagonal
    entries times √2 (Clarabel's PSD-triangle convention); `S` is symmetrized first."""
    S = np.asarray(S, dtype=float)
    r, c = np.tril_indices(S.shape[-1])  # (row i = c ≤ column j = r), by columns
    w = np.where(r == c, 1.0, np.sqrt(2.0))
    return 0.5 * (S[..., c, r] + S[..., r, c]) * w


def sym_basis(q: int) -> np.ndarray:
    """``(q(q+1)/2, q, q)``: the symmetric matrices ``B_i`` with ``svec(Σ x_i B_i) = x``."""
    r, c = np.tril_indices(q)
    B = np.zeros((r.size, q, q))
    k = np.arange(r.size)
    v = np.where(r == c, 1.0, np.sqrt(0.5))
    B[k, c, r] = v
    B[k, r, c] = v
    return B


def smat(x: np.ndarray, q: int) -> np.ndarray:
    """The inverse of `svec` for one symmetric ``q × q`` matrix."""
    return np.tensordot(np.asarray(x, dtype=float), sym_basis(q), axes=1)


def kron_batch(L: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``kron(L, X_k)`` for every ``X_k`` of a batch ``(p, q, q)``."""
    p, q = X.shape[0], X.shape[-1]
    m = L.shape[0]
    return np.einsum("ab,pij->paibj", L, X).reshape(p, m * q, m * q)


def region_lmi_batch(L: np.ndarray, M: np.ndarray, X: np.ndarray, Phi: np.ndarray) -> np.ndarray:
    """`region_lmi` of the characteristic matrices ``(L, M)`` for batches ``X, Φ`` of shape
    ``(p, q, q)`` in NumPy: the coefficients of an LMI linear in its variables."""
    out = kron_batch(L, X) + kron_batch(M, np.swapaxes(Phi, -1, -2)) + kron_batch(M.T, Phi)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


class ConicLMI(NamedTuple):
    r"""``min c·x + ‖x[norm]‖₂`` subject to ``F0 + Σ_i x_i F[i] ⪰ 0`` for every block
    ``(F0, F)`` (``F0`` of shape ``(m, m)``, ``F`` of shape ``(len(x), m, m)``, symmetric).
    ``norm=None``: no norm term."""

    c: np.ndarray
    blocks: tuple
    norm: np.ndarray | None = None

    def feasibility(self) -> ConicLMI:
        """The same constraints with the objective 0."""
        return ConicLMI(np.zeros_like(self.c), self.blocks)

    @property
    def sizes(self) -> list[int]:
        return [F0.shape[0] for F0, _ in self.blocks]

    def to_cvxpy(self):
        """``(x, objective, constraints)`` of the same program in cvxpy."""
        import cvxpy as cp
        x = cp.Variable(self.c.size)
        cons = []
        for F0, F in self.blocks:
            m = F0.shape[0]
            M = cp.reshape(F.reshape(F.shape[0], m * m).T @ x, (m, m), order="C") + F0
            cons.append(0.5 * (M + M.T) >> 0)
        obj = self.c @ x + (cp.norm(x[self.norm], 2) if self.norm is not None else 0)
        return x, obj, cons


#: Added to the settings of a direct Clarabel solve: one thread (the LMIs are small; a second
#: thread costs more CPU than it saves time).
CLARABEL_DIRECT = dict(max_threads=1)
#: cvxpy's reading of Clarabel's statuses (cvxpy.reductions.solvers.conic_solvers.clarabel_conif)
CLARABEL_STATUS = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate", "PrimalInfeasible": "infeasible",
                   "AlmostPrimalInfeasible": "infeasible_inaccurate", "DualInfeasible": "unbounded",
                   "AlmostDualInfeasible": "unbounded_inaccurate", "MaxIterations": "user_limit",
                   "MaxTime": "user_limit"}


def clarabel_data(prob: ConicLMI):
    """``(P, q, A, b, cones)`` of `prob` for ``clarabel.DefaultSolver`` (variables ``x``, then
    the norm's bound ``t`` if any)."""
    import clarabel
    import scipy.sparse as sp
    p = prob.c.size
    nt = 0 if prob.norm is None else 1
    idx = np.zeros(0, dtype=int) if prob.norm is None else np.asarray(prob.norm).ravel()
    cones = [clarabel.SecondOrderConeT(1 + idx.size)] if nt else []
    rows = (1 + idx.size if nt else 0) + sum(F0.shape[0] * (F0.shape[0] + 1) // 2 for F0, _ in prob.blocks)
    A = np.zeros((rows, p + nt))
    b = np.zeros(rows)
    if nt:  # (t, x[norm]) in the second-order cone
        A[0, p] = -1.0
        A[np.arange(1, 1 + idx.size), idx] = -1.0
    r = 1 + idx.size if nt else 0
    for F0, F in prob.blocks:
        m = F0.shape[0] * (F0.shape[0] + 1) // 2
        A[r:r + m, :p] = -svec(F).T
        b[r:r + m] = svec(F0)
        cones.append(clarabel.PSDTriangleConeT(F0.shape[0]))
        r += m
    q = np.concatenate([prob.c, np.ones(nt)])
    return sp.csc_array((p + nt, p + nt)), q, sp.csc_array(A), b, cones


def solve_conic(prob: ConicLMI, name: str, hint: str = "") -> tuple[np.ndarray, dict]:
    """Solve `prob` with Clarabel, directly; ``(x, info)`` like `solve` (same statuses, retry
    and errors)."""
    import clarabel
    data = clarabel_data(prob)
    info: dict = {"solver": "CLARABEL", "interface": "direct"}
    out: dict = {}

    def run(settings):
        opts = clarabel.DefaultSettings()
        opts.verbose = False
        for k, v in {**settings, **CLARABEL_DIRECT}.items():
            setattr(opts, k, v)
        sol = clarabel.DefaultSolver(*data, opts).solve()
        if str(sol.status) not in CLARABEL_STATUS:  # NumericalError, InsufficientProgress: retried
            raise RuntimeError(f"Clarabel stopped with status {sol.status}")
        status = CLARABEL_STATUS[str(sol.status)]
        out["x"] = np.asarray(sol.x, dtype=float)[:prob.c.size]
        return status, sol.iterations, sol.solve_time

    _attempts(run, (CLARABEL_SETTINGS, CLARABEL_RETRY), name, hint, info, lambda: {
        "variables": int(prob.c.size), "constraints": int(data[2].shape[0]),
        "data_magnitude": float(max(np.abs(data[2].data).max(initial=0.0), np.abs(data[3]).max(initial=0.0)))})
    return out["x"], info
