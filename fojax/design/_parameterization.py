r"""The functional-observer parameterization of thesis §3.1.2 as pure JAX.

**The design conditions.** For the plant $E\dot x = Ax + Bu$, $y = Cx$, $z = Lx$ and
the observer (3.5) driven by the measured signal $w = [-E^\perp B u;\, y] = \Psi x$,
$\Psi = [E^\perp A;\, C]$, the error $\varepsilon = \zeta - TEx$ obeys
$\dot\varepsilon = N\varepsilon + Jv$, $\dot v = S\varepsilon + Gv$,
$\hat z - z = P\varepsilon$ iff

- a. $NTE + F\Psi - TA = 0$, b. $H = TB$, c. $STE + M\Psi = 0$, d. $PTE + Q\Psi = L$.

**Derivation (re-done; deviations from the printed thesis are marked).**
With $\Gamma = [E;\Psi]$ and $R$ ($q_0\times n$, rows in the row space of $\Gamma$),
$[T\;K]\Gamma = R$ has the solutions $[T\;K] = R\Gamma^+ - Z_{\rm eff}(I - \Gamma\Gamma^+)$,
i.e. $T = T_1 - Z_{\rm eff}T_2$, $K = K_1 - Z_{\rm eff}K_2$ (3.16–3.18). Then
$[TE;\Psi] = \begin{bmatrix}I&-K\\0&I\end{bmatrix}\Sigma$ with $\Sigma = [R;\Psi]$, so
condition a. reads $[N\;\tilde K]\Sigma = TA$ with $\tilde K = F - NK$. Its solutions are
$[N\;\tilde K] = TA\Sigma^+ - Y_1(I - \Sigma\Sigma^+)$, which gives

$$N = TA\Sigma^+\!\begin{bmatrix}I\\0\end{bmatrix} - Y_1 N_3,\qquad
  F = TA\Sigma^+\!\begin{bmatrix}K\\I\end{bmatrix} - Y_1 F_3,$$

$N_3 = (I - \Sigma\Sigma^+)[I;0]$, $F_3 = (I-\Sigma\Sigma^+)[K;I]$. Hence
$N_1 - Z_{\rm eff}N_2$ with $N_1 = T_1A\Sigma^+[I;0]$ and
$N_2 = T_2A\Sigma^{+}[I;0]$ — *the thesis prints $N_{i2} = T_{i2}A\Sigma_i[I;0]$ without
the pseudo-inverse (3.23, 3.126, 3.165); the residual tests confirm $\Sigma^+$.*
Conditions c.–d. give $S = -Y_2N_3$, $M = -Y_2F_3$, $P = L\Sigma^+[I;0] - Y_3N_3$,
$Q = L\Sigma^+[K;I] - Y_3F_3$ (3.29–3.32).

**Deviation: the solvability of a. for every $Z$.** The thesis requires
$\operatorname{rank}[\Sigma; TA] = \operatorname{rank}\Sigma$ but $T$ depends on $Z$.
fojax makes a. hold *identically*: the condition is
$Z_{\rm eff}\,V = U$ with $V = T_2A(I-\Sigma^+\Sigma)$, $U = T_1A(I-\Sigma^+\Sigma)$, whose
solutions are $Z_{\rm eff} = UV^+ + Z\,(I - VV^+)$ for a *free* $Z$ (existence:
$U(I - V^+V) = 0$). When $\Gamma$ has full column rank $V = 0$ and $Z_{\rm eff} = Z$.
So the free parameters $(Z, Y_1, Y_2, Y_3, J, G)$ are unconstrained: every value
yields a valid observer, which is what gradient tuning moves along.

The error dynamics are $\mathbb A = \mathbb A_1 - \mathbb Y\mathbb A_2$ with
$\mathbb A_1 = \operatorname{diag}(N_1 - Z_{\rm eff}N_2, 0)$,
$\mathbb Y = \begin{bmatrix}Y_1&J\\Y_2&G\end{bmatrix}$,
$\mathbb A_2 = \operatorname{diag}(N_3, -I)$ (3.33).

**Exactness at any size (the dead components are projected out first).** Write
$P_\Gamma = I - \Gamma\Gamma^+ = [T_2\;K_2]$ and $P_\Sigma = I - \Sigma\Sigma^+$ (exactly zero
when $\Sigma$ has full row rank, `left_null_projector`). The parameters act on the observer
only through $Z_{\rm eff}P_\Gamma$ and $Y_iP_\Sigma$: $T, K$ are $[T_1\;K_1] - Z_{\rm eff}P_\Gamma$
and $N, F, S, M, P, Q$ contain $Y_i$ only as $Y_i[N_3\;F_3] = Y_iP_\Sigma[I_{q_0}\;\tilde K]$.
Since $\operatorname{range}V \subseteq \operatorname{range}P_\Gamma$ ($V = T_2A(\cdot)$,
$T_2 = P_\Gamma[I;0]$), the projectors $\Pi_Z$ and $P_\Gamma$ commute and
$W = \Pi_ZP_\Gamma$ is the orthogonal projector onto $\operatorname{range}P_\Gamma \cap
(\operatorname{range}V)^\perp$; so $Z\,\Pi_Z T_2 = ZWT_2$, and every component of $Z$
outside $\operatorname{range}W$, or of a row of $Y_i$ in $\operatorname{range}\Sigma$, is
*dead*: it cannot change the observer. In exact arithmetic nothing else is needed. In
float64 the computed projector leaks $\epsilon$ of a dead direction, so a dead component
of size $\delta$ left $\epsilon\delta$ in the matrices where the conditions need an exact
zero: condition c., for instance, is $-Y_2P_\Sigma\Sigma = 0$, and its residual was
$\epsilon\|Y_2\|\|\Sigma\|$ while its terms are $\|Y_2P_\Sigma\|\|\Sigma\|$ — on the
thesis's example 3.3.7 with $10^8\times$ a dead direction added to $Y_2$: relative
residual 1.2e-5 (1e-1 at $10^{12}$); $Z$ and $Y_1, Y_3$ likewise (4e-8 … 4e-7 at $10^8$).
fojax therefore evaluates the *live parts first*, $\hat Z = (ZW)W$ and $\hat Y_i = Y_iP_\Sigma$,
and only then the matrices with them ($Z_{\rm eff} = Z_0 + \hat Z$,
$Y_iN_3 = \hat Y_iP_\Sigma[I;0]$). The first product rounds to $ZW + \eta$ with
$\|\eta\| \lesssim \epsilon\|Z\|$ in any direction; the second leaves of its dead part
only $\epsilon(\|ZW\| + \|\eta\|)$, so what enters the conditions is of the size of the live
part (plus $\epsilon^2\|Z\|$), and so is their residual — relative to terms of that size it
stays at rounding for any size of the parameters (tested up to $10^{13}$ in every
block: at the unperturbed design's own level, ≤ 2e-15 on 3.3.7 and on the hand example of
``tests/test_parameterization.py``, and on the LC filter of ``benchmarks/lc_filter.py``; $Y_i$ needs no second product: $\hat Y_i$ is multiplied by
$P_\Sigma$ again inside $N_3, F_3$). The observer is that of the projected parameters
(`project_parameters`) up to rounding of their size. What cannot be recovered is the
live part's own rounding in a huge parameter: $\|\eta\|\approx\epsilon\|Z\|$, i.e. a
parameter stored as $10^{12}$ carries its live content only to about $10^{-4}$ — that moves
the observer to another valid observer (a.–d. still hold), it does not break one.

**Measured-signal choices.** ``psi="descriptor"`` uses $\Psi = [E^\perp A; C]$ (eq. 3.5);
``psi="output"`` uses $\Psi = C$ (the Takagi–Sugeno observer 3.152, where
$E^\perp A_i$ differs between rules, and standard systems with $E = I$).
For several rules ($A$ of shape ``(k, n, n)``) the matrices $N_{i1}, N_{i2}$ and the
condition $Z_{\rm eff}V_i = U_i$ are formed per rule, with one common $T$.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._dtype import as_matrix
from .._errors import ShapeError
from .._linalg import jpinv, RANK_RTOL


class FunctionalObserverStructure(eqx.Module):
    r"""The data of a functional-observer design problem (plant, $L$, $R$, $E^\perp$).

    Build it with `observer_structure`; `observer_matrices` maps free parameters to
    observer matrices. All arrays are leaves (differentiable, vmappable); the sizes
    are static.

    `A` is ``(n, n)`` or ``(k, n, n)`` (Takagi–Sugeno rules); likewise `B`.
    `Eperp` is ``(r1, n)`` (``r1 = 0`` when ``psi="output"``).
    """

    E: Float[Array, "n n"]
    A: Float[Array, "*k n n"]
    B: Float[Array, "*k n m"]
    C: Float[Array, "p n"]
    L: Float[Array, "q n"]
    R: Float[Array, "q0 n"]
    Eperp: Float[Array, "r1 n"]
    Z0: Float[Array, "q0 nZ"]
    PiZ: Float[Array, "nZ nZ"]
    solvability_residual: float = eqx.field(static=True)
    q1: int = eqx.field(static=True)
    psi: str = eqx.field(static=True)
    D: Float[Array, "p m"] | None = None

    @property
    def n(self):
        return self.E.shape[0]

    @property
    def q0(self):
        return self.R.shape[0]

    @property
    def q(self):
        return self.L.shape[0]

    @property
    def r1(self):
        return self.Eperp.shape[0]

    @property
    def p(self):
        return self.C.shape[0]

    @property
    def m(self):
        return self.B.shape[-1]

    @property
    def nw(self):
        """Size of the measured signal ``w`` (``r1 + p``)."""
        return self.r1 + self.p

    @property
    def num_rules(self):
        return self.A.shape[0] if self.A.ndim == 3 else 1

    def rules_A(self):
        return self.A if self.A.ndim == 3 else self.A[None]

    def rules_B(self):
        return self.B if self.B.ndim == 3 else self.B[None]

    def Psi(self, A):
        return jnp.concatenate([self.Eperp @ A, self.C], axis=0)

    def w_matrices(self, B):
        """``(Wu, Wy)`` with ``w = Wu u + Wy y`` (``w = [-E⊥B u; y]``); for a plant with
        feedthrough ``D`` the observer takes ``y - D u``: ``Wu - Wy D``."""
        Wu = jnp.concatenate([-self.Eperp @ B, jnp.zeros((self.p, B.shape[-1]))], axis=0)
        Wy = jnp.concatenate([jnp.zeros((self.r1, self.p)), jnp.eye(self.p)], axis=0)
        if self.D is not None:
            Wu = Wu - Wy @ self.D
        return Wu, Wy

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shapes of the free parameters (for one rule)."""
        nS = self.q0 + self.nw
        return {
            "Z": (self.q0, self.n + self.nw),
            "Y1": (self.q0, nS),
            "Y2": (self.q1, nS),
            "Y3": (self.q, nS),
            "J": (self.q0, self.q1),
            "G": (self.q1, self.q1),
        }


