"""Typed errors raised by fojax.

Every error carries the numbers that made the check fail, so that a caller can
inspect them programmatically, and a message that names the offending matrix
(or condition) and says what to change.
"""

from __future__ import annotations

import functools
from typing import Any


class FojaxError(Exception):
    """Base class of every error raised on purpose by fojax."""


# --------------------------------------------------------------------------- input


class InputError(FojaxError, ValueError):
    """Bad user input (shape, dtype, value). Subclass of `ValueError`."""


class ShapeError(InputError):
    """A matrix or vector has the wrong shape.

    Attributes `name`, `expected` and `actual` hold what was checked.
    """

    def __init__(self, name: str, expected: Any, actual: Any, hint: str = ""):
        self.name = name
        self.expected = expected
        self.actual = actual
        msg = f"{name} has shape {actual}, expected {expected}."
        if hint:
            msg += " " + hint
        super().__init__(msg)


class NonFiniteError(InputError):
    """A matrix contains NaN or infinite entries."""

    def __init__(self, name: str, count: int, first_index: tuple[int, ...] | None = None):
        self.name = name
        self.count = count
        self.first_index = first_index
        where = f" (first at index {first_index})" if first_index is not None else ""
        super().__init__(
            f"{name} contains {count} non-finite (NaN or inf) entries{where}; "
            "every matrix entry must be a finite number."
        )


class Float64RequiredError(InputError):
    """fojax computes in float64 and refuses to silently return float32 results."""


class IrregularSystemError(InputError):
    """The pencil sE - A is singular for every s (no unique solution exists)."""


class NumericallyUndecidableError(InputError):
    """Whether the pencil sE - A is regular cannot be decided at the rank tolerance: a
    singular value that decides it is within a small factor of the tolerance, and two
    algorithms (fojax's orthogonal deflation and SLICOT AG08BD) give different verdicts.

    Attributes `tol` (the tolerance), `singular_value` (fojax's decision closest to it),
    `deflation_regular` and `ag08bd_regular` (the two verdicts), `normal_rank` (AG08BD's).
    """

    def __init__(self, tol: float, singular_value: float, deflation_regular: bool, ag08bd_regular: bool,
                 normal_rank: int):
        self.tol = tol
        self.singular_value = singular_value
        self.deflation_regular = deflation_regular
        self.ag08bd_regular = ag08bd_regular
        self.normal_rank = normal_rank
        verdict = {True: "regular", False: "singular"}
        super().__init__(
            f"the regularity of the pencil sE - A is numerically undecidable at tolerance {tol:.1e}: "
            f"a deciding singular value is {singular_value:.2e} (of the balanced pencil with "
            f"‖E‖ = ‖A‖ = 1), and fojax's deflation calls the pencil {verdict[deflation_regular]} while "
            f"SLICOT AG08BD calls it {verdict[ag08bd_regular]} (normal rank {normal_rank}). The pencil is "
            f"within about {singular_value:.0e} of a pencil with the other verdict. Decide with an explicit "
            "tol= (larger: treat that singular value as zero; smaller: as nonzero), with balance=False when "
            "the entries that balancing scales up are round-off of the data as given, or check the model for "
            "an equation that is nearly a combination of others."
        )


class ImpulsiveSystemError(InputError):
    """The system is regular but not impulse-free (index > 1)."""


class DataRangeError(InputError):
    """Matrix entries too large or too small for the LMI solvers (units far from 1).

    Attributes `name` (the matrix), `magnitude` (its largest absolute entry) and `bounds`
    (the accepted range of that magnitude).
    """

    def __init__(self, name: str, magnitude: float, bounds: tuple[float, float], fname: str = ""):
        self.name = name
        self.magnitude = magnitude
        self.bounds = bounds
        where = f"{fname}: " if fname else ""
        super().__init__(
            f"{where}the largest entry of {name} has magnitude {magnitude:.3e}, outside the range "
            f"[{bounds[0]:.1e}, {bounds[1]:.1e}] that the LMI solvers (Clarabel/SCS, double "
            "precision with absolute tolerances near 1e-9) can represent: products of such "
            "entries overflow or vanish, and a solver status would mean nothing. Rescale the "
            f"model: choose units in which the entries of {name} are within a few orders of "
            "magnitude of 1 (e.g. kPa instead of Pa, or divide an equation's row of E, A and B "
            "by a common factor), design, and convert the estimates back."
        )


