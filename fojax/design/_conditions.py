"""Existence conditions of functional observers, checked before any LMI, and the default R."""

from __future__ import annotations

import numpy as np

from .._errors import (
    DataRangeError,
    DetectabilityError,
    FunctionalObservabilityError,
    ImpulsiveSystemError,
    IrregularSystemError,
    RankConditionError,
)
from .._linalg import canonical_row_space, rank, RANK_RTOL
from ._parameterization import FunctionalObserverStructure, observer_structure, pieces
from ._regions import AbstractRegion


#: Tolerance on the relative residual of the solvability condition U(I - V⁺V) = 0.
SOLVABILITY_RTOL = 1e-9


def gamma_matrix(E, A, C, Eperp) -> np.ndarray:
    """Γ = [E; E⊥A; C] (host)."""
    E, A, C, Ep = (np.asarray(x, dtype=float) for x in (E, A, C, Eperp))
    return np.vstack([E, Ep @ A, C])


def require_equal_rank(condition: str, lhs: int, rhs: int, detail: str, fix: str) -> None:
    """`RankConditionError` (``"<condition> fails: <detail> <fix>"``, with `lhs`, `rhs`) unless
    the two compared ranks (or orders) `lhs` and `rhs` are equal."""
    if lhs != rhs:
        raise RankConditionError(condition, detail, fix, lhs=lhs, rhs=rhs)


def check_order(R, q0: int | None) -> None:
    """A given `q0` must be the number of rows of the given `R` (the observer order)."""
    if q0 is not None:
        require_equal_rank("observer order", q0, R.shape[0], f"q0 = {q0} but R has {R.shape[0]} rows.",
                           "Give either R or q0.")


def check_regular(E, A, *, fname: str, what: str = "the plant") -> None:
    r"""Refuse a singular pencil before any LMI: `fojax.errors.IrregularSystemError` with the numbers.

    The decision is `fojax.analysis.is_regular`'s (the orthogonal deflation of the
    normalised pencil $(E/\|E\|, A/\|A\|)$ with the fojax rank rule), so design and
    analysis give the same verdict on the same data. The thesis's observers assume a
    regular plant (§3.1: "we assume that system (3.1) is regular"): for a singular pencil
    $\det(sE - A) \equiv 0$, the solutions $x$ are not unique, $z = Lx$ is not a function
    of $(u, y)$, and a "verified" observer would certify error dynamics of a system that
    does not determine what it estimates. The error has attributes `property`
    (``"regularity"``), `detail` (the failed rank decision with the singular value and
    the threshold) and `fname`.
    """
    from ..analysis._common import as_pencil, deflate

    d = deflate(as_pencil(np.asarray(E, dtype=float), np.asarray(A, dtype=float), fname=fname), None)
    if d.failed is None:
        return
    err = IrregularSystemError(
        f"{fname}: {what} is not regular: the pencil sE - A is singular (det(sE - A) = 0 for "
        f"every s; fojax.analysis.is_regular is False): {d.failed}, on the pencil normalised "
        "to (E/‖E‖, A/‖A‖). The observer theory (thesis §3.1) assumes a regular plant: its "
        "solutions x are not unique, so z = Lx is not determined by u and y and no observer "
        "can be verified. Fix the model (a missing or duplicated equation, or a state that "
        "appears in no equation, typically causes this); fojax.structure_report shows the "
        "structure."
    )
    err.property, err.detail, err.fname = "regularity", d.failed, fname
    raise err


#: The largest absolute entry of every non-zero design matrix must lie in
#: ``[DATA_RANGE[0], DATA_RANGE[1]] = [2^-100, 2^100]`` (about 8e-31 to 1.3e30).
#: Outside it, the region LMIs (whose coefficients are products of two or three such
#: entries) leave the range where double precision with the solvers' absolute tolerances
#: (~1e-9) means anything: relative residuals of 1e-299 "verify", rank decisions go wrong
#: and the solvers fail to allocate. Inside the range, mixed units can
#: still make a design fail (a typed RankConditionError/DesignVerificationError), but the
#: per-condition verification never returns a wrong observer.
DATA_RANGE = (2.0**-100, 2.0**100)