def observer_structure(
    E,
    A,
    B,
    C,
    L,
    R,
    *,
    q1: int = 0,
    psi: str = "descriptor",
    Eperp=None,
) -> FunctionalObserverStructure:
    """Validate the problem data and build a `FunctionalObserverStructure` (host).

    **Arguments:**

    - `E, A, B, C`: plant matrices (`A`, `B` may carry a leading rule axis).
    - `L`: ``(q, n)`` functional to estimate.
    - `R`: ``(q0, n)`` full-row-rank matrix with rows in the row space of Γ; sets the
      observer order ``q0``.
    - `q1`: size of the auxiliary state ``v`` (0 for a proportional observer).
    - `psi`: ``"descriptor"`` (Ψ = [E⊥A; C]) or ``"output"`` (Ψ = C).
    - `Eperp`: optional left annihilator of E (default: orthonormal basis of the
      left null space; for unknown-input designs the left null space of ``[E D]``).
    """
    E = as_matrix("E", E)
    n = E.shape[0]
    A = jnp.asarray(A, dtype=float)
    B = jnp.asarray(B, dtype=float)
    if A.shape[-2:] != (n, n):
        raise ShapeError("A", (n, n), tuple(A.shape))
    if B.shape[-2] != n:
        raise ShapeError("B", (n, "m"), tuple(B.shape))
    C = as_matrix("C", C, cols=n)
    L = as_matrix("L", L, cols=n, hint=f"L needs one column per state (n = {n}).")
    R = as_matrix("R", R, cols=n, hint=f"R needs one column per state (n = {n}).")
    if psi not in ("descriptor", "output"):
        raise ValueError(f"psi must be 'descriptor' or 'output', got {psi!r}")
    if psi == "output":
        Ep = jnp.zeros((0, n))
    elif Eperp is None:
        from ..analysis import e_perp  # analysis decides the rank of E (balanced)

        Ep = jnp.asarray(e_perp(np.asarray(E)))
    else:
        Ep = as_matrix("Eperp", Eperp, cols=n)
    Z0, PiZ, resid = _z_restriction(*(np.asarray(x) for x in (E, A, C, R, Ep)))
    return FunctionalObserverStructure(
        E, A, B, C, L, R, Ep, jnp.asarray(Z0), jnp.asarray(PiZ), float(resid), int(q1), psi
    )