class InconsistentInitialConditionError(InputError):
    """x0 violates the algebraic constraints and strict consistency was requested."""

    def __init__(self, residual: float, tol: float):
        self.residual = residual
        self.tol = tol
        super().__init__(
            f"x0 violates the algebraic constraints by {residual:.3e} (tolerance {tol:.1e}). "
            "Pass a consistent x0, or call with strict=False to project x0 onto the "
            "constraint set (the projection distance is reported in Solution.stats)."
        )


class RegionError(InputError):
    """An LMI region was specified with invalid parameters."""


# --------------------------------------------------------------------------- design


class ExistenceConditionError(FojaxError, ValueError):
    """A necessary condition for the existence of the requested observer fails.

    Attributes:
        condition: short name of the failing condition (e.g. ``"functional observability"``).
        lhs, rhs: the two numbers compared (usually ranks), when applicable.
        suggestion: what the user can change.
    """

    def __init__(
        self,
        condition: str,
        detail: str,
        suggestion: str,
        lhs: Any = None,
        rhs: Any = None,
    ):
        self.condition = condition
        self.detail = detail
        self.suggestion = suggestion
        self.lhs = lhs
        self.rhs = rhs
        super().__init__(f"{condition} fails: {detail} {suggestion}")


class FunctionalObservabilityError(ExistenceConditionError):
    """Assumption 1: rank [L; E; E⊥A; C] != rank [E; E⊥A; C]."""


class RankConditionError(ExistenceConditionError):
    """A rank condition of the parameterization fails (rank [Σ; TA] or rank [Σ; L])."""


class DetectabilityError(ExistenceConditionError):
    """The pair (𝔸2, 𝔸1) is not detectable (Lemma 8 / Remark 3)."""


class ImpulseObservabilityError(ExistenceConditionError):
    """Assumption 2 (Takagi–Sugeno): rank [E; E⊥A_i; C] != n for some rule."""


class StabilizabilityError(ExistenceConditionError):
    """No state feedback ``u = Lx`` makes ``(E, A + BL)`` admissible (with the requested
    pole region): the system is not impulse controllable, or a finite mode that no
    feedback can move lies outside the region (uncontrollable modes in `lhs`)."""


class LMIInfeasibleError(FojaxError, RuntimeError):
    """The LMI was shown infeasible: a solver returned status ``"infeasible"`` (a
    certificate of infeasibility), or a route without a solver proved that no solution
    exists (e.g. no stabilizing Riccati solution).

    A solver that stops short of the required accuracy raises `SolverStoppedShortError`
    instead; catch both with ``except LMI_FAILURES``.

    Attributes:
        status: the solver status string (e.g. ``"infeasible"``).
        problem: a short name of the LMI that was solved.
        info: extra numbers (solver name, iterations, residuals) when available.
    """

    def __init__(self, problem: str, status: str, info: dict | None = None, hint: str = ""):
        self.problem = problem
        self.status = status
        self.info = dict(info or {})
        msg = f"LMI '{problem}' was not solved: solver status '{status}'."
        if hint:
            msg += " " + hint
        super().__init__(msg)