def check_data_range(blocks: dict, *, fname: str) -> None:
    """`fojax.errors.DataRangeError` when a non-zero matrix has its largest entry outside `DATA_RANGE`.

    `blocks` maps names (``"E"``, ``"A"``, ...) to arrays; empty and all-zero matrices are
    skipped (a zero ``B`` or ``A`` is legitimate).
    """
    lo, hi = DATA_RANGE
    for name, M in blocks.items():
        M = np.asarray(M, dtype=float)
        if M.size == 0:
            continue
        big = float(np.max(np.abs(M)))
        if big != 0.0 and not (lo <= big <= hi):
            raise DataRangeError(name, big, DATA_RANGE, fname)


def check_impulse_free(E, A, *, fname: str, what: str = "the closed loop (E, A + BL)") -> None:
    r"""Refuse an impulsive (index > 1) regular pencil: `fojax.errors.ImpulsiveSystemError`.

    Regularity first (`check_regular`); then `fojax.analysis.nilpotency_index` decides
    (index $\le 1$ is impulse-free, the same decision as `fojax.analysis.is_impulse_free`).
    The message reports the index and `fojax.analysis.impulse_free_margin`
    ($\sigma_{\min}(U_2^\top A V_2)$, relative to $\|A\|_2$) against ``RANK_RTOL``.
    Attributes `property` (``"impulse-freeness"``), `index`, `margin`, `tol`.
    """
    from ..analysis import impulse_free_margin, nilpotency_index

    E, A = np.asarray(E, dtype=float), np.asarray(A, dtype=float)
    check_regular(E, A, fname=fname, what=what)
    nu = nilpotency_index(E, A)
    if nu <= 1:
        return
    nA = float(np.linalg.norm(A, 2)) or 1.0
    margin = float(impulse_free_margin(E, A)) / nA
    err = ImpulsiveSystemError(
        f"{fname}: {what} is impulsive: nilpotency index {nu} > 1 "
        f"(fojax.analysis.is_impulse_free is False; impulse-free margin "
        f"σmin(U2ᵀ A V2)/‖A‖ = {margin:.2e}, threshold {RANK_RTOL:.0e}). Its response has "
        "impulses and derivatives of the inputs, and fojax's simulation and the thesis's "
        "admissibility (regular, impulse-free, stable) need index <= 1. Choose a feedback "
        "that makes it impulse-free (omit L to let fojax.design_state_feedback design one), "
        "or change the model."
    )
    err.property, err.index, err.margin, err.tol = "impulse-freeness", nu, margin, RANK_RTOL
    raise err


def check_functional_observability(E, A, C, L, Eperp=None, *, what: str = "L", D=None,
                                   output_only: bool = False) -> None:
    """Assumption 1: rank [L; E; E⊥A; C] = rank [E; E⊥A; C]; raises with a suggestion.

    The ranks are `fojax.analysis.functional_rank_pair`'s (blocks normalised by their
    norms, the fojax rank rule), so this check and `fojax.analysis.is_functionally_observable`
    cannot disagree. `Eperp` is accepted for compatibility and ignored: the annihilator is
    the left null space of ``E`` (of ``[E D]`` when `D` is given); with `output_only`
    ``Γ = [E; C]`` (the Takagi–Sugeno observer).
    """
    from ..analysis._observability import functional_rank_pair

    r1, r0 = functional_rank_pair(E, A, C, np.asarray(L, float), D=D, output_only=output_only)
    if r1 != r0:
        G = "[E; C]" if output_only else "[E; E⊥A; C]"
        raise FunctionalObservabilityError(
            "functional observability (Assumption 1)",
            f"rank [{what}; {G[1:-1]}] = {r1} but rank {G} = {r0}: the functional "
            f"z = {what} x is not determined by the measured signals and the constraints.",
            f"Estimate another functional (rows of L in the row space of {G}), or "
            "add outputs (rows of C) that measure the missing directions.",
            lhs=r1,
            rhs=r0,
        )