def _pinv_abs(M: np.ndarray, atol: float) -> np.ndarray:
    if M.size == 0:
        return np.zeros(M.shape[::-1])
    U, sv, Vt = np.linalg.svd(M, full_matrices=False)
    keep = sv > max(atol, RANK_RTOL * (sv[0] if sv.size else 0.0))
    inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
    return (Vt.T * inv) @ U.T


def _z_restriction(E, A, C, R, Ep):
    """Host computation of ``Z_eff = Z0 + Z Π_Z`` (condition a. solvable for every Z).

    ``V = T2 A (I - Σ⁺Σ)`` is often pure round-off (Σ of full column rank); its
    pseudo-inverse therefore uses an *absolute* cutoff scaled by ``‖T2‖‖A‖``, not
    only a relative one. Returns ``(Z0, Π_Z, relative residual of U(I - V⁺V))``.
    """
    n = E.shape[0]
    As = A if A.ndim == 3 else A[None]
    Psi = np.vstack([Ep @ As[0], C])
    Gam = np.vstack([E, Psi])
    Gp = np.linalg.pinv(Gam, rtol=RANK_RTOL)
    RG = R @ Gp
    PG = np.eye(Gam.shape[0]) - Gam @ Gp
    T1, T2 = RG[:, :n], PG[:, :n]
    Sig = np.vstack([R, Psi])
    Pn = np.eye(n) - np.linalg.pinv(Sig, rtol=RANK_RTOL) @ Sig
    V = np.hstack([T2 @ Ai @ Pn for Ai in As])
    U = np.hstack([T1 @ Ai @ Pn for Ai in As])
    scale = max(1.0, float(np.abs(As).max())) * max(1.0, np.linalg.norm(T1, 2), np.linalg.norm(T2, 2))
    atol = 1e3 * np.finfo(float).eps * scale * max(V.shape + (1,))
    Vp = _pinv_abs(V, atol)
    Z0 = U @ Vp
    PiZ = np.eye(V.shape[0]) - V @ Vp
    resid = U - Z0 @ V
    rel = float(np.abs(resid).max()) / scale if resid.size else 0.0
    return Z0, PiZ, rel


