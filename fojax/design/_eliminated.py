r"""The region LMI of one rule with the gains eliminated: an LMI in the $\varepsilon$-block's
certificate alone (generalized, PI and proportional observers; every region).

`fojax.design._region_lmi.solve_gains` solves the Chilali–Gahinet LMI of the whole error
dynamics $\mathbb A = \mathbb A_1(Z) - \mathbb Y\mathbb A_2$ (order $d = q_0 + q_1$) in
$(X, W = X_1Z, \mathcal W = X\mathbb Y)$. `eliminated_gains` solves a smaller LMI with the
same feasible set, in three exact reductions, and recovers the gains from its solution in closed
form.

**1. The integral block.** With $Z$, $Y_1$ given, $\mathbb A = \begin{bmatrix}A_\varepsilon & J\\
-Y_2N_3 & G\end{bmatrix}$, $A_\varepsilon = N_1' - [Z\;Y_1]C_\varepsilon$,
$C_\varepsilon = \begin{bmatrix}N_2'\\ N_3\end{bmatrix}$, and $J, Y_2, G$ are free (generalized;
$Y_2 = 0$ for PI). *Claim:* gains of the kind placing the eigenvalues of $\mathbb A$ in a region
$\mathcal R$ exist iff gains $[Z\;Y_1]$ placing those of $A_\varepsilon$ in $\mathcal R$ exist.
($\Leftarrow$) $J = 0$, $Y_2 = 0$, $G = gI$ with $g \in \mathcal R$ real give
$\operatorname{eig}\mathbb A = \operatorname{eig}A_\varepsilon \cup \{g\}$.
($\Rightarrow$) PI: $\mathbb A$ is block upper triangular, so $\operatorname{eig}A_\varepsilon
\subset \operatorname{eig}\mathbb A$. Generalized: a mode $\lambda$ of $N_1' - ZN_2'$ with
$N_3x = 0$ is an eigenvalue of every $\mathbb A$ ($\mathbb A[x; 0] = \lambda[x; 0]$); the
unobservable modes of $(C_\varepsilon, N_1')$ are among them, so they lie in $\mathcal R$, and
output injection through $C_\varepsilon$ places the observable ones anywhere (pole placement;
$\mathcal R$ meets the real axis). The proportional observer is the $\varepsilon$-block. The
$\varepsilon$-block problem is an output-injection problem of order $q_0$ with the one gain
$K = [Z\;Y_1]$; only $KC_\varepsilon$ matters, so with the thin SVD
$C_\varepsilon = U_kS_kR$ ($R$ orthonormal rows, rank $k$) it is posed for the gain
$K_r = KU_kS_k$ and the output $R$, and $K = K_rS_k^{-1}U_k^\top$ (least norm) is returned.
The full LMI's structured certificate $\begin{bmatrix}X_1 & X_1\Pi\\ \cdot & X_2\end{bmatrix}$
is congruent to $\operatorname{diag}(X_1, X_2 - \Pi^\top X_1\Pi)$, which certifies the block
triangular $\begin{bmatrix}A_\varepsilon & \ast\\ 0 & g\end{bmatrix}$ for a large enough second
block: the full LMI has the same feasible set.

**2. The gain of the $\varepsilon$-block.** Let $N$ be an orthonormal basis of the null space
of $R$. With $\Phi = XA - \mathcal W R$ ($A = N_1'$, $\mathcal W = XK_r$) the Chilali–Gahinet
condition $L\otimes X + M\otimes\Phi^\top + M^\top\otimes\Phi \prec 0$ is solved as follows.

- *Disk* $\mathcal Q(\alpha, \tau)$ (elimination lemma, Gahinet–Apkarian): with
  $\bar A = (A - \alpha I)/\tau$ the condition is $\begin{bmatrix}X & X\bar A - \mathcal W R/\tau\\
  \cdot & X\end{bmatrix}\succ 0$; since $\mathcal W$ is free, it holds for some $\mathcal W$ iff
  $\begin{bmatrix}X & X\bar AN\\ N^\top\bar A^\top X & N^\top XN\end{bmatrix}\succ 0$ — one cone
  of size $q_0 + k_0$, $k_0 = q_0 - k$. *Gain:* $M^\top XM \prec X \iff MPM^\top \prec P$
  ($P = X^{-1}$), and $MPM^\top$ is smallest in the Loewner order at
  $\bar K = \bar AP\bar C^\top(\bar CP\bar C^\top)^{-1}$ with $\bar C = R/\tau$, i.e.
  $K_r = \tau\bar APR^\top(RPR^\top)^{-1}$, which therefore meets the condition whenever some
  gain does. $RPR^\top$ is $k\times k$ and positive definite
  ($R$ has orthonormal rows), solved by Cholesky. The certificate returned is the Stein
  certificate of the closed loop (`fojax.design._stein`).
- *Half-planes, sectors and their intersections* ($M_j + M_j^\top \succ 0$ for every part $j$:
  $M = 1$, resp. $M + M^\top = 2\sin\theta\,I$; Finsler's lemma): for every part,
  $(I\otimes N)^\top F_j(X, XA)(I\otimes N) \prec 0$, where $F_j$ is the part's LMI without
  gain — cones of sizes $q_0$ (for $X \succ 0$) and $m_jk_0$. ($\Rightarrow$) the gain terms
  vanish on $I\otimes N$ ($RN = 0$). ($\Leftarrow$) By Finsler's lemma each part has a
  $\rho_j$ with $F_j - \rho_jI\otimes R^\top R \prec 0$; with $\mathcal W = wR^\top$,
  $F_j - w(M_j + M_j^\top)\otimes R^\top R \preceq F_j - w\mu_jI\otimes R^\top R$
  ($\mu_j = \lambda_{\min}(M_j + M_j^\top) > 0$), so every $w > \max_j\rho_j^*/\mu_j$ works,
  with $\rho_j^*$ the smallest such $\rho$: in the basis $(I\otimes N, I\otimes R^\top)$,
  $\rho_j^* = \lambda_{\max}(F_{rr} - F_{rn}F_{nn}^{-1}F_{nr})$ (Schur complement; $F_{nn}
  \prec 0$ by the LMI). *Gain:* $\mathcal W = \mathcal W_0 + wR^\top$, where
  $\mathcal W_0 = N(N^\top XAR^\top + \bar c\,(RXAN)^\top) + R^\top RXAR^\top$ ($\bar c$ the mean
  of $\cos 2\psi_j$ over the parts, $\psi_j = 0$ for a half-plane and $\psi_j = \pi/2 - \theta$
  for a sector) cancels the row-space block of $\Phi$ and, for half-planes exactly, the coupling
  of the two blocks, so that the multiplier needed is small; the argument above holds with
  $F_j$ evaluated at $\mathcal W_0$, and $w = \max_j(\rho_j^* + \delta_j)/\mu_j$ with
  $\delta_j = \max(|\rho_j^*|, \lambda_j, \epsilon)$, $-\lambda_j$ the largest eigenvalue of
  $F_{nn}$. $K_r = X^{-1}\mathcal W$ by a symmetric solve; the certificate is the LMI's $X$.
  Intersections on which the solver stops short are shown infeasible when one part alone is.
- *An intersection with a disk*, first: the disk form for the largest disk $\mathcal Q(c, \rho)$
  centred on the real axis inside the region (`inscribed_disk`: $\rho$ is the region's
  margin at $c$, the distance to the nearest boundary). Its certificate $X$ gives
  $\|X^{1/2}(A_{cl} - cI)X^{-1/2}\| < \rho$, so for a disk part $\mathcal Q(\alpha, \tau)
  \supseteq \mathcal Q(c, \rho)$, $\|X^{1/2}(A_{cl} - \alpha I)X^{-1/2}\| < \rho + |c - \alpha|
  \le \tau$ (its LMI, by a Schur complement), and the $X$-numerical range of $A_{cl}$ lies in
  $\mathcal Q(c, \rho)$, which is what the LMI of a half-plane or a sector at $X$ says
  (`fojax.design._riccati`): every solution of the inscribed disk's LMI solves the
  intersection's LMI, not conversely (a mode no gain moves may lie in the region but outside
  the inscribed disk). When it has no solution, the intersection's own LMI decides (next
  item); only that one raises `fojax.errors.LMIInfeasibleError`.
- *Other regions*, and an intersection with a disk whose inscribed disk has no solution: the
  $\varepsilon$-block's Chilali–Gahinet LMI in $(X, \mathcal W)$, one cone of size $m_jq_0$ per
  part $j$ (the region's LMI is block diagonal), $K_r = X^{-1}\mathcal W$.

**3. One step of the observability staircase.** In the orthonormal basis $Q = [N\;R^\top]$
write $Q^\top XQ = \begin{bmatrix}X_{nn} & X_{nr}\\ X_{nr}^\top & X_{rr}\end{bmatrix}$,
$a = N^\top AN$, $b = RAN$ (so $AN = Na + R^\top b$). The LMIs of step 2 leave $X_{rr}$ to
$X \succ 0$, which holds iff $X_{nn} \succ 0$ and $X_{rr} \succ X_{nr}^\top X_{nn}^{-1}X_{nr}$:

- *Finsler:* $N^\top XN = X_{nn}$ and $N^\top XAN = X_{nn}a + X_{nr}b$, so each part's LMI is
  $L_j\otimes X_{nn} + M_j\otimes\Phi^\top + M_j^\top\otimes\Phi \prec 0$ with
  $\Phi = X_{nn}a + X_{nr}b$: the Chilali–Gahinet LMI of the output-injection problem
  $(a, -b)$ of order $k_0$, with $X_{nr}$ as its gain variable. Every solution of step 2 gives
  one, and $X_{rr} = X_{nr}^\top X_{nn}^{-1}X_{nr} + I$ completes every solution.
- *Disk* ($a, b$ of $\bar A$): by a Schur complement the cone of step 2 is $X \succ 0$ and
  $X_{nn} - [a; b]^\top Q^\top XQ[a; b] \succ 0$. With $X_{rr} \succeq
  X_{nr}^\top X_{nn}^{-1}X_{nr}$, $[a; b]^\top Q^\top XQ[a; b] \succeq \Psi^\top X_{nn}^{-1}\Psi$,
  $\Psi = X_{nn}a + X_{nr}b$, with equality in the limit: step 2's LMI has a solution iff
  $\begin{bmatrix}X_{nn} & \Psi\\ \Psi^\top & X_{nn}\end{bmatrix} \succ 0$ has one (the unit
  disk's LMI of $(a, -b)$), and $X_{rr} = X_{nr}^\top X_{nn}^{-1}X_{nr} + \delta I$, with
  $\delta\|b\|^2$ half the smallest eigenvalue of $X_{nn} - \Psi^\top X_{nn}^{-1}\Psi$,
  completes a solution.

Both are solved with $X_{nn} \succeq I$ and the objective $\operatorname{tr}X_{nn} +
\|X_{nr}\|_F$ (unbounded on unbounded parts of the feasible set, so the optimum is attained);
the gain then comes from the completed $X$ as in step 2. When $R$ has rank $q_0$ ($k_0 = 0$)
no constraint is left and $X = I$.

**Integral block and coupling.** $G = gI$ with $g$ the real part of the $\varepsilon$-block's
eigenvalue deepest in the region (inside: the regions are convex and symmetric about the real
axis), certificate $\operatorname{diag}(X_\varepsilon, I)$. A generalized
observer is then coupled like the Riccati route's (`fojax.design._riccati`): $J = \kappa\Pi$,
$Y_2 = \kappa\Pi^\top Y_1/\|Y_1\|$ (PI: $J = \kappa\Pi$ only, $S = 0$ stays). The coupling adds
$\kappa D$ to $\mathbb A$ and $\kappa(M\otimes(XD)^\top + M^\top\otimes XD)$, of norm at most
$2\kappa\|M\|\|XD\|$, to the region LMI at the fixed $X$; $\kappa$ is `COUPLING_SHARE` of
$\lambda/(2\|M\|\|XD\|)$, with $-\lambda$ the largest eigenvalue of the decoupled LMI, so the
same $X$ certifies the coupled observer.

**Solving.** Each reduced LMI is built with NumPy as a `fojax.design._lmi.ConicLMI` in the
coordinates $x = \operatorname{svec}X$ (and the entries of $\mathcal W$ where it is kept) and
solved by Clarabel directly, without cvxpy's canonicalisation; the ladder's SCS rungs solve
the same program through cvxpy (`fojax.design._region_lmi.solve_conic_with_fallbacks`).

Costs: the full LMI has $d(d+1)/2 + d(k + q_1)$ scalar variables and a cone of size $md$; the
reduced ones $k_0(k_0+1)/2 + k_0k$ variables and cones of sizes $k_0$ and $m_jk_0$ (disk:
$2k_0$). Every design is verified in float64 by the caller (`fojax.design.verify`), whichever
formulation produced it.
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError, LMIInfeasibleError, SolverStoppedShortError
from ._lmi import check_solver, ConicLMI, DEFAULT_SOLVER, region_lmi_batch, smat, svec, sym_basis
from ._parameterization import FunctionalObserverStructure, pieces
from ._regions import AbstractRegion, Disk, HalfPlane, Intersection, Sector


#: The coupling of a generalized (J, Y2) or PI (J) design uses this share of the room its
#: decoupled certificate leaves (module docstring).
COUPLING_SHARE = 0.5
HINT = ("No observer gain places the error dynamics in the region: enlarge the region, "
        "or choose another R / observer order.")


def formulation(region: AbstractRegion) -> str:
    """Which LMI `eliminated_gains` solves for `region`: ``"disk"`` (elimination lemma),
    ``"finsler"`` (every part a half-plane or a sector), ``"inscribed disk"`` (an intersection
    with a disk: the disk form for `inscribed_disk`, then ``"full"`` if that has no solution)
    or ``"full"`` (the ε-block's LMI with its gain)."""
    if isinstance(region, Disk):
        return "disk"
    parts = region.parts if isinstance(region, Intersection) else (region,)
    if all(isinstance(p, HalfPlane | Sector) for p in parts):
        return "finsler"
    if any(isinstance(p, Disk) for p in parts):
        return "inscribed disk"
    return "full"


#: Centres tried by `inscribed_disk` along the real diameter of the region's disks.
INSCRIBED_GRID = 2001


def inscribed_disk(region: AbstractRegion) -> Disk | None:
    """The largest disk centred on the real axis inside `region` (an intersection with a disk
    part), its radius the region's margin at the centre (on a grid of `INSCRIBED_GRID`
    centres); ``None`` if there is none."""
    parts = region.parts if isinstance(region, Intersection) else (region,)
    disks = [p for p in parts if isinstance(p, Disk)]
    lo = max(float(d.center) - float(d.radius) for d in disks)
    hi = min(float(d.center) + float(d.radius) for d in disks)
    if not hi > lo:
        return None
    c = np.linspace(lo, hi, INSCRIBED_GRID)
    r = np.asarray(region.margin(c.astype(complex)), dtype=float)
    i = int(np.argmax(r))
    if not r[i] > 0:
        return None
    try:
        return type(disks[0])(float(c[i]), float(r[i]))
    except InputError:
        return None


def epsilon_output(Ceps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""``(R, N, back)`` of the thin SVD $C_\varepsilon = U_kS_kR$: orthonormal rows `R` of the
    row space, an orthonormal basis `N` of the null space, and ``back`` $= S_k^{-1}U_k^\top$
    ($K = K_r\,$``back``). The rank rule is `fojax._linalg`'s."""
    from .._linalg import row_null_split

    R, N, U, sv = row_null_split(Ceps)
    return R, N, (U / sv).T


def _staircase(A, R, N):
    """``(a, b) = (NᵀAN, RAN)``: ``AN`` in the basis ``Q = [N, Rᵀ]`` (module docstring, step 3)."""
    return N.T @ A @ N, R @ A @ N


def _lift(Xnn, Xnr, Xrr, N, R):
    """``X = Q [[Xnn, Xnr], [Xnrᵀ, Xrr]] Qᵀ`` with ``Q = [N, Rᵀ]``."""
    X = N @ Xnn @ N.T + N @ Xnr @ R + R.T @ Xnr.T @ N.T + R.T @ Xrr @ R
    return 0.5 * (X + X.T)


def _certificate(x, q0, staircase, level, N, R, x_rr):
    """The certificate ``X`` from the solver's ``x``: ``smat(x)`` (step 2), ``I`` when the
    null space of ``R`` is trivial (no LMI was solved), else the staircase's ``(X_nn,
    X_nr)`` lifted with the completion ``x_rr(X_nn, X_nr)`` of its region kind."""
    if not staircase:
        return smat(x, q0)
    if level is None:
        return np.eye(q0)
    Xnn, Xnr = level[1](x)
    return _lift(Xnn, Xnr, x_rr(Xnn, Xnr), N, R)


def _next_level(N, R, region_parts, a, b, margin):
    """The LMI of the next level (step 3): gain kept for ``(a, -b)`` in `region_parts`, the
    variables ``(X_nn, X_nr)``; ``None`` when the null space of `R` is trivial."""
    if N.shape[1] == 0:
        return None
    return _gain_kept(a, -b, region_parts, margin)


def _disk_lmi(A, R, N, disk, margin, staircase=True):
    q0, k0 = A.shape[0], N.shape[1]
    alpha, tau = float(disk.center), float(disk.radius)
    Ab = (A - alpha * np.eye(q0)) / tau
    if staircase:
        a, b = _staircase(Ab, R, N)
        unit = (-np.eye(2), np.array([[0.0, 1.0], [0.0, 0.0]]))  # the unit disk's (L, M)
        level = _next_level(N, R, [unit], a, b, margin)
        prob = None if level is None else level[0]
    else:  # step 2: one cone, its (1,1) block carries the normalization X ⪰ I
        level = None
        B = sym_basis(q0)  # x = svec X
        BAN = B @ (Ab @ N)
        F = np.zeros((B.shape[0], q0 + k0, q0 + k0))
        F[:, :q0, :q0] = B
        F[:, :q0, q0:] = BAN
        F[:, q0:, :q0] = np.swapaxes(BAN, 1, 2)
        F[:, q0:, q0:] = N.T @ B @ N
        prob = ConicLMI(svec(np.eye(q0)), ((-np.diag(np.r_[np.ones(q0), np.full(k0, margin)]), F),))

    def x_rr(Xnn, Xnr):
        # X_rr = X_rn X_nn⁻¹ X_nr + δI, δ half the room the Schur complement leaves
        Psi = Xnn @ a + Xnr @ b
        S = Xnn - Psi.T @ np.linalg.solve(Xnn, Psi)
        nb = float(np.linalg.norm(b, 2)) ** 2 if b.size else 0.0
        room = float(np.linalg.eigvalsh(0.5 * (S + S.T))[0])
        delta = 0.5 * room / nb if nb > 0 and room > 0 else 1.0
        return Xnr.T @ np.linalg.solve(Xnn, Xnr) + delta * np.eye(R.shape[0])

    def gain(x):
        Xv = _certificate(x, q0, staircase, level, N, R, x_rr)
        # K = τ Ā P Rᵀ (R P Rᵀ)⁻¹ with P = X⁻¹ (module docstring), by Cholesky solves
        Lx = np.linalg.cholesky(Xv)
        PRt = np.linalg.solve(Lx.T, np.linalg.solve(Lx, R.T))  # P Rᵀ
        return Xv, (tau * np.linalg.solve(R @ PRt, (Ab @ PRt).T).T if R.size else np.zeros((q0, 0)))

    return prob, gain


def _finsler_lmi(A, R, N, region, margin, staircase=True):
    q0, k0 = A.shape[0], N.shape[1]
    parts = region.parts if isinstance(region, Intersection) else (region,)
    chars = [p.characteristic() for p in parts]
    if staircase:
        a, b = _staircase(A, R, N)
        level = _next_level(N, R, chars, a, b, margin)
        prob = None if level is None else level[0]
    else:  # step 2: X ⪰ I and each part's LMI on the null space of R
        level = None
        B = sym_basis(q0)  # x = svec X
        blocks = [(-np.eye(q0), B)]
        for L, M in chars:
            In = np.kron(np.eye(L.shape[0]), N)
            blocks.append((-margin * np.eye(L.shape[0] * k0), -(In.T @ region_lmi_batch(L, M, B, B @ A) @ In)))
        prob = ConicLMI(svec(np.eye(q0)), tuple(blocks))

    def x_rr(Xnn, Xnr):  # X_rr = X_rn X_nn⁻¹ X_nr + I: X ≻ 0, the parts' LMIs need no more
        return Xnr.T @ np.linalg.solve(Xnn, Xnr) + np.eye(R.shape[0])

    def gain(x):
        Xv = _certificate(x, q0, staircase, level, N, R, x_rr)
        # 𝒲 = 𝒲0 + w Rᵀ: 𝒲0 cancels the coupling of the null-space and row-space blocks
        # (exactly for half-planes, up to |sin 2ψ| for a sector) and the row-space block of
        # XA; w from the Schur complement (module docstring)
        XA = Xv @ A
        Pnr, Prn = N.T @ XA @ R.T, R @ XA @ N
        cos2 = np.mean([1.0 if isinstance(p, HalfPlane) else 1.0 - 2.0 * float(p.damping) ** 2 for p in parts])
        W0 = N @ (Pnr + cos2 * Prn.T) + R.T @ (R @ XA @ R.T)
        w = 0.0
        for L, M in chars:
            m = L.shape[0]
            Phi = XA - W0 @ R
            F = np.kron(L, Xv) + np.kron(M, Phi.T) + np.kron(M.T, Phi)
            F = 0.5 * (F + F.T)
            In, Ir = (N, R.T) if m == 1 else (np.kron(np.eye(m), N), np.kron(np.eye(m), R.T))
            Fnn, Fnr, Frr = In.T @ F @ In, In.T @ F @ Ir, Ir.T @ F @ Ir
            lam = -float(np.linalg.eigvalsh(Fnn)[-1]) if k0 else margin
            S = Frr - Fnr.T @ np.linalg.solve(Fnn, Fnr) if k0 else Frr
            rstar = float(np.linalg.eigvalsh(0.5 * (S + S.T))[-1]) if S.size else 0.0
            mu = float(np.linalg.eigvalsh(M + M.T)[0])
            w = max(w, (rstar + max(abs(rstar), lam, margin)) / mu)
        return Xv, np.linalg.solve(Xv, W0 + w * R.T)

    return prob, gain


def _gain_kept(A, R, parts, margin):
    """The Chilali–Gahinet LMI of ``A - KR`` in ``(X, 𝒲 = XK)`` for the characteristic
    matrices ``parts = [(L, M), …]``, one cone per part, ``X ⪰ I``, objective
    ``tr X + ‖𝒲‖_F``: ``(ConicLMI, unpack)`` with ``unpack(x) = (X, 𝒲)``.
    Coordinates ``x = (svec X, 𝒲 row by row)``."""
    q0, k = A.shape[0], R.shape[0]
    BX = sym_basis(q0)
    p, nW = BX.shape[0], q0 * k
    E = np.eye(nW).reshape(nW, q0, k)  # 𝒲's unit matrices
    blocks = [(-np.eye(q0), np.concatenate([BX, np.zeros((nW, q0, q0))]))]  # X ⪰ I
    for L, M in parts:
        F = np.concatenate([region_lmi_batch(L, M, BX, BX @ A), region_lmi_batch(L, M, np.zeros((nW, q0, q0)), -E @ R)])
        blocks.append((-margin * np.eye(F.shape[1]), -F))

    def unpack(x):
        return smat(x[:p], q0), x[p:].reshape(q0, k)

    c = np.r_[svec(np.eye(q0)), np.zeros(nW)]
    return ConicLMI(c, tuple(blocks), norm=np.arange(p, p + nW) if nW else None), unpack


def _full_lmi(A, R, region, margin):
    parts = region.parts if isinstance(region, Intersection) else (region,)
    prob, unpack = _gain_kept(A, R, [p.characteristic() for p in parts], margin)

    def gain(x):
        Xv, W = unpack(x)
        return Xv, np.linalg.solve(Xv, W)

    return prob, gain


def epsilon_block_lmi(A, Ceps, region: AbstractRegion, *, margin: float = 1e-3, solver: str = DEFAULT_SOLVER,
                      name: str = "ε-block region LMI"):
    r"""Output injection by the reduced region LMI (module docstring, steps 2 and 3): a gain
    ``K`` with the eigenvalues of ``A - K Ceps`` in `region`, and the certificate.

    **Returns:** ``(K, X, info)``: ``K`` ``(q, rows of Ceps)``, least norm; ``X`` the closed
    loop's certificate (the Stein certificate for a disk, the LMI's ``X`` otherwise); ``info``
    of `fojax.design._region_lmi.solve_with_fallbacks` plus ``formulation`` and ``lmi_size``
    (cone sizes).

    **Raises:** `fojax.errors.LMIInfeasibleError` when the solver shows the LMI infeasible
    (equivalently: a mode of ``(A, Ceps)`` no gain can move lies outside `region`) — for an
    intersection on which the solver stopped short, also when one part alone is shown
    infeasible; `fojax.errors.SolverStoppedShortError` when it stops short or the certificate is
    not finite.
    """
    from ._region_lmi import solve_conic_with_fallbacks
    from ._stein import host_stein_certificate

    A, Ceps = np.asarray(A, dtype=float), np.asarray(Ceps, dtype=float)
    form = formulation(region)
    inner_refused = None
    if form == "inscribed disk":
        inner = inscribed_disk(region)
        try:
            if inner is None:
                raise LMIInfeasibleError(name, "no disk inside the region", {}, HINT)
            K, X, info = epsilon_block_lmi(A, Ceps, inner, margin=margin, solver=solver, name=name)
        except (LMIInfeasibleError, SolverStoppedShortError) as err:  # not a proof: the full form decides
            inner_refused = f"{type(err).__name__} ({err.status}) for the inscribed disk"
        else:
            info.update(formulation=form, inscribed=inner.describe())
            info["notes"].append(f"eigenvalues placed in the inscribed {inner.describe()}")
            return K, X, info
        form = "full"
    R, N, back = epsilon_output(Ceps)
    # step 3 first (min-gain, Clarabel alone under "auto"); step 2 when its solver stops short
    # or its design fails the float64 check (same feasible set: an infeasibility certificate
    # of step 3 is final)
    tries = (True, False) if form in ("disk", "finsler") else (None,)
    notes: list = []
    for staircase in tries:
        if form == "disk":
            prob, gain = _disk_lmi(A, R, N, region, margin, staircase)
        elif form == "finsler":
            prob, gain = _finsler_lmi(A, R, N, region, margin, staircase)
        else:
            prob, gain = _full_lmi(A, R, region, margin)
        if prob is None:  # R has full rank: no constraint is left, X = I (module docstring, step 3)
            x, info = np.zeros(0), {"solver": None, "status": "optimal", "route": "no LMI left (ker R = 0): X = I"}
        else:
            first = bool(staircase)
            try:
                x, info = solve_conic_with_fallbacks(
                    prob, f"{name} ({form} form{', staircase' if first else ''})", HINT,
                    "CLARABEL" if first and check_solver(solver) == "AUTO" else solver,
                    objectives=("min-gain",) if first else None)
            except SolverStoppedShortError as err:
                if first:
                    notes.append(f"staircase form: {err.status}; step 2 form solved")
                    continue
                _part_infeasible(A, Ceps, region, margin, solver, name, err)
                raise
        ok = bool(np.all(np.isfinite(x)))
        if ok:
            try:
                Xv, Kr = gain(x)
            except np.linalg.LinAlgError:  # X not positive definite in float64
                ok = False
        if staircase and prob is not None and not (ok and _holds(A - Kr @ R, Xv, region)):
            notes.append("staircase form: its design failed the float64 check; step 2 form solved")
            continue
        if not ok:
            raise SolverStoppedShortError(f"{name} ({form} form)", "solution_not_positive_definite", info)
        break
    K = Kr @ back
    if form == "disk":
        Xv = host_stein_certificate(A - K @ Ceps, float(region.center), float(region.radius), notes=notes)
    if not np.all(np.isfinite(Xv)):
        raise SolverStoppedShortError(f"{name} ({form} form)", "certificate_not_finite", {"notes": notes})
    if inner_refused:
        notes.append(inner_refused)
    info.update(formulation=form, lmi_size=[] if prob is None else prob.sizes, notes=notes)
    return K, 0.5 * (Xv + Xv.T), info


def _holds(Acl, X, region) -> bool:
    """The float64 check of a staircase design: ``X ≻ 0`` and the region's LMI at ``X`` (a
    disk: the Möbius closed loop's spectral radius below 1, the Stein certificate follows)."""
    if not (np.all(np.isfinite(Acl)) and np.all(np.isfinite(X))):
        return False
    if isinstance(region, Disk):
        Ab = (Acl - float(region.center) * np.eye(Acl.shape[0])) / float(region.radius)
        return bool(np.max(np.abs(np.linalg.eigvals(Ab)), initial=0.0) < 1.0 - 1e-9)
    return bool(np.linalg.eigvalsh(X)[0] > 0 and np.linalg.eigvalsh(region.lmi_matrix(X, X @ Acl))[-1] < 0)


def _part_infeasible(A, Ceps, region, margin, solver, name, err) -> None:
    """Raise `LMIInfeasibleError` if one part of an intersection is shown infeasible alone (its
    LMI is one of the intersection's constraints, with the same certificate): infeasibility of
    the intersection is then shown, where the solver stopped short on the intersection."""
    if not isinstance(region, Intersection):
        return
    for p in region.parts:
        try:
            epsilon_block_lmi(A, Ceps, p, margin=margin, solver=solver, name=name)
        except LMIInfeasibleError as alone:
            raise LMIInfeasibleError(f"{name} ({formulation(region)} form)", f"{err.status}; infeasible for "
                                     f"{p.describe()} alone: {alone.status}", err.info, HINT) from None
        except SolverStoppedShortError:
            continue


def eliminated_gains(s: FunctionalObserverStructure, region: AbstractRegion, *, kind: str,
                     margin: float = 1e-3, solver: str = DEFAULT_SOLVER):
    """Gains of one rule from the reduced region LMI (module docstring).

    **Returns:** ``(X, Z, [𝕐], info)`` like `fojax.design._region_lmi.solve_gains`; ``info["lmi"]``
    has the ``route`` line, the ``formulation`` and the cone sizes (``lmi_size``).

    **Raises:** as `epsilon_block_lmi` (`fojax.errors.LMIInfeasibleError` only when the solver
    shows the reduced LMI infeasible, i.e. no gain of the kind places the error eigenvalues in
    `region`).
    """
    if s.num_rules != 1:
        raise ValueError("eliminated_gains designs one rule; use solve_gains for rules")
    pc = pieces(s, xp=np)
    N1, N2, N3 = np.asarray(pc.N1)[0], np.asarray(pc.N2)[0], np.asarray(pc.N3)
    q0, q1 = s.q0, (0 if kind == "proportional" else s.q1)
    nZ, c, d = N2.shape[0], N3.shape[0], q0 + q1
    Ceps = np.vstack([N2, N3])
    K, Xeps, info = epsilon_block_lmi(N1, Ceps, region, margin=margin, solver=solver,
                                      name=f"{kind} observer, ε-block region LMI")
    Z, Y1 = K[:, :nZ], K[:, nZ:]
    Aeps = N1 - K @ Ceps
    Y = np.zeros((d, c + q1))
    Y[:q0, :c] = Y1
    X = np.zeros((d, d))
    X[:q0, :q0] = Xeps
    if q1:
        # the real part of the ε-block's best-placed eigenvalue (inside: the regions are
        # convex and symmetric about the real axis)
        cands = np.real(np.linalg.eigvals(Aeps))
        g = float(cands[np.argmax(region.margin(cands.astype(complex)))])
        Y[q0:, c:] = g * np.eye(q1)  # G = g I
        X[q0:, q0:] = np.eye(q1)
        kappa = _couple(Y, X, Aeps, N3, region, q0, c, kind)
        info["notes"].append(f"G = {g:.6g}·I; coupling κ = {kappa:.3g} "
                             f"({'J, Y2' if kind == 'generalized' else 'J'})")
    form, sizes = info["formulation"], "+".join(map(str, info["lmi_size"]))
    how = "gain kept" if form == "full" else "gain eliminated"
    label = f"disk form for the inscribed {info['inscribed']}" if form == "inscribed disk" else f"{form} form"
    info["route"] = (f"{info['route']}; reduced to the ε-block of order {q0}, {how} "
                     f"({label}, cones of size {sizes}; the full LMI's cone is {_full_cone(region, d)})")
    return X, Z, [Y], {"lmi": info}


def _full_cone(region, d) -> int:
    return region.characteristic()[0].shape[0] * d


def _couple(Y, X, Aeps, N3, region, q0, c, kind) -> float:
    """Set ``J = κΠ`` (and ``Y2 = κΠᵀY1/‖Y1‖`` for a generalized observer) in `Y` in place,
    with κ from the room the decoupled region LMI leaves at `X` (module docstring)."""
    d = X.shape[0]
    q1 = d - q0
    Pi = np.eye(q0, q1)
    Y1 = Y[:q0, :c]
    nY1 = float(np.linalg.norm(Y1, 2)) if Y1.size else 0.0
    Y2 = Pi.T @ Y1 / nY1 if kind == "generalized" and nY1 > 0 else np.zeros((q1, c))
    A0 = np.zeros((d, d))
    A0[:q0, :q0] = Aeps
    A0[q0:, q0:] = Y[q0:, c:]
    D = np.zeros((d, d))
    D[:q0, q0:] = Pi
    D[q0:, :q0] = -Y2 @ N3
    lam = -float(np.linalg.eigvalsh(region.lmi_matrix(X, X @ A0))[-1])
    bound = 2.0 * float(np.linalg.norm(region.characteristic()[1], 2)) * float(np.linalg.norm(X @ D, 2))
    kappa = COUPLING_SHARE * lam / bound if lam > 0 and bound > 0 and np.isfinite(bound) else 0.0
    Y[:q0, c:] = kappa * Pi
    Y[q0:, :c] = kappa * Y2
    return kappa