#: Largest ``l + n`` for which the structure's rank decisions and a design made on the data as
#: given are also taken in the unit-free frame (`unit_free_structure`;
#: `fojax.analysis.unit_scaling` costs a least-squares solve of size ``l + n`` per model).
UNIT_FREE_CHECK_MAX = 200


def unit_free_structure(s: FunctionalObserverStructure, *, orthonormal: bool = False):
    r"""``(sb, d_l, d_r)``: the structure `s` in the unit-free frame of
    `fojax.analysis.unit_scaling` ($E_b = D_lED_r$, $A_b = D_lAD_r$, $B_b = D_lB$,
    $C_b = CD_r$, $L_b = LD_r$, $R_b = RD_r$, $E^\perp_b = E^\perp D_l^{-1}$: still
    $E^\perp_bE_b = 0$, and the same measured signal $w$), or ``None`` when the model is
    larger than `UNIT_FREE_CHECK_MAX` or has rules (Takagi–Sugeno: not checked;
    ``tests/test_unit_invariance.py`` checks such designs against every frozen rule's
    plant). With `orthonormal` $E^\perp_b$ is
    replaced by an orthonormal basis of its rows (the same row space, so the same rank
    conditions; for rank decisions, not for mapping parameters)."""
    from ..analysis._balance import scale_model, unit_scaling

    E, A, B, C, L = (np.asarray(x, dtype=float) for x in (s.E, s.A, s.B, s.C, s.L))
    if A.ndim != 2 or E.shape[0] + E.shape[1] > UNIT_FREE_CHECK_MAX or getattr(s, "num_rules", 1) > 1:
        return None
    dl, dr = unit_scaling(E, A, B, C)
    Epb = np.asarray(s.Eperp) / dl[None, :]
    if orthonormal and Epb.size:
        Epb = np.linalg.svd(Epb, full_matrices=False)[2][: Epb.shape[0]]
    sb = observer_structure(*scale_model(dl, dr, E, A, B, C), L * dr, np.asarray(s.R) * dr, q1=s.q1, psi=s.psi,
                            Eperp=Epb)
    return sb, dl, dr


def check_structure(s: FunctionalObserverStructure) -> None:
    """Rank conditions of the parameterization for a given R (host).

    The rank decisions are taken in the unit-free frame (`unit_free_structure`, models with
    ``l + n ≤ UNIT_FREE_CHECK_MAX``): the conditions are statements about row spaces, which
    diagonal changes of units leave unchanged, but fojax's relative rank rule on the data as
    given is not (on a model with rows and states rescaled by 1e-3…1e3 it can decide
    rank Γ one too low)."""
    uf = unit_free_structure(s, orthonormal=True)
    if uf is not None:
        s = uf[0]
    n = s.n
    As = np.asarray(s.rules_A())
    Ep, C, E, R, L = (np.asarray(x) for x in (s.Eperp, s.C, s.E, s.R, s.L))
    Psi = np.vstack([Ep @ As[0], C])
    Gam = np.vstack([E, Psi])
    rR = rank(R)
    require_equal_rank("full row rank of R", rR, R.shape[0], f"R is {R.shape[0]} x {n} but has rank {rR}.",
                       "Remove dependent rows of R (the observer order q0 is the number of rows of R).")
    rG, rRG = rank(Gam), rank(np.vstack([R, Gam]))
    require_equal_rank("rank [R; Γ] = rank Γ", rRG, rG,
                       f"rank [R; E; Ψ] = {rRG} but rank [E; Ψ] = {rG}: some rows of R are not in the row "
                       "space of Γ = [E; Ψ], so T E + K Ψ = R has no solution.",
                       "Choose R with rows in the row space of [E; E⊥A; C] (or let fojax choose R).")
    Sig = np.vstack([R, Psi])
    rS, rSL = rank(Sig), rank(np.vstack([Sig, L]))
    require_equal_rank("rank [Σ; L] = rank Σ", rSL, rS,
                       f"rank [R; Ψ; L] = {rSL} but rank Σ = rank [R; Ψ] = {rS}: conditions c.–d. have no "
                       "solution (L is not a combination of R and the measured signals).",
                       "Add the missing directions of L to R (a larger observer order q0), or let fojax "
                       "choose R.")
    rel = s.solvability_residual
    if rel > SOLVABILITY_RTOL:
        raise RankConditionError(
            "rank [Σ; TA] = rank Σ",
            f"no choice of Z makes TA a combination of Σ = [R; Ψ] (relative residual {rel:.2e}); "
            "condition a. cannot hold with this R.",
            "Choose another R or a larger observer order q0 (more rows in R), or let fojax choose R.",
            lhs=rel,
            rhs=SOLVABILITY_RTOL,
        )