class ParameterizationPieces(NamedTuple):
    """Intermediate matrices of the parameterization (thesis names)."""

    T1: Array
    T2: Array
    K1: Array
    K2: Array
    Sigma: Array
    Sigma_pinv: Array
    Z0: Array
    PiZ: Array
    N1: Array  # (k, q0, q0) per rule, already with Z0: N1 - Z0 N2
    N2: Array  # (k, nZ, q0): Π_Z N2 so that N1 - Z_eff N2 = N1' - Z N2'
    N3: Array
    solvability_residual: float


def _pinv(xp, M):
    if M.size == 0:
        return xp.zeros(M.shape[::-1])
    if xp is np:
        return np.linalg.pinv(M, rtol=RANK_RTOL)
    return jpinv(M)


def left_null_projector(xp, M):
    r"""$I - MM^+$, set to exactly zero when `M` has full row rank (fojax's rank rule on its
    singular values: ``RANK_RTOL`` relative; traceable, shapes static).

    *Why the zero:* when `M` has full row rank the projector is zero, but $I - MM^+$ leaves
    rounding (~1e-16) that a large free parameter multiplies: $Y_1N_3$ with
    $N_3 = (I - \Sigma\Sigma^+)[I;0]$ made the residual of condition a. grow with $\|Y_1\|$
    (1.3e-3 relative at 1e13). *Why not* $U_0U_0^\top$ from the full SVD in general: its
    trailing singular vectors depend on the LAPACK kernel more than $I - MM^+$ does (with some
    BLAS kernels the observers of thesis example 4.1.3 then met
    conditions a.–d. only to ~1e-7 in simulation), so the rank-deficient case keeps
    $I - MM^+$.
    """
    m = M.shape[0]
    if M.size == 0:
        return xp.eye(m)
    P = xp.eye(m) - M @ _pinv(xp, M)
    if m > M.shape[1]:  # more rows than columns: never full row rank
        return P
    sv = xp.linalg.svd(M, compute_uv=False)
    full_row_rank = xp.all(sv > RANK_RTOL * sv[0])
    return xp.where(full_row_rank, xp.zeros_like(P), P)