class SolverStoppedShortError(FojaxError, RuntimeError):
    """The LMI solver stopped short of the accuracy fojax requires (status
    ``"optimal_inaccurate"``, an iteration limit, a numerical breakdown) without showing
    the LMI infeasible. fojax never accepts such a solution.

    Attributes:
        status: the solver status string (for ``solver="auto"``, one per solver).
        problem: a short name of the LMI that was solved.
        info: the solver's numbers (iterations, solve time, tolerances; per solver).
        tried_solvers: the solvers that were run.
        balanced_error: the error of the design on the unit-free model, when it was tried
            next (``balance=None``) and failed too.
    """

    def __init__(self, problem: str, status: str, info: dict | None = None, hint: str = "",
                 balanced_error: BaseException | None = None):
        self.problem = problem
        self.status = status
        self.info = dict(info or {})
        self.tried_solvers = _solvers_in(self.info)
        self.balanced_error = balanced_error
        runs = "; ".join(_describe_run(k, v) for k, v in _runs_in(self.info))
        msg = (f"LMI '{problem}' was not solved: the solver stopped short of the accuracy fojax requires "
               f"(status '{status}'{'; ' + runs if runs else ''}). This does not show that the LMI is "
               "infeasible. Try: ")
        tries = []
        if len(self.tried_solvers) < 2:
            tries.append("another solver (solver='CLARABEL' or 'SCS')")
        if balanced_error is None:
            tries.append("balance=True (the design on the unit-free model)")
        tries += ["a looser region (a larger disk or sector, a half-plane further right), which gives "
                  "the solver a better conditioned problem"]
        msg += ", ".join(tries) + "."
        if balanced_error is not None:
            msg += (f" The design on the unit-free model (balance=True) was tried too: "
                    f"{type(balanced_error).__name__}: {balanced_error}")
        if hint:
            msg += " " + hint
        super().__init__(msg)


def _runs_in(info: dict) -> list:
    """``(solver, info)`` pairs of one solver's info or of ``{"clarabel": ..., "scs": ...}``."""
    if "solver" in info or "status" in info:
        return [(str(info.get("solver", "solver")), info)]
    return [(k, v) for k, v in info.items() if isinstance(v, dict)]


def _solvers_in(info: dict) -> list:
    return [k.upper() for k, _ in _runs_in(info)]


def _describe_run(name: str, info: dict) -> str:
    settings = info.get("settings") or {}
    tol = settings.get("tol_feas", settings.get("eps_abs"))
    parts = [f"{name.upper()}: {info.get('status', '?')}"]
    if info.get("iterations") is not None:
        parts.append(f"{info['iterations']} iterations")
    if tol is not None:
        parts.append(f"tolerance {tol:.0e}")
    if info.get("solve_time") is not None:
        parts.append(f"{float(info['solve_time']):.2g} s")
    if info.get("message"):
        parts.append(str(info["message"]))
    if info.get("variables") is not None:
        parts.append(f"problem of {info['variables']} scalar variables, {info['constraints']} constraints, "
                     f"largest data entry {float(info['data_magnitude']):.1e}")
    return ", ".join(parts)


#: Every error of an LMI solve that returned no accepted solution (``except LMI_FAILURES``).
LMI_FAILURES = (LMIInfeasibleError, SolverStoppedShortError)

#: Solver statuses that show infeasibility (a certificate of primal infeasibility).
INFEASIBLE_STATUSES = ("infeasible",)


def solver_failure(problem: str, status: str, info: dict | None = None, hint: str = ""):
    """The typed error of an LMI solve that ended with `status` (not ``"optimal"``):
    `LMIInfeasibleError` when the status shows infeasibility (`INFEASIBLE_STATUSES`), else
    `SolverStoppedShortError`. `hint` (what infeasibility means for the caller's problem and
    what to change) is given to the first only: a solver that stopped short showed nothing
    about the problem, and its error says what to try instead."""
    if str(status) in INFEASIBLE_STATUSES:
        return LMIInfeasibleError(problem, str(status), info, hint)
    return SolverStoppedShortError(problem, str(status), info)