#: Above this size `unobservable_modes` runs the per-eigenvalue test only on the eigenvalues of
#: the unobservable part of SLICOT's orthogonal staircase form (``AB01ND``).
PBH_SCREEN_MIN = 48


def unobservable_modes(A: np.ndarray, Cm: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    r"""Eigenvalues λ of `A` with rank [λI - A; Cm] < dim A (PBH test, relative tolerance).

    The test is $\sigma_{\min}([\lambda I - A; C_m]) \le$ `tol` $\cdot\max(1, \|A\|, \|C_m\|)$
    for each eigenvalue: one SVD per eigenvalue, $O(n^4)$ in all. For ``dim A >``
    `PBH_SCREEN_MIN` the candidates are first narrowed in $O(n^3)$ to the eigenvalues of the
    unobservable block of the observability staircase form of $(A, C_m)$ (SLICOT
    ``AB01ND`` on the dual pair, orthogonal similarities, its rank decisions at the same
    absolute threshold), and only those get the SVD test.
    """
    A, Cm = np.asarray(A, float), np.asarray(Cm, float)
    n = A.shape[0]
    if n == 0:
        return np.zeros(0, complex)
    scale = max(1.0, np.linalg.norm(A, 2), np.linalg.norm(Cm, 2) if Cm.size else 0.0)
    # Shortcut (exact, O(n³) instead of one SVD per eigenvalue): σ_min([λI - A; Cm]) ≥
    # σ_min(Cm) for every λ (appending rows never lowers the smallest singular value), so
    # when Cm has full column rank with twice the threshold to spare, no mode fails the test.
    if Cm.shape[0] >= n and np.linalg.svd(Cm, compute_uv=False)[n - 1] > 2.0 * tol * scale:
        return np.zeros(0, complex)
    # [λI - A; Cm] and [λI - A; R] (Cm = QR) have the same singular values (an orthogonal
    # transformation of the rows): the per-eigenvalue SVDs get at most 2n rows.
    Rc = np.linalg.qr(Cm, mode="r") if Cm.shape[0] > n else Cm
    if n > PBH_SCREEN_MIN and Cm.size:
        import slycot

        Ac, _, ncont, *_ = slycot.ab01nd(n, Rc.shape[0], A.T.copy(), Rc.T.copy(), jobz="N", tol=tol * scale)
        eigs = np.linalg.eigvals(Ac[ncont:, ncont:]) if ncont < n else np.zeros(0, complex)
    else:
        eigs = np.linalg.eigvals(A)
    out = []
    for lam in eigs:
        Mx = np.vstack([lam * np.eye(n) - A, Rc]) if Cm.size else lam * np.eye(n) - A
        s = np.linalg.svd(Mx, compute_uv=False)
        if s.size < n or s[n - 1] <= tol * scale:
            out.append(lam)
    return np.asarray(out, complex)


def fixed_modes(s: FunctionalObserverStructure) -> list[np.ndarray]:
    """Per rule, the eigenvalues of N1' that no (Z, Y1) can move (Lemma 8 / Remark 3)."""
    pc = pieces(s, xp=np)
    N1, N2, N3 = (np.asarray(x) for x in (pc.N1, pc.N2, pc.N3))
    return [unobservable_modes(N1[i], np.vstack([N2[i], N3])) for i in range(N1.shape[0])]


def check_detectability(
    s: FunctionalObserverStructure, region: AbstractRegion, reported: AbstractRegion | None = None
) -> None:
    """Raise `DetectabilityError` if some fixed mode lies outside `region`.

    `reported` is the region named in the message (the user's region when `region` is
    its tightened version).
    """
    shown = reported if reported is not None else region
    for i, modes in enumerate(fixed_modes(s)):
        bad = [lam for lam in modes if not region.contains([lam])]
        if bad:
            rule = f" of rule {i + 1}" if s.num_rules > 1 else ""
            raise DetectabilityError(
                "detectability of (𝔸2, 𝔸1) (Lemma 8 / Remark 3)",
                f"the mode(s) {', '.join(f'{b:.4g}' for b in bad)}{rule} of the observer cannot be "
                f"moved by any gain (rank [λI - N1; N2; N3] < q0 = {s.q0}) and are not in the "
                f"requested region ({shown.describe()}).",
                "Choose another R (or a larger observer order q0), add outputs, or enlarge the region.",
                lhs=bad,
                rhs=shown.describe(),
            )


def _order_candidates(Gam, Psi, L, q0):
    """Candidate R's by increasing order: a row basis of L, then directions of Γ outside
    the row space of [R; Ψ] (they enlarge Σ), then directions of Γ outside the row space of
    R (inside Ψ's span). The largest order is rank Γ (= rank [L; Γ] under Assumption 1).

    Every basis here is `canonical_row_space`: a candidate takes only the first rows of a
    complement (``rows[:j]``), and the complement of a subspace of Γ's row space is, in
    G_rows coordinates, an orthogonal projector whose singular values are all 1, so the
    SVD's basis of it is a rotation decided by rounding: taking its first rows would make
    the default R's row space depend on rounding, and a model and its power-of-two rescaled
    twin could get different default designs."""
    base = L if rank(L) == L.shape[0] else canonical_row_space(L)
    G_rows = canonical_row_space(Gam)

    def complement(S):
        if S.size == 0:
            return G_rows
        return canonical_row_space(G_rows - G_rows @ np.linalg.pinv(S) @ S)

    extra = complement(np.vstack([base, Psi]))
    more = complement(np.vstack([base, extra])) if extra.size else complement(base)
    rows = np.vstack([extra, more]) if extra.size else more
    max_order = base.shape[0] + rows.shape[0]
    if q0 is None:
        return _Candidates(base, rows, extra.shape[0] + 1), G_rows
    if q0 < 1:
        raise RankConditionError("observer order", f"q0 = {q0}", "q0 must be at least 1.", lhs=q0, rhs=1)
    if q0 <= base.shape[0]:
        return [base[:q0]], G_rows
    if q0 > max_order:
        raise RankConditionError(
            "observer order",
            f"q0 = {q0} exceeds the largest useful order {max_order} (rank of [L; Γ] with "
            "Γ = [E; E⊥A; C]: R must have independent rows in the row space of Γ).",
            "Choose a smaller q0.",
            lhs=q0,
            rhs=max_order,
        )
    return [np.vstack([base, rows[: q0 - base.shape[0]]])], G_rows


class _Candidates:
    """The candidate R's of increasing order ``[base; rows[:j]]``, ``j < count``, built on
    demand (a list of all of them would take O(n³) memory)."""

    def __init__(self, base, rows, count):
        self.base, self.rows, self.count = base, rows, count

    def __len__(self):
        return self.count

    def __getitem__(self, j):
        return np.vstack([self.base, self.rows[:j]])


class _HostStructure:
    """A NumPy stand-in for `FunctionalObserverStructure` (the fields `pieces` reads).

    The default-R search evaluates thousands of candidates; building JAX arrays for each
    would dominate its run time.
    """

    def __init__(self, E, A, C, R, Ep):
        from ._parameterization import _z_restriction

        self.E, self.C, self.R, self.Eperp = E, C, R, Ep
        self._A = A if A.ndim == 3 else A[None]
        self.Z0, self.PiZ, self.solvability_residual = _z_restriction(E, A, C, R, Ep)
        self.n, self.q0, self.num_rules = E.shape[0], R.shape[0], self._A.shape[0]

    def rules_A(self):
        return self._A


def _modes_objective(E, A, B, C, L, q1, psi, Ep, region, target, R, *, require_solvable: bool = False):
    """``(penalty, fixed modes)`` of `R` (host); with `require_solvable`, ``(inf, None)`` when
    condition a. is not solvable with `R` (then the fixed modes mean nothing)."""
    s = _HostStructure(E, A, C, R, Ep)
    if require_solvable and s.solvability_residual > SOLVABILITY_RTOL:
        return np.inf, None
    modes = np.concatenate(fixed_modes(s)) if s.q0 else np.zeros(0)
    if modes.size == 0:
        return 0.0, modes
    scale = max(1.0, abs(target))
    return float(np.sum(np.abs(modes - target) ** 2)) / scale**2, modes


#: The Nelder–Mead search of `default_R` runs only for ``q0 · rank Γ`` up to this many free
#: entries (beyond it the search makes no progress within `max_iter` and its simplex alone
#: takes O((q0 n)²) memory): larger problems take the next order instead.
SEARCH_MAX_ENTRIES = 150
#: With up to this many candidate orders `default_R` tries each in turn; with more it tries
#: the orders 0, 1, 2, 4, … above the smallest and bisects back to the smallest that passes.
LINEAR_ORDERS = 16


def _passes_rank(E, A, B, C, L, R, q1, psi, Ep) -> bool:
    try:
        check_structure(observer_structure(E, A, B, C, L, R, q1=q1, psi=psi, Eperp=Ep))
        return True
    except RankConditionError:
        return False


def _nelder_mead_R(E, A, B, C, L, q1, psi, Ep, region, target, R0, G_rows, max_iter):
    """``R = R0 + D G_rows`` (rows stay in the row space of Γ) with ``D`` from a Nelder–Mead
    search that drives the fixed modes to ``region.target()``, with a small penalty on
    ``‖D‖``. `G_rows` is canonical, so the start simplex does not depend on SVD signs."""
    import scipy.optimize

    nR = np.linalg.norm(R0)

    def f(d):
        R = R0 + d.reshape(R0.shape[0], G_rows.shape[0]) @ G_rows
        try:
            val, _ = _modes_objective(E, A, B, C, L, q1, psi, Ep, region, target, R)
        except Exception:
            return 1e12
        return val + 1e-4 * float(np.sum(d**2)) / max(nR, 1.0) ** 2

    d0 = np.zeros(R0.shape[0] * G_rows.shape[0])
    res = scipy.optimize.minimize(f, d0, method="Nelder-Mead",
                                  options=dict(maxiter=max_iter, xatol=1e-8, fatol=1e-12, initial_simplex=None))
    return R0 + res.x.reshape(R0.shape[0], G_rows.shape[0]) @ G_rows


def default_R(E, A, B, C, L, *, psi: str, Eperp, region: AbstractRegion, q0: int | None = None,
              q1: int = 0, max_iter: int = 3000, balance: bool = True) -> np.ndarray:
    r"""fojax's default choice of R (documented; the thesis leaves R to the user).

    **Unit-free** (``balance=True``, the default): the search below runs on
    the model rescaled by `fojax.analysis.unit_scaling` ($E_b = D_lED_r$, $A_b = D_lAD_r$,
    $B_b = D_lB$, $C_b = CD_r$, $L_b = LD_r$, $E^\perp_b$ an orthonormal basis of the rows
    of $E^\perp D_l^{-1}$), and the result is returned as $R = R_bD_r^{-1}$, so that
    $Rx = R_bx_b$: the same functional of the physical state whatever units the equations
    and states are written in (the orthonormal bases below and the search's penalty would
    otherwise depend on them). ``balance=False`` searches on the
    data as given.

    1. Orders: start from a row basis of ``L`` (``q0 = rank L``, the smallest order)
       and add rows of an orthonormal basis of the row space of Γ = [E; Ψ] not yet in
       the row space of Σ = [R; Ψ], one at a time (only order `q0` when given). The bases
       are `fojax._linalg.canonical_row_space` (pivoted on the states of the unit-free
       frame): the rows taken first are decided by the subspaces, not by the rotation or
       the signs an SVD returns, so neither LAPACK's rounding nor a power-of-two rescaling
       of the model changes the default R (see `_order_candidates`).
    2. For each order, R must satisfy the rank conditions; the modes that no gain can
       move (`fixed_modes`, Lemma 8) must lie in the region. When they do not, R is
       moved inside the row space of Γ, starting from the candidate, by a
       Nelder–Mead search that drives the fixed modes to ``region.target()``
       (with a small penalty on the distance to the candidate). The first R that
       passes is returned.

    Raises the last existence error when no order works.
    """
    E, A, C, L = (np.asarray(x, float) for x in (E, A, C, L))
    B = np.asarray(B, float)
    As = A if A.ndim == 3 else A[None]
    Ep = np.asarray(Eperp, float)
    if balance:
        from ..analysis._balance import scale_model, unit_scaling

        Bs = B if B.ndim == 3 else B[None]
        dl, dr = unit_scaling(E, As[0], Bs[0], C)
        Epb = Ep / dl[None, :]
        if Epb.size:
            Epb = np.linalg.svd(Epb, full_matrices=False)[2][: Ep.shape[0]]  # orthonormal rows, same row space
        Rb = default_R(*scale_model(dl, dr, E, A, B, C), L * dr, psi=psi, Eperp=Epb, region=region, q0=q0, q1=q1,
                       max_iter=max_iter, balance=False)
        if Rb.shape == L.shape and np.array_equal(Rb, L * dr):
            return L.copy()  # the row basis of L itself (step 1): exactly L, not L D_r / D_r
        return Rb / dr[None, :]
    Psi = np.vstack([Ep @ As[0], C])
    Gam = np.vstack([E, Psi])
    candidates, G_rows = _order_candidates(Gam, Psi, L, q0)
    inner = region.tightened(0.05)
    target = region.target()
    errors: list = []

    def accept(R):
        """`R` if it passes the rank conditions and its fixed modes lie in `inner`, else None.
        The fixed modes are checked first, on the host structure (the cheaper test)."""
        try:
            _, modes = _modes_objective(E, A, B, C, L, q1, psi, Ep, region, target, R, require_solvable=True)
            if modes is None or not all(inner.contains([m]) for m in modes):
                return None
        except (np.linalg.LinAlgError, ValueError):
            pass  # the full check below names the failure
        return confirmed(R)

    def confirmed(R):
        s = observer_structure(E, A, B, C, L, R, q1=q1, psi=psi, Eperp=Ep)
        try:
            check_structure(s)
            check_detectability(s, inner, reported=region)
            return R
        except (RankConditionError, DetectabilityError) as err:
            errors.append(err)
            return None

    def searched(R0):
        """`R0` moved by the Nelder–Mead search of step 2 (``None``: too many free entries,
        or the search found no R that passes)."""
        if R0.shape[0] * G_rows.shape[0] > SEARCH_MAX_ENTRIES or not _passes_rank(E, A, B, C, L, R0, q1, psi, Ep):
            return None
        return confirmed(_nelder_mead_R(E, A, B, C, L, q1, psi, Ep, region, target, R0, G_rows, max_iter))

    count = len(candidates)
    if count <= LINEAR_ORDERS:  # every order in turn, each with the search
        for j in range(count):
            R = accept(candidates[j])
            R = R if R is not None else searched(candidates[j])
            if R is not None:
                return R
    else:  # the smallest order, else the largest (module constant LINEAR_ORDERS)
        for j in (0, count - 1):
            R = accept(candidates[j])
            if R is not None:
                return R
        R = searched(candidates[count - 1])
        if R is not None:
            return R
    if not errors:  # the last candidate failed the cheap test: its full check names why
        confirmed(candidates[len(candidates) - 1])
    last_err = errors[-1] if errors else None
    if last_err is None:  # every candidate passed the rank checks but none the modes
        raise RankConditionError("default R", "no candidate R was found", "Pass R explicitly.")
    raise last_err