def pieces(s: FunctionalObserverStructure, xp=jnp) -> ParameterizationPieces:
    """The Z-independent matrices of the parameterization.

    Traceable with ``xp=jax.numpy`` (default); ``xp=numpy`` gives a fast host version
    (used by the search for a default R).
    """
    n = s.n
    As = xp.asarray(s.rules_A())
    E, C, R, Ep = (xp.asarray(x) for x in (s.E, s.C, s.R, s.Eperp))
    # Ψ must be common to all rules: with psi="descriptor" we use the first rule's E⊥A.
    Psi = xp.concatenate([Ep @ As[0], C], axis=0)
    Gam = xp.concatenate([E, Psi], axis=0)
    Gp = _pinv(xp, Gam)
    RG = R @ Gp
    PG = xp.eye(Gam.shape[0]) - Gam @ Gp
    T1, K1 = RG[:, :n], RG[:, n:]
    T2, K2 = PG[:, :n], PG[:, n:]
    Sig = xp.concatenate([R, Psi], axis=0)
    Sp = _pinv(xp, Sig)
    Pn = xp.eye(n) - Sp @ Sig
    PS = left_null_projector(xp, Sig)
    Iq = xp.eye(Sig.shape[0], s.q0)
    N3 = PS @ Iq
    # Z_eff = Z0 + Z Π_Z makes condition a. solvable for every Z (computed on the host
    # when the structure is built; see `_z_restriction`).
    Z0, PiZ = xp.asarray(s.Z0), xp.asarray(s.PiZ)
    resid = s.solvability_residual
    del Pn
    N1 = xp.stack([T1 @ Ai @ Sp @ Iq for Ai in As])
    N2 = xp.stack([T2 @ Ai @ Sp @ Iq for Ai in As])
    N1p = N1 - xp.einsum("ij,kjl->kil", Z0, N2)
    N2p = xp.einsum("ij,kjl->kil", PiZ, N2)
    return ParameterizationPieces(T1, T2, K1, K2, Sig, Sp, Z0, PiZ, N1p, N2p, N3, resid)


class ObserverMatrices(NamedTuple):
    """Observer matrices (per rule along a leading axis when the plant has rules)."""

    N: Array
    J: Array
    F: Array
    H: Array
    S: Array
    G: Array
    M: Array
    P: Array
    Q: Array
    T: Array
    K: Array
    Z_eff: Array
    F3: Array


def _rule_param(x, k, xp=jnp):
    x = xp.asarray(x)
    return x if x.ndim == 3 else xp.broadcast_to(x, (k,) + x.shape)


def _z_projector(s: FunctionalObserverStructure, pc: ParameterizationPieces, xp):
    r"""$W = \Pi_Z(I - \Gamma\Gamma^+)$: ``Z`` acts on the observer only through ``Z W``."""
    PG = xp.concatenate([pc.T2, pc.K2], axis=1)  # I − ΓΓ⁺ = [T2  K2]
    return xp.asarray(s.PiZ) @ PG