def combined_failure(problem: str, status: str, errors, info: dict | None = None, hint: str = ""):
    """The typed error when every attempt of a fallback ladder at one problem failed with
    `errors` (`LMI_FAILURES`): `LMIInfeasibleError` if one of them showed infeasibility
    (the attempts differ in objective, preconditioning or solver, not in the feasible set),
    else `SolverStoppedShortError`."""
    if any(isinstance(e, LMIInfeasibleError) for e in errors):
        return LMIInfeasibleError(problem, status, info, hint)
    return SolverStoppedShortError(problem, status, info)


class DesignVerificationError(FojaxError, RuntimeError):
    """A design failed its float64 verification (residuals, eigenvalues or LMI margin).

    Attribute `report` holds the full verification report.
    """

    def __init__(self, message: str, report: Any = None):
        self.report = report
        super().__init__(message)


class AlgebraicLoopError(InputError):
    """A feedback ``u = ẑ + u_r`` with a direct feedthrough ``ẑ = ... + D u`` cannot be
    solved for ``u`` because ``I - D`` is singular (ill-posed algebraic loop)."""


class ConfigError(InputError):
    """A configuration file is malformed. The message names the file and the key."""

    def __init__(self, file: str | None, key: str, message: str):
        self.file = file
        self.key = key
        where = f"{file}: " if file else ""
        super().__init__(f"{where}[{key}] {message}")


class UnsafePathError(InputError):
    """A file would be written outside the results folder its path was built from
    (a name holding ``..`` or a path separator, or a symlink leading out of the folder).

    Attributes `path` (as given), `folder` (the results folder) and `resolved` (where the
    file would have landed).
    """

    def __init__(self, path: Any, folder: Any, resolved: Any):
        self.path = path
        self.folder = folder
        self.resolved = resolved
        super().__init__(
            f"refusing to write {path}: it resolves to {resolved}, outside the results folder "
            f"{folder}; fojax never writes outside the folder you chose. Use a plain file name "
            "(letters, digits, '.', '_', '-') for every name that becomes a file."
        )


class DistributedError(FojaxError, RuntimeError):
    """A multi-process run (`jax.distributed.initialize`) failed on another process, or
    the processes were not given the same inputs.

    Raised on every process that is still alive: the message says which process and what
    the runtime reported (a collective that lost its peer, a heartbeat timeout), and how
    to continue (restart every process; ``fojax study --resume FOLDER``)."""


#: The keywords a stepper object replaced (``simulate``, ``run_study``, ``tune``, ``SimConfig``)
#: and what to pass instead; `removed_keywords` turns them into a `TypeError` naming it.
REMOVED_KEYWORDS = {
    "method": "stepper=fojax.Auto() | fojax.Exact() | fojax.Exponential() | fojax.Diffrax(...)",
    "solver": "stepper=fojax.Diffrax(solver) (or fojax.Auto(diffrax=fojax.Diffrax(solver)))",
    "rtol": "stepper=fojax.Diffrax(rtol=...) (or fojax.Auto(diffrax=fojax.Diffrax(rtol=...)))",
    "atol": "stepper=fojax.Diffrax(atol=...) (or fojax.Auto(diffrax=fojax.Diffrax(atol=...)))",
    "max_steps": "stepper=fojax.Diffrax(max_steps=...) (or fojax.Auto(diffrax=fojax.Diffrax(max_steps=...)))",
}


def removed_keywords(fn, who: str | None = None):
    """`fn`, raising `TypeError` when called with a keyword of `REMOVED_KEYWORDS`; the message
    names the stepper to pass instead."""
    name = who or fn.__name__

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        bad = [k for k in REMOVED_KEYWORDS if k in kwargs]
        if bad:
            raise TypeError(
                f"{name}() got the removed keyword(s) {', '.join(k + '=' for k in bad)}; the stepper object "
                "replaces them: " + "; ".join(f"instead of {k}= pass {REMOVED_KEYWORDS[k]}" for k in bad) + "."
            )
        return fn(*args, **kwargs)

    return wrapper