def _live_part(s: FunctionalObserverStructure, pc: ParameterizationPieces, Z, Y1, Y2, Y3, xp) -> dict:
    r"""The live parts ``(Z W) W`` and ``Y_i P_\Sigma`` of the parameters (module docstring,
    *Exactness at any size*), and $P_\Sigma = I - \Sigma\Sigma^+$ (``"PS"``)."""
    W = _z_projector(s, pc, xp)
    PS = left_null_projector(xp, pc.Sigma)
    out = {"Z": (xp.asarray(Z) @ W) @ W, "PS": PS}
    for name, Y in (("Y1", Y1), ("Y2", Y2), ("Y3", Y3)):
        out[name] = xp.asarray(Y) @ PS
    return out


def split_Y(Y: np.ndarray, q0: int, c: int) -> dict:
    """Split 𝕐 = [[Y1, J], [Y2, G]] into its blocks."""
    return {"Y1": Y[:q0, :c], "J": Y[:q0, c:], "Y2": Y[q0:, :c], "G": Y[q0:, c:]}


def project_parameters(s: FunctionalObserverStructure, params: dict, *, xp=jnp) -> dict:
    r"""The parameters with their dead components removed (traceable; ``xp=numpy`` on the host).

    ``Z`` $\to ZW$ with $W = \Pi_Z(I - \Gamma\Gamma^+)$, $Y_{1,2,3} \to Y_iP_\Sigma$ with
    $P_\Sigma = I - \Sigma\Sigma^+$ (exactly zero when $[R;\Psi]$ has full row rank); ``J``
    and ``G`` are kept. In exact arithmetic `observer_matrices` gives the same observer for
    `params` and for the result; in float64 the two agree to rounding of the *projected*
    size (the dead components, however large, never enter a product; module docstring).
    Used by `fojax.design.certify`, so a certified design stores only what acts.

    **Arguments:** `s` the structure, `params` a dict with (some of) ``Z, Y1, Y2, Y3, J, G``
    (``Y`` blocks may carry a leading rule axis).

    **Returns:** a dict with the same keys.
    """
    pc = pieces(s, xp=xp)
    out = dict(params)
    if "Z" in params:
        out["Z"] = xp.asarray(params["Z"]) @ _z_projector(s, pc, xp)
    PS = left_null_projector(xp, pc.Sigma)
    for name in ("Y1", "Y2", "Y3"):
        if name in params:
            out[name] = xp.asarray(params[name]) @ PS
    return out


def observer_matrices(
    s: FunctionalObserverStructure, Z, Y1, Y2, Y3, J, G, *, xp=jnp
) -> ObserverMatrices:
    r"""Map the free parameters to the observer matrices (pure JAX).

    `Z` is common to all rules (one ``T``); `Y1, Y2, Y3, J, G` may carry a leading
    rule axis. Conditions a.–d. hold for *every* value of the parameters (when the
    existence conditions hold; see `design_residuals`), in float64 to rounding relative to
    the terms of each condition for parameters of any size: the dead components of ``Z``
    and ``Y_i`` are projected out before they enter a product (module docstring,
    *Exactness at any size*; ``Z_eff`` is returned with them removed). Returned matrices
    have a leading rule axis of size ``k`` (1 for LTI plants). ``xp=numpy`` evaluates the
    same formulas on the host (used for float64 verification without JAX dispatch).
    """
    k = s.num_rules
    pc = pieces(s, xp=xp)
    live = _live_part(s, pc, Z, Y1, Y2, Y3, xp)
    Z_eff = xp.asarray(s.Z0) + live["Z"]
    T = pc.T1 - Z_eff @ pc.T2
    K = pc.K1 - Z_eff @ pc.K2
    Sp, Sig = pc.Sigma_pinv, pc.Sigma
    PS = live["PS"]
    Iq = xp.eye(Sig.shape[0], s.q0)
    KI = xp.concatenate([K, xp.eye(s.nw)], axis=0)
    N3 = PS @ Iq
    F3 = PS @ KI
    Y1, Y2, Y3 = (_rule_param(live[y], k, xp) for y in ("Y1", "Y2", "Y3"))
    J, G = _rule_param(J, k, xp), _rule_param(G, k, xp)
    As = xp.asarray(s.rules_A())
    Bs = xp.broadcast_to(xp.asarray(s.rules_B()), (k,) + s.rules_B().shape[-2:])
    L = xp.asarray(s.L)
    TA = xp.einsum("ij,kjl->kil", T, As)
    N = TA @ Sp @ Iq - Y1 @ N3
    F = TA @ Sp @ KI - Y1 @ F3
    S = -Y2 @ N3
    M = -Y2 @ F3
    # explicit leading rule axis: no implicit rank promotion (jax_numpy_rank_promotion="raise")
    P = (L @ Sp @ Iq)[None] - Y3 @ N3
    Q = (L @ Sp @ KI)[None] - Y3 @ F3
    H = xp.einsum("ij,kjl->kil", T, Bs)
    return ObserverMatrices(N, J, F, H, S, G, M, P, Q, T, K, Z_eff, F3)


def error_dynamics(mats: ObserverMatrices, xp=jnp) -> Array:
    r"""$\mathbb A_i = [N_i\; J_i;\; S_i\; G_i]$ for every rule, shape ``(k, q0+q1, q0+q1)``."""
    top = xp.concatenate([mats.N, mats.J], axis=-1)
    bot = xp.concatenate([mats.S, mats.G], axis=-1)
    return xp.concatenate([top, bot], axis=-2)


def design_residuals(
    s: FunctionalObserverStructure, mats: ObserverMatrices, xp=jnp
) -> dict[str, Array]:
    r"""Residuals of conditions a.–d. (max over rules, spectral norm), traceable.

    Returns a dict with ``a, b, c, d`` and ``scale``: the norm of the data
    ``max(‖E‖, ‖A‖, ‖B‖, ‖C‖, ‖L‖, 1)`` times ``max(1, ‖T‖, ‖N‖, ‖F‖, ...)`` used to
    make the residuals relative.
    """
    As = xp.asarray(s.rules_A())
    Bs = xp.broadcast_to(xp.asarray(s.rules_B()), (s.num_rules,) + s.rules_B().shape[-2:])
    Psi = xp.concatenate([xp.asarray(s.Eperp) @ As[0], xp.asarray(s.C)], axis=0)
    TE = mats.T @ xp.asarray(s.E)
    L = xp.asarray(s.L)
    ra = xp.einsum("kij,jl->kil", mats.N, TE) + mats.F @ Psi - xp.einsum("ij,kjl->kil", mats.T, As)
    rb = mats.H - xp.einsum("ij,kjl->kil", mats.T, Bs)
    rc = xp.einsum("kij,jl->kil", mats.S, TE) + mats.M @ Psi
    rd = xp.einsum("kij,jl->kil", mats.P, TE) + mats.Q @ Psi - L

    def nrm(x):
        return xp.max(xp.linalg.norm(x, ord=2, axis=(-2, -1))) if x.size else xp.zeros(())

    data = xp.max(
        xp.stack([nrm(xp.asarray(s.E)[None]), nrm(As), nrm(Bs) if Bs.size else 0.0, nrm(xp.asarray(s.C)[None]), nrm(L[None]), 1.0])
    )
    gains = xp.max(
        xp.stack(
            [nrm(mats.T[None]), nrm(mats.N), nrm(mats.F), nrm(mats.S), nrm(mats.M), nrm(mats.P), nrm(mats.Q), 1.0]
        )
    )
    return {"a": nrm(ra), "b": nrm(rb), "c": nrm(rc), "d": nrm(rd), "scale": data * gains}


def zero_params(s: FunctionalObserverStructure, rules: bool = False) -> dict[str, Array]:
    """All-zero free parameters of the right shapes (a leading rule axis if `rules`)."""
    k = s.num_rules
    out = {}
    for name, shape in s.param_shapes().items():
        if rules and name != "Z":
            shape = (k,) + shape
        out[name] = jnp.zeros(shape)
    return out


__all__ = [
    "FunctionalObserverStructure",
    "ObserverMatrices",
    "design_residuals",
    "error_dynamics",
    "observer_matrices",
    "observer_structure",
    "pieces",
    "project_parameters",
    "zero_params",
]

_ = jax  # keep the import for type checkers using jax.Array
